import pytest
import torch
from torchrl.objectives.value.functional import generalized_advantage_estimate

from trainers.ppo.advantages import generalized_advantages, reverse_linear_scan


def _sequential_scan(inputs: torch.Tensor, coefficients: torch.Tensor) -> torch.Tensor:
    """y_t = inputs_t + coefficients_t * y_{t+1} over the last dim, one step at a time."""
    out, carry = torch.empty_like(inputs), torch.zeros_like(inputs[..., 0])
    for t in reversed(range(inputs.shape[-1])):
        carry = out[..., t] = inputs[..., t] + coefficients[..., t] * carry
    return out


@pytest.mark.parametrize("steps", [1, 2, 3, 7, 8, 64, 129])
def test_the_scan_is_the_recurrence_at_every_length(steps):
    generator = torch.Generator().manual_seed(steps)
    inputs = torch.randn(5, steps, generator=generator, dtype=torch.float64)
    coefficients = torch.rand(5, steps, generator=generator, dtype=torch.float64)
    coefficients[coefficients < 0.2] = 0  # cuts, as an episode's end makes them
    scanned = reverse_linear_scan(inputs, coefficients, dim=-1)
    torch.testing.assert_close(scanned, _sequential_scan(inputs, coefficients), rtol=1e-12, atol=1e-12)


def test_the_scan_runs_along_any_dim():
    inputs, coefficients = torch.randn(3, 10, 4, dtype=torch.float64), torch.rand(3, 10, 4, dtype=torch.float64)
    along_time = reverse_linear_scan(inputs, coefficients, dim=1)
    moved = _sequential_scan(inputs.transpose(1, 2), coefficients.transpose(1, 2)).transpose(1, 2)
    torch.testing.assert_close(along_time, moved, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("ends", ["mid-batch", "at the batch end", "none"])
def test_gae_equals_torchrl_with_episodes_ending_anywhere(ends):
    """Batches laid out as the trainer's: [B, T, 2 agents, 1], done shared by the agents; episodes of random length
    end mid-batch, or exactly at the batch end, or not at all."""
    generator = torch.Generator().manual_seed(0)
    batch, steps = 6, 256
    value = torch.randn(batch, steps, 2, 1, generator=generator)
    next_value = torch.randn(batch, steps, 2, 1, generator=generator)
    reward = torch.randn(batch, steps, 2, 1, generator=generator)
    done = torch.zeros(batch, steps, 1, 1, dtype=torch.bool)
    if ends == "mid-batch":
        done = torch.rand(batch, steps, 1, 1, generator=generator) < 0.02
        done[0, 100] = True
    elif ends == "at the batch end":
        done[:, -1] = True
    done = done.expand(batch, steps, 2, 1)
    terminated = done & (torch.rand(batch, steps, 2, 1, generator=generator) < 0.5)

    ours = generalized_advantages(0.99, 0.95, value, next_value, reward, done, terminated, time_dim=1)
    theirs = generalized_advantage_estimate(0.99, 0.95, value.transpose(1, 2), next_value.transpose(1, 2),
                                            reward.transpose(1, 2), done.transpose(1, 2), terminated.transpose(1, 2),
                                            time_dim=-2)
    for mine, reference in zip(ours, theirs):
        torch.testing.assert_close(mine, reference.transpose(1, 2), rtol=1e-5, atol=1e-5)

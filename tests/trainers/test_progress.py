"""The training progress bar: the recent episodes' mean deliveries, read from the device only when shown."""

from types import SimpleNamespace

import torch
from device_audit import DeviceAudit
from tensordict import TensorDict

from trainers.config import TrainConfig
from trainers.ppo.loop import Progress


def batch_with_episodes(deliveries: list[list[float]], done: list[list[bool]]) -> TensorDict:
    """A collector's batch [B, T] whose episodes end where `done` says, with those deliveries."""
    shape = torch.Size([len(done), len(done[0])])
    return TensorDict({"next": {"done": torch.tensor(done).unsqueeze(-1),
                                "episode_deliveries": torch.tensor(deliveries).unsqueeze(-1)}}, batch_size=shape)


def progress(shown: bool) -> Progress:
    team = SimpleNamespace(config=TrainConfig(progress=shown, total_steps=1024), env_steps=0)
    return Progress([team])


def test_the_bar_shows_the_mean_deliveries_of_the_episodes_that_ended_in_the_recent_batches():
    bar = progress(shown=True)
    bar.update(batch_with_episodes([[0, 3], [9, 5]], [[False, True], [False, True]]), 100.0)  # 3 and 5
    bar.update(batch_with_episodes([[2, 0], [0, 0]], [[True, False], [False, False]]), 100.0)  # 2
    assert bar.bar.postfix.startswith("deliveries=3.33")
    assert bar.bar.n == 8
    for _ in range(Progress.RECENT_UPDATES):  # the first batches' episodes fall out of the window
        bar.update(batch_with_episodes([[1, 1], [1, 1]], [[False, True], [False, True]]), 100.0)
    assert bar.bar.postfix.startswith("deliveries=1.00")
    bar.close()


def test_a_hidden_bar_reads_nothing_from_the_device():
    bar = progress(shown=False)
    with DeviceAudit() as audit:
        bar.update(batch_with_episodes([[0, 3]], [[False, True]]), 100.0)
    assert not audit.host_reads, audit.report()

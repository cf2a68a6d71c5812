import copy
import io

import pytest
import torch
from tensordict import TensorDict
from tiny import compiled_with_operator, infinite_observations
from torch import nn

from torch_kitchen import sparse_linear
from torch_kitchen.cpu_kernels import accelerate_cpu
from torch_kitchen.models import make_actor_critic
from torch_kitchen.models.networks import make_encoder
from torch_kitchen.sparse_linear import ObservationLinear, SparseInputLinear

HIDDEN = 32


@pytest.fixture(scope="module")
def observations() -> torch.Tensor:
    """Real Infinite Kitchen observations, uint8 [64, 2, 7, 7, 26], a few steps into their episodes."""
    return infinite_observations(64, seed=0)


def _pair(in_features: int, out_features: int = HIDDEN) -> tuple[nn.Linear, SparseInputLinear]:
    torch.manual_seed(0)
    dense = nn.Linear(in_features, out_features)
    sparse = SparseInputLinear(in_features, out_features)
    sparse.load_state_dict(dense.state_dict())
    return dense, sparse


def test_observations_are_mostly_zero(observations):
    # What the layer is for; if the observation became dense, the layer would be the wrong tool.
    assert 0 < (observations != 0).float().mean() < 0.05


def test_forward_and_gradients_equal_a_dense_linear_to_rounding(observations):
    x = observations.reshape(128, -1)
    dense, sparse = _pair(x.shape[1])
    grad_out = torch.randn(128, HIDDEN)
    dense(x.float()).backward(grad_out)
    out = sparse(x)  # uint8 read as it is
    out.backward(grad_out)
    torch.testing.assert_close(out, dense(x.float()))
    torch.testing.assert_close(sparse.weight.grad, dense.weight.grad)
    torch.testing.assert_close(sparse.bias.grad, dense.bias.grad)
    # The weights of inputs that are zero everywhere in the batch get no gradient at all.
    unused = (x != 0).sum(0) == 0
    assert unused.any() and (sparse.weight.grad[:, unused] == 0).all()


def test_an_input_that_needs_its_gradient_gets_it():
    dense, sparse = _pair(10, 4)
    x = torch.zeros(6, 10)
    x[::2, 3], x[1, 7], x[5, 0] = 1.0, -2.5, 0.5
    x_dense, x_sparse = x.clone().requires_grad_(), x.clone().requires_grad_()
    (dense(x_dense) ** 2).sum().backward()
    (sparse(x_sparse) ** 2).sum().backward()
    torch.testing.assert_close(x_sparse.grad, x_dense.grad)
    torch.testing.assert_close(sparse.weight.grad, dense.weight.grad)


def test_all_zero_rows_and_leading_dims(observations):
    x = observations[:4].clone()
    x[1] = 0  # an all-zero observation (E3T's context padding) gives the bias alone
    dense, sparse = _pair(7 * 7 * 26)
    out = sparse(x.flatten(-3))
    assert out.shape == (4, 2, HIDDEN)
    torch.testing.assert_close(out, dense(x.flatten(-3).float()))
    torch.testing.assert_close(out[1], dense.bias.detach().expand(2, HIDDEN))


def test_it_is_a_linear_layer_to_checkpoints():
    dense, sparse = _pair(12)
    assert isinstance(sparse, nn.Linear)
    assert sparse.state_dict().keys() == dense.state_dict().keys()
    torch.testing.assert_close(sparse.state_dict(), dense.state_dict(), rtol=0, atol=0)
    buffer = io.BytesIO()
    torch.save(sparse.state_dict(), buffer)
    buffer.seek(0)
    plain = nn.Linear(12, HIDDEN)
    plain.load_state_dict(torch.load(buffer))
    torch.testing.assert_close(plain.state_dict(), dense.state_dict(), rtol=0, atol=0)


def test_its_weight_is_stored_column_by_column_through_loads_copies_and_moves(observations):
    # The forward reads weight.T's rows; stored so, they need no copy, and the weight's gradient fits it as it is.
    dense, sparse = _pair(7 * 7 * 26)  # loaded from a plain layer's state_dict
    for layer in (sparse, copy.deepcopy(sparse), sparse.to(torch.float32)):
        assert layer.weight.shape == (HIDDEN, 7 * 7 * 26) and layer.weight.t().is_contiguous()
    sparse(observations.flatten(-3)).sum().backward()
    assert sparse.weight.grad.stride() == sparse.weight.stride()


def test_compiled_graphs_use_the_dense_product(observations):
    _, sparse = _pair(7 * 7 * 26)
    x = observations.flatten(-3)
    compiled = torch.compile(sparse, fullgraph=True)  # nonzero inside would break the graph
    torch.testing.assert_close(compiled(x), sparse(x))


def _critic_values(critic, observations: torch.Tensor) -> torch.Tensor:
    td = TensorDict({("agents", "observation"): observations}, batch_size=observations.shape[:1])
    return critic(td)["agents", "state_value"]


def test_a_shared_mlp_reads_uint8_observations_through_it(observations, monkeypatch):
    assert type(make_encoder("mlp", (7, 7, 26), HIDDEN)[1]) is ObservationLinear  # plain until accelerated
    critic = make_actor_critic("mlp", hidden=HIDDEN, share_params=True).critic
    accelerate_cpu(critic)
    encoder = critic.module[0].module.shared_net()
    assert isinstance(encoder[1], SparseInputLinear) and encoder[1].weight.t().is_contiguous()
    values = _critic_values(critic, observations[:8])
    values.sum().backward()
    grads = [p.grad.clone() for p in critic.parameters()]
    # The reference: the first layer as the dense product.
    monkeypatch.setattr(sparse_linear, "plain_linear_here", lambda x, weight, **_: True)
    critic.zero_grad()
    expected = _critic_values(critic, observations[:8])
    expected.sum().backward()
    torch.testing.assert_close(values, expected)
    for grad, parameter in zip(grads, critic.parameters()):
        torch.testing.assert_close(grad, parameter.grad)


def test_per_agent_networks_take_the_dense_product_and_agree_with_the_sparse_one(observations):
    # Separate networks per agent run under TorchRL's vmap, where `nonzero` has no batched form; agent i's values
    # equal those of a shared network holding agent i's weights, which takes the sparse product.
    separate = make_actor_critic("mlp", hidden=HIDDEN, share_params=False).critic
    accelerate_cpu(separate)
    values = _critic_values(separate, observations[:8])
    for agent in range(2):
        shared = make_actor_critic("mlp", hidden=HIDDEN, share_params=True).critic
        accelerate_cpu(shared)
        shared.load_state_dict({key: value[agent] for key, value in separate.state_dict().items()})
        torch.testing.assert_close(_critic_values(shared, observations[:8])[:, agent], values[:, agent])


def test_the_actor_and_the_critic_find_the_entries_of_one_minibatch_once(observations):
    x = observations.reshape(128, -1)
    first = sparse_linear.nonzero_entries(x, torch.float32)
    # Another view of the same data (each network flattens its input anew) finds them cached ...
    assert sparse_linear.nonzero_entries(x.view(128, -1), torch.float32) is first
    # ... a copy, another dtype, or the same tensor changed in place do not.
    assert sparse_linear.nonzero_entries(x.clone(), torch.float32) is not first
    assert sparse_linear.nonzero_entries(x, torch.float64) is not first
    changed = x.clone()
    before = sparse_linear.nonzero_entries(changed, torch.float32)
    changed[0].zero_()
    after = sparse_linear.nonzero_entries(changed, torch.float32)
    assert after is not before and (after.rows != 0).all()


def test_a_layer_after_its_input_changed_in_place_computes_the_new_product(observations):
    dense, sparse = _pair(7 * 7 * 26)
    x = observations.reshape(128, -1).clone()
    sparse(x)
    x[:10] = 0
    x[10:20, :5] = 3
    torch.testing.assert_close(sparse(x), dense(x.float()))


def test_teams_learning_on_threads_keep_their_own_entries(observations):
    import threading

    x = observations.reshape(128, -1)
    _, sparse = _pair(7 * 7 * 26)
    expected = sparse(x).detach()
    results, errors = {}, []

    def run(name, data):
        try:
            for _ in range(20):
                results[name] = sparse(data).detach()
        except Exception as error:  # pragma: no cover - reported below
            errors.append(error)

    flipped = x.flip(0).contiguous()
    threads = [threading.Thread(target=run, args=("a", x)), threading.Thread(target=run, args=("b", flipped))]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    torch.testing.assert_close(results["a"], expected)
    torch.testing.assert_close(results["b"], expected.flip(0))


def test_the_sparse_product_as_a_graphs_operator_is_registered_whole_and_equals_a_dense_linear(observations):
    """`sparse_input_linear`, what a compiled graph calls for the layer: torch's checks of its schema, fake tensor
    and autograd registration pass, and its output and gradients are a dense linear's to rounding."""
    x = observations.reshape(128, -1)
    dense, sparse = _pair(x.shape[1])
    torch.library.opcheck(sparse_linear.sparse_input_linear, (x, sparse.weight, sparse.bias))
    out = sparse_linear.sparse_input_linear(x, sparse.weight, sparse.bias)
    expected = dense(x.float())
    torch.testing.assert_close(out, expected)
    grad_out = torch.randn_like(out)
    out.backward(grad_out)
    expected.backward(grad_out)
    torch.testing.assert_close(sparse.weight.grad, dense.weight.grad)
    torch.testing.assert_close(sparse.bias.grad, dense.bias.grad)


def test_a_compiled_graph_calls_the_sparse_product_and_computes_what_the_eager_layer_does(observations):
    x = observations.reshape(128, -1)
    _, sparse = _pair(x.shape[1])
    grad_out = torch.randn(128, HIDDEN)
    eager = sparse(x)
    eager.backward(grad_out)
    eager_grad = sparse.weight.grad.clone()
    sparse.zero_grad()
    compiled = compiled_with_operator(sparse, x, "sparse_input_linear", grad_out)
    torch.testing.assert_close(compiled, eager)
    torch.testing.assert_close(sparse.weight.grad, eager_grad)
    # An input that needs its gradient gets it inside a graph too.
    floats = x[:8].float().requires_grad_()
    torch.compile(sparse, fullgraph=True)(floats).sum().backward()
    torch.testing.assert_close(floats.grad, sparse.weight.sum(0).expand(8, -1))


@pytest.mark.parametrize("dtype", [torch.uint8, torch.float32, torch.int16])
def test_the_search_by_words_finds_what_nonzero_finds(observations, dtype, monkeypatch):
    monkeypatch.setattr(sparse_linear, "WORD_SEARCH_MIN", 0)
    flat = observations.reshape(-1).to(dtype)
    if dtype.is_floating_point:
        flat[::7] = -0.0  # zero, though its bits are not
    for tensor in (flat, flat[:-3], flat[::2]):  # a whole number of words, not, and not contiguous
        assert torch.equal(sparse_linear.flat_nonzero(tensor), tensor.nonzero().squeeze(1))


def test_the_stable_order_of_narrowed_keys_is_argsorts():
    keys = torch.randint(0, 40_000, (5_000,), generator=torch.Generator().manual_seed(0))
    for bound in (40_000, 1 << 20, 1 << 40):
        assert torch.equal(sparse_linear.stable_order(keys, bound), torch.argsort(keys, stable=True))

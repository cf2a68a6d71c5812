import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.collectors import Collector
from torchrl.envs.utils import RandomPolicy, check_env_specs

from jax_env import State, load_layout
from jax_env.state import make_state
from torch_kitchen.env import AgentDones, KitchenEnv


def _numpy_states(states):
    return [np.array(leaf) for leaf in jax.tree_util.tree_leaves(states)]


@pytest.mark.parametrize("levels", ["cramped_room_7x7", "infinite", ["forced_coord_7x7", "coord_ring_7x7"]])
def test_specs_hold(levels):
    env = KitchenEnv(num_envs=4, levels=levels, max_steps=10)
    check_env_specs(env)
    assert env.observation_spec["agents", "observation"].shape == (4, 2, 7, 7, 26)
    assert env.full_action_spec["agents", "action"].shape == (4, 2)


def test_native_layout_has_its_own_shape():
    env = KitchenEnv(num_envs=3, levels="cramped_room", max_steps=10)
    check_env_specs(env)
    assert env.reset()["agents", "observation"].shape == (3, 2, 4, 5, 26)


def test_torchrl_rollout_equals_the_raw_jax_stepper():
    num_envs, steps, seed = 6, 30, 3
    env = KitchenEnv(num_envs=num_envs, levels="infinite", max_steps=100, seed=seed)
    td = env.reset()
    # The first reset draws its levels from the second half of split(PRNGKey(seed)).
    _, key = jax.random.split(jax.random.PRNGKey(seed))
    obs, states = env.jax_env.reset_batch(key, num_envs)
    np.testing.assert_array_equal(td["agents", "observation"].numpy(), np.asarray(obs))

    actions = torch.randint(0, 6, (steps, num_envs, 2), generator=torch.Generator().manual_seed(0))
    step = jax.jit(jax.vmap(env.jax_env.step_env))
    delivered = np.zeros(num_envs)
    for t in range(steps):
        td["agents", "action"] = actions[t]
        out = env.step(td)["next"]
        states, reward, done, info = step(states, jnp.asarray(actions[t].numpy(), jnp.int32))
        np.testing.assert_array_equal(
            out["agents", "observation"].numpy(), np.asarray(jax.vmap(env.jax_env.get_obs)(states))
        )
        np.testing.assert_array_equal(out["agents", "reward"].numpy()[..., 0], np.asarray(reward))
        np.testing.assert_array_equal(out["agents", "shaped_reward"].numpy()[..., 0], np.asarray(info["shaped_reward"]))
        np.testing.assert_array_equal(out["done"].numpy()[:, 0], np.asarray(done))
        delivered += np.asarray(reward)[:, 0] / 20
        np.testing.assert_array_equal(out["episode_deliveries"].numpy()[:, 0], delivered)
        td = out.clone()
    for ours, raw in zip(_numpy_states(env.states), _numpy_states(states)):
        np.testing.assert_array_equal(ours, raw)


def test_same_seed_same_rollout_and_rollouts_reset_finished_episodes():
    def run(seed):
        env = KitchenEnv(num_envs=4, levels="infinite", max_steps=8, seed=seed)
        torch.manual_seed(0)
        return env.rollout(20, break_when_any_done=False)

    a, b, c = run(1), run(1), run(2)
    assert (a["agents", "observation"] == b["agents", "observation"]).all()
    assert not (a["agents", "observation"] == c["agents", "observation"]).all()
    assert a["next", "done"].sum() == 4 * 2
    # After each done step the next step starts a fresh episode (step counter back to the start).
    urgency = a["agents", "observation"][..., 25].flatten(2).amax(-1)  # [B, T, ...]
    assert urgency.any()


def test_partial_reset_resets_exactly_the_masked_kitchens():
    env = KitchenEnv(num_envs=8, levels="infinite", max_steps=50)
    td = env.reset()
    for _ in range(3):
        td["agents", "action"] = torch.randint(0, 6, (8, 2))
        td = env.step(td)["next"].clone()
    before = _numpy_states(env.states)
    mask = torch.tensor([True, False, False, True, False, False, False, True]).unsqueeze(-1)
    previous_obs = td["agents", "observation"].clone()
    td.set("_reset", mask)  # as a collector does: the last step's data plus the mask
    out = env.reset(td)
    after = _numpy_states(env.states)
    steps = np.asarray(env.states.step)
    assert (steps[mask[:, 0].numpy()] == 0).all() and (steps[~mask[:, 0].numpy()] == 3).all()
    keep = ~mask[:, 0].numpy()
    for old, new in zip(before, after):
        np.testing.assert_array_equal(old[keep], new[keep])
    np.testing.assert_array_equal(out["agents", "observation"][keep].numpy(), previous_obs[keep].numpy())
    fresh_obs = jax.vmap(env.jax_env.get_obs)(env.states)
    np.testing.assert_array_equal(out["agents", "observation"].numpy(), np.asarray(fresh_obs))
    assert (out["episode_deliveries"][mask[:, 0]] == 0).all()


def test_observations_are_zero_copy_and_torchrl_writes_cannot_corrupt_the_state():
    env = KitchenEnv(num_envs=4, levels="cramped_room_7x7", max_steps=50, seed=5)
    twin = KitchenEnv(num_envs=4, levels="cramped_room_7x7", max_steps=50, seed=5)
    td, twin_td = env.reset(), twin.reset()
    assert td["agents", "observation"].data_ptr() == env._last_obs.unsafe_buffer_pointer()
    state_pointers = {leaf.unsafe_buffer_pointer() for leaf in jax.tree_util.tree_leaves(env.states)}
    for value in td.values(include_nested=True, leaves_only=True):
        assert value.data_ptr() not in state_pointers

    actions = torch.randint(0, 6, (10, 4, 2), generator=torch.Generator().manual_seed(1))
    for t in range(10):
        td["agents", "action"], twin_td["agents", "action"] = actions[t], actions[t].clone()
        out, twin_out = env.step(td)["next"], twin.step(twin_td)["next"]
        np.testing.assert_array_equal(out["agents", "observation"].numpy(), twin_out["agents", "observation"].numpy())
        for value in out.values(include_nested=True, leaves_only=True):
            value.fill_(1)  # TorchRL writes into tensors it is given; the env must not care
        td, twin_td = out, twin_out.clone()
    for ours, theirs in zip(_numpy_states(env.states), _numpy_states(twin.states)):
        np.testing.assert_array_equal(ours, theirs)


def test_collector_with_a_random_policy():
    env = KitchenEnv(num_envs=4, levels="infinite", max_steps=16)
    collector = Collector(env, RandomPolicy(env.full_action_spec), frames_per_batch=4 * 32, total_frames=4 * 64)
    batches = list(collector)
    collector.shutdown()
    assert len(batches) == 2
    batch = batches[0]
    assert batch["agents", "observation"].shape == (4, 32, 2, 7, 7, 26)
    assert batch["next", "done"].sum() == 4 * 2


def test_cuda_without_a_gpu_jax_says_what_to_install():
    if jax.default_backend() == "gpu":
        pytest.skip("this JAX has a GPU")
    with pytest.raises(RuntimeError, match=r"jax\[cuda12\]"):
        KitchenEnv(num_envs=2, levels="cramped_room_7x7", device="cuda")


def _through_a_file(state_dict, tmp_path):
    """The state dict as a checkpoint holds it: saved, and read back with torch's weights-only unpickler."""
    torch.save(state_dict, tmp_path / "env.pt")
    return torch.load(tmp_path / "env.pt", weights_only=True)


def test_state_dict_restores_the_kitchens_mid_episode(tmp_path):
    actions = torch.randint(0, 6, (12, 5, 2), generator=torch.Generator().manual_seed(1))
    env = KitchenEnv(num_envs=5, levels="infinite", max_steps=8, seed=4)
    td = env.reset()
    for t in range(6):
        _, td = env.step_and_maybe_reset(td.set(("agents", "action"), actions[t]))
    saved = _through_a_file(env.state_dict(), tmp_path)
    twin = KitchenEnv(num_envs=5, levels="infinite", max_steps=8, seed=99)
    twin.load_state_dict(saved)
    for restored, original in zip(jax.tree_util.tree_leaves(twin.states), jax.tree_util.tree_leaves(env.states)):
        assert restored.dtype == original.dtype
        np.testing.assert_array_equal(np.asarray(restored), np.asarray(original))
    twin_td = twin.reset()  # hands out the restored kitchens, not new ones
    np.testing.assert_array_equal(twin_td["agents", "observation"].numpy(), td["agents", "observation"].numpy())
    np.testing.assert_array_equal(twin_td["episode_deliveries"].numpy(), td["episode_deliveries"].numpy())
    # The same actions from here give the same steps, across the episode ends and resets at step 8.
    for t in range(6, 12):
        _, td = env.step_and_maybe_reset(td.set(("agents", "action"), actions[t]))
        _, twin_td = twin.step_and_maybe_reset(twin_td.set(("agents", "action"), actions[t]))
        np.testing.assert_array_equal(twin_td["agents", "observation"].numpy(), td["agents", "observation"].numpy())
    # A later reset draws new kitchens again.
    assert not np.array_equal(twin.reset()["agents", "observation"].numpy(), td["agents", "observation"].numpy())


def test_state_dict_of_another_batch_is_refused():
    saved = KitchenEnv(num_envs=3, levels="infinite").state_dict()
    with pytest.raises(ValueError, match="num_envs and levels"):
        KitchenEnv(num_envs=4, levels="infinite").load_state_dict(saved)


def test_the_env_state_is_tensors_named_by_the_state_fields():
    env = KitchenEnv(num_envs=3, levels="infinite", max_steps=8)
    state = env.get_extra_state()
    assert set(state) == {"key", "states", "deliveries"}
    assert list(state["states"]) == [field.name for field in dataclasses.fields(State)]
    for name, tensor in state["states"].items():
        assert tensor.device.type == "cpu"
        assert tensor.numpy().dtype == getattr(env.states, name).dtype
    assert state["deliveries"].dtype == torch.int32 and state["deliveries"].shape == (3,)


def test_the_jax_key_round_trips_bit_for_bit(tmp_path):
    # Values with the top bit set, which a signed 32-bit store would mangle.
    key = jnp.asarray([[0xFFFFFFFF, 0x80000001]], dtype=jnp.uint32)  # [teams, 2]
    env = KitchenEnv(num_envs=2, levels="infinite", max_steps=8)
    env.reset()
    env._key = key
    twin = KitchenEnv(num_envs=2, levels="infinite", max_steps=8, seed=5)
    twin.load_state_dict(_through_a_file(env.state_dict(), tmp_path))
    assert twin._key.dtype == jnp.uint32
    np.testing.assert_array_equal(np.asarray(twin._key), np.asarray(key))
    twin.reset()  # hands out the restored kitchens; from here on the key decides
    observation = ("agents", "observation")
    np.testing.assert_array_equal(twin.reset()[observation].numpy(), env.reset()[observation].numpy())


def test_compile_step_compiles_without_stepping_the_kitchens():
    env = KitchenEnv(2, levels="cramped_room_7x7", seed=1)
    env.precompile()  # resets first
    before = jax.tree_util.tree_map(np.asarray, env.states)
    env.precompile()
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(before),
                                                     jax.tree_util.tree_leaves(env.states)))
    fresh = KitchenEnv(2, levels="cramped_room_7x7", seed=1)
    fresh.reset()
    actions = torch.tensor([[0, 5], [3, 4]])
    stepped = [e.step(TensorDict({"agents": {"action": actions}}, batch_size=[2]))["next", "agents", "observation"]
               for e in (env, fresh)]
    assert torch.equal(stepped[0], stepped[1])
    # The step it compiled is the one the real steps use: no second compilation (a game's first tick would pay it).
    assert env._programs.step._cache_size() == 1


def test_kitchens_of_one_size_share_one_compilation_and_keep_their_own_levels():
    """A server starts each game on a new env: kitchens that differ only in their levels reuse the first one's
    compiled reset and step (no compilation when a game starts), and each still plays its own layout."""
    first = KitchenEnv(1, levels="cramped_room_7x7", max_steps=37, seed=3)
    first.precompile()
    second = KitchenEnv(1, levels="coord_ring_7x7", max_steps=37, seed=3)
    assert second._programs is first._programs
    second.precompile()
    actions = TensorDict({"agents": {"action": torch.tensor([[1, 2]])}}, batch_size=[1])
    for env in (first, second):
        env.step(actions.clone())
    programs = first._programs
    assert programs.step._cache_size() == 1 and programs.reset_all._cache_size() == 1
    for env, name in ((first, "cramped_room_7x7"), (second, "coord_ring_7x7")):
        assert np.array_equal(np.asarray(env.states.grid[0]), np.asarray(make_state(load_layout(name)).grid))
    # Other settings are another program.
    assert KitchenEnv(1, levels="cramped_room_7x7", max_steps=38)._programs is not programs


def test_the_host_knows_when_episodes_end_without_reading_done_from_the_device():
    """`any_done` answers from the host's step counts, which follow the kitchens' own through full and partial
    resets; a step and its reset then make the host wait for nothing."""
    from op_audit import OpAudit

    env = KitchenEnv(num_envs=4, levels="infinite", max_steps=5)
    td = env.reset()
    ends = {kitchen: [] for kitchen in range(4)}
    for step in range(17):
        td["agents", "action"] = torch.randint(0, 6, (4, 2))
        if step == 7:  # a partial reset of two kitchens mid-episode moves their episodes' ends
            td.set("_reset", torch.tensor([True, False, True, False]).unsqueeze(-1))
            td = env.reset(td)
            td["agents", "action"] = torch.randint(0, 6, (4, 2))
        with OpAudit() as audit:
            stepped, td = env.step_and_maybe_reset(td)
        done = stepped["next", "done"][:, 0]
        np.testing.assert_array_equal(env._episode_steps, np.asarray(env.states.step))
        for kitchen in done.nonzero()[:, 0].tolist():
            ends[kitchen].append(step)
        if done.any():
            assert (np.asarray(env.states.step)[done.numpy()] == 0).all()  # reset by the same call
        else:
            assert audit.syncs == 0, audit.summary()
    # Kitchens 0 and 2 restarted their second episode at step 7, which moved its end from step 9 to 11.
    assert ends == {0: [4, 11, 16], 1: [4, 9, 14], 2: [4, 11, 16], 3: [4, 9, 14]}


@pytest.mark.parametrize("architecture", ["mlp_lstm", "e3t_mlp"])
def test_with_the_models_transforms_a_step_still_waits_for_nothing(architecture):
    """Recurrent and E3T models put transforms on the env (episode starts, LSTM states, the partner context); the
    episode ends still come from the host, and the transforms read nothing back either."""
    from op_audit import OpAudit

    from torch_kitchen.env import with_transforms
    from torch_kitchen.models import make_actor_critic

    kitchen = KitchenEnv(num_envs=4, levels="infinite", max_steps=3)
    env = with_transforms(kitchen, make_actor_critic(architecture, hidden=8).env_transforms())
    td = env.reset()
    syncs, ends = [], 0
    for _ in range(7):
        td["agents", "action"] = torch.randint(0, 6, (4, 2))
        with OpAudit() as audit:
            stepped, td = env.step_and_maybe_reset(td)
        ended = bool(stepped["next", "done"].any())
        ends += ended
        if not ended:
            syncs.append(audit.syncs)
    assert ends == 2 and syncs == [0] * 5


def test_packed_outputs_as_a_gpu_crosses_them_hold_what_the_three_arrays_hold():
    """On a GPU a step's outputs cross DLPack as one packed buffer (`pack_outputs`): forced on the CPU here, the
    env hands out the same observations, rewards, deliveries and dones as from the three arrays the CPU uses."""
    from torch_kitchen.env import kitchen_programs

    plain = KitchenEnv(num_envs=6, levels="infinite", max_steps=7, seed=2)
    packed = KitchenEnv(num_envs=6, levels="infinite", max_steps=7, seed=2)
    packed._packed, packed._programs = True, kitchen_programs(packed.jax_env, 6, 1, False, packed=True)
    assert packed._programs is not plain._programs
    actions = torch.randint(0, 6, (12, 6, 2), generator=torch.Generator().manual_seed(3))
    ours, theirs = packed.reset(), plain.reset()
    for t in range(12):
        assert set(ours.keys(True, True)) == set(theirs.keys(True, True))
        for key in theirs.keys(True, True):
            assert torch.equal(ours[key], theirs[key]), (t, key)
        ours["agents", "action"], theirs["agents", "action"] = actions[t], actions[t]
        ours, theirs = packed.step_and_maybe_reset(ours)[1], plain.step_and_maybe_reset(theirs)[1]


def test_agent_dones_put_each_kitchens_flags_beside_each_agents_reward():
    env = KitchenEnv(num_envs=3, levels="cramped_room_7x7", max_steps=4, seed=0).append_transform(AgentDones())
    check_env_specs(env)
    rollout = env.rollout(6, break_when_any_done=False)  # an episode ends at step 4, the next one starts
    for flag in ("done", "terminated", "truncated"):
        per_agent, kitchen = rollout["next", "agents", flag], rollout["next", flag]
        assert per_agent.shape == rollout["next", "agents", "reward"].shape == (3, 6, 2, 1)
        assert torch.equal(per_agent, kitchen.unsqueeze(-2).expand(3, 6, 2, 1))
    assert rollout["next", "agents", "done"][:, 3].all() and not rollout["next", "agents", "done"][:, :3].any()

"""Several teams in one process: each team gets exactly what a run of its own with its seed gets."""

import dataclasses
import threading
import time

import pytest
import torch
from test_ppo import MAIN_CONFIG, read_metrics, tiny_config
from tiny import TINY

from torch_kitchen.env import KitchenEnv
from torch_kitchen.onednn_linear import OneDNNProduct
from torch_kitchen.teams import RandomStream
from trainers.checkpoint import load_checkpoint
from trainers.config import ConfigError
from trainers.ppo.loop import train, train_teams
from trainers.ppo.runtime import ShardPool, TeamPool, learning_pool
from trainers.ppo.team import team_configs
from trainers.train_command import main


def assert_same_run(team_run, single_run):
    """Weights, optimizer, kitchens, counters, torch's random stream and every logged metric but the timings, bit
    for bit. (Python's and NumPy's global generators, which training does not draw from, are the process's.)"""
    team, single = load_checkpoint(team_run), load_checkpoint(single_run)
    for part in ("actor", "critic", "optimizer", "env", "algorithm"):
        torch.testing.assert_close(team[part], single[part], rtol=0, atol=0, msg=lambda m: f"{part}: {m}")
    assert torch.equal(team["rng"]["torch"], single["rng"]["torch"])
    assert (team["update"], team["env_steps"]) == (single["update"], single["env_steps"])
    assert "runtime" not in team["config"]  # how the teams took turns is not the run's
    assert {**team["config"], "run_dir": None} == {**single["config"], "run_dir": None}  # but where it was written
    assert read_metrics(team_run) == read_metrics(single_run)


@pytest.mark.parametrize("overrides", [
    # levels drawn per episode from each team's key; the teams stacked inside one XLA program (the default collector)
    ["levels=infinite", "runtime.collector=xla"],
    # recurrent state and stacked per-agent networks
    ["architecture=mlp_lstm", "share_params=false", "runtime.collector=xla"],
    ["algorithm=e3t", "architecture=e3t_mlp", "algorithm_config.partner_policy=copy"],  # partner seats drawn per team
    # Alone, a team's minibatch shards run on threads at once; beside other teams, one after the other.
    ["architecture=mlp_lstm", "share_params=false", "runtime.minibatch_shards=2"],
], ids=["ippo-infinite", "lstm", "e3t", "shards"])
@pytest.mark.bitwise
def test_each_team_of_a_multi_team_run_is_the_run_of_its_seed_alone(tmp_path, overrides):
    # Two teams learn at once on threads, the third after them: each as it would alone (whose shards, if any,
    # run on two threads at once).
    config = tiny_config(tmp_path / "teams", "runtime.teams=3", "seed=5", "runtime.parallel_teams=2", *overrides)
    runs = train_teams(team_configs(config))
    assert [run.name for run in runs] == ["seed5", "seed6", "seed7"]
    for run, seed in zip(runs, (5, 6, 7)):
        assert_same_run(run, train(tiny_config(tmp_path / "single", f"seed={seed}", *overrides)))


@pytest.mark.bitwise
def test_a_team_of_a_multi_team_run_resumes_alone_and_teams_resume_together(tmp_path):
    assert main([*tiny_args(tmp_path / "teams"), "runtime.teams=2", "total_steps=64"]) == 0
    team0, team1 = tmp_path / "teams" / "main" / "seed0", tmp_path / "teams" / "main" / "seed1"
    assert main(["--resume", str(team1), "total_steps=128"]) == 0  # alone, as a run of its own
    assert main(["--resume", str(team0), str(team1), "total_steps=128"]) == 2  # now at different updates
    assert main(["--resume", str(team0), "total_steps=128"]) == 0
    assert main(["--resume", str(team0), str(team1), "total_steps=192"]) == 0  # together again
    for seed, run in enumerate((team0, team1)):  # the same budgets one after the other (they set lr's annealing)
        single = tmp_path / "single" / "main" / f"seed{seed}"
        assert main([*tiny_args(tmp_path / "single"), f"seed={seed}", "total_steps=64"]) == 0
        for budget in (128, 192):
            assert main(["--resume", str(single), f"total_steps={budget}"]) == 0
        assert_same_run(run, single)


def tiny_args(run_dir):
    return [MAIN_CONFIG, *TINY, f"run_dir={run_dir}"]


def test_teams_trained_together_share_every_setting_but_the_seed(tmp_path):
    first, second = team_configs(tiny_config(tmp_path, "runtime.teams=2"))
    second = dataclasses.replace(second, ppo=dataclasses.replace(second.ppo, lr=1e-3))
    with pytest.raises(ConfigError, match="seed 1 differs from seed 0 in ppo.lr"):
        train_teams([first, second])
    with pytest.raises(ConfigError, match="train_teams"):
        train(tiny_config(tmp_path, "runtime.teams=2"))
    with pytest.raises(ConfigError, match="teams must be at least 1"):
        tiny_config(tmp_path, "runtime.teams=0")
    with pytest.raises(ConfigError, match="go past the largest seed"):
        tiny_config(tmp_path, "runtime.teams=2", f"seed={2**32 - 1}")


def observations(env: KitchenEnv, actions: torch.Tensor) -> torch.Tensor:
    """uint8 [T, B, 2, H, W, C]: the observations after each step of `actions` [T, B, 2], resets included."""
    tensordict, seen = env.reset(), []
    for step_actions in actions:
        _, tensordict = env.step_and_maybe_reset(tensordict.set(("agents", "action"), step_actions))
        seen.append(tensordict["agents", "observation"].clone())
    return torch.stack(seen)


@pytest.mark.bitwise
def test_the_env_teams_see_the_levels_of_one_team_envs_with_their_seeds():
    teams = KitchenEnv(num_envs=6, levels="infinite", max_steps=3, seed=[3, 9])
    actions = torch.randint(6, (8, 6, 2), generator=torch.Generator().manual_seed(0))
    together = observations(teams, actions)  # two resets after the first episode: new levels per team
    for team, seed in enumerate((3, 9)):
        alone, rows = KitchenEnv(num_envs=3, levels="infinite", max_steps=3, seed=seed), slice(3 * team, 3 * team + 3)
        assert torch.equal(together[:, rows], observations(alone, actions[:, rows]))
        torch.testing.assert_close(teams.team_state(team), alone.team_state(0), rtol=0, atol=0)
    with pytest.raises(ValueError, match="cannot split 5 kitchens"):
        KitchenEnv(num_envs=5, levels="infinite", seed=[0, 1])


def test_a_random_stream_is_its_own_and_leaves_the_global_one_alone():
    torch.manual_seed(1)
    expected_global = torch.rand(3)
    stream = RandomStream(7)
    torch.manual_seed(1)
    with stream.active():
        first = torch.rand(2)
    outside = torch.rand(3)
    with stream.active():
        second = torch.rand(2)
        with stream.active():  # nested: the stream goes on, its draws are not replayed
            third = torch.rand(2)
        fourth = torch.rand(2)
    torch.manual_seed(7)
    assert torch.equal(torch.cat([first, second, third, fourth]), torch.rand(8))
    assert torch.equal(outside, expected_global)


def test_teams_learn_at_once_on_as_many_threads_as_the_cores_allow(tmp_path, monkeypatch):
    monkeypatch.setattr("trainers.ppo.runtime.usable_cores", lambda: 4)

    def workers(*overrides, teams=6):
        pool = learning_pool(tiny_config(tmp_path, *overrides), teams)
        return 1 if pool is None else pool._max_workers

    assert workers() == 4  # threads=1: one team per core
    # each team's torch threads take cores too
    assert workers("runtime.threads=2") == 2 and workers("runtime.threads=4") == 1
    assert workers(teams=3) == 3 and workers(teams=1) == 1
    assert workers("runtime.parallel_teams=1") == 1 and workers("runtime.parallel_teams=6") == 6  # asked for: as asked


def test_a_team_alone_runs_its_shards_on_a_shard_pool(tmp_path, monkeypatch):
    monkeypatch.setattr("trainers.ppo.runtime.usable_cores", lambda: 4)
    pool = learning_pool(tiny_config(tmp_path, "runtime.minibatch_shards=2"), 1)
    assert isinstance(pool, ShardPool) and pool._max_workers == 2
    assert learning_pool(tiny_config(tmp_path), 1) is None  # one shard: nothing to run at once
    assert not isinstance(learning_pool(tiny_config(tmp_path, "runtime.minibatch_shards=2"), 3), ShardPool)


@pytest.mark.bitwise
@pytest.mark.parametrize("pool", [lambda: TeamPool(2, 1), lambda: ShardPool(2, 1)], ids=["teams", "shards"])
def test_a_pool_threads_products_sum_as_the_main_threads(pool):
    """A oneDNN product on a team's or a shard's thread is the main thread's, bit for bit: the thread takes the run's
    torch threads (1 here) when it starts. Left at OpenMP's default of one per core, oneDNN's AVX2 kernels split this
    product's sum between two threads (run with ONEDNN_MAX_CPU_ISA=AVX2, as `make test`'s second pass does). The
    weight is read transposed, as the gradients' products read their operands."""
    generator = torch.Generator().manual_seed(0)
    row, weight = torch.randn(1, 4096, generator=generator), torch.randn(4096, 256, generator=generator).t()

    def product():
        return OneDNNProduct.apply(row, weight, None)

    with pool() as threads:
        assert torch.equal(threads.submit(product).result(), product())


def test_a_shard_pool_runs_the_shards_the_faster_way_and_times_the_other_now_and_then():
    caller = threading.current_thread()
    on_threads = []  # per shard run: whether it ran on the pool's threads

    def shard(x):  # slow on the pool's threads, as when another process holds a core
        on_threads.append(threading.current_thread() is not caller)
        if on_threads[-1]:
            time.sleep(0.05)
        return 2 * x

    ways = []  # per map: whether its shards ran at once
    with ShardPool(2, 1, explore_every=8) as pool:
        for _ in range(17):
            on_threads.clear()
            assert list(pool.map(shard, [1, 2, 3])) == [2, 4, 6]  # the same results either way
            assert len(set(on_threads)) == 1
            ways.append(on_threads[0])
    assert ways[0] and not ways[1]  # each way timed once
    assert [i for i, at_once in enumerate(ways) if at_once] == [0, 7, 15]  # then one after the other, but every 8th


@pytest.mark.parametrize("architecture", ["mlp", "ego_mlp"])
@pytest.mark.bitwise
def test_stacked_teams_act_as_the_teams_one_after_another_at_one_teams_launches(tmp_path, architecture):
    """The teams' networks stacked and vmapped (the GPU's way) give each team's logits and values to float rounding
    and, sampled in each team's own stream, its actions; restacked, the weights are the teams' after an optimizer's
    step; and acting for 3 teams launches one team's kernels but a draw per team."""
    from op_audit import OpAudit
    from tensordict import TensorDict
    from tensordict.nn import InteractionType, set_interaction_type

    from torch_kitchen.onednn_linear import device_path
    from torch_kitchen.teams import TeamPolicy
    from trainers.ppo.team import build_team, make_env

    config = tiny_config(tmp_path, f"architecture={architecture}", "levels=infinite", "runtime.teams=3")
    configs = team_configs(config)
    kitchen = make_env(configs[0], num_envs=3 * config.num_envs, seed=[c.seed for c in configs])
    teams = [build_team(c, tmp_path / str(c.seed), kitchen, k) for k, c in enumerate(configs)]
    observation = kitchen.reset().get(("agents", "observation"))

    def act(policy_of_teams, streams_seed):
        streams = [RandomStream(streams_seed + k) for k in range(3)]
        policy = TeamPolicy([team.policy for team in teams], streams, config.num_envs, stack=policy_of_teams)
        with torch.no_grad(), OpAudit() as audit:
            out = policy(TensorDict({("agents", "observation"): observation}, batch_size=[len(observation)]))
        return out, audit, policy

    with device_path(), set_interaction_type(InteractionType.RANDOM):  # sampled, whatever another test left set
        one_by_one, loop_audit, _ = act(False, 10)
        stacked, stacked_audit, policy = act(True, 10)
        for key in ("logits", "state_value", "action_log_prob"):
            torch.testing.assert_close(stacked["agents", key], one_by_one["agents", key], rtol=1e-5, atol=1e-6)
        assert torch.equal(stacked["agents", "action"], one_by_one["agents", "action"])
        with OpAudit() as single:
            with torch.no_grad():
                teams[0].policy(TensorDict({("agents", "observation"): observation[:config.num_envs]},
                                           batch_size=[config.num_envs]))
        # The networks' and the sampling's kernels once for all teams; per team only its draw, then one concatenation.
        assert stacked_audit.launches == single.launches + 2 + 1 < loop_audit.launches

        for parameter in teams[1].parameters:  # a step of team 1's fused Adam, which leaves no trace on the weights
            parameter.grad = torch.ones_like(parameter)
        teams[1].optimizer.step()
        policy.restack()
        followed = policy(TensorDict({("agents", "observation"): observation}, batch_size=[len(observation)]))
        rows = slice(config.num_envs, 2 * config.num_envs)
        expected = teams[1].actor_critic.critic(TensorDict({("agents", "observation"): observation[rows]},
                                                           batch_size=[config.num_envs]))
        torch.testing.assert_close(followed["agents", "state_value"][rows], expected["agents", "state_value"],
                                   rtol=1e-5, atol=1e-6)


def test_teams_trained_the_gpus_way_learn_what_they_learn_one_after_another(tmp_path, monkeypatch):
    """The trainer's GPU way, forced on the CPU: the teams act as one stacked network, each drawing from its own
    stream, and learn as one vmapped loss with each team's own clipping and Adam step. The kitchens end where they
    do one team after another (the same actions at every step), every team logs its own losses, and the weights
    agree to float rounding, which Adam's first steps amplify where a gradient is near zero (up to 2e-4 here)."""
    import trainers.ppo.runtime

    overrides = ["levels=infinite", "runtime.teams=2", "ppo.shaping_weight=1"]
    apart = tiny_config(tmp_path / "apart", *overrides)
    train_teams(team_configs(apart))
    monkeypatch.setattr(trainers.ppo.runtime, "acts_stacked", lambda config, policies: True)
    monkeypatch.setattr(trainers.ppo.runtime, "learns_stacked", lambda config, teams: True)
    stacked = tiny_config(tmp_path / "stacked", *overrides)
    train_teams(team_configs(stacked))
    for seed in (0, 1):
        apart_run, stacked_run = apart.run_path.parent / f"seed{seed}", stacked.run_path.parent / f"seed{seed}"
        apart_state, stacked_state = load_checkpoint(apart_run), load_checkpoint(stacked_run)
        torch.testing.assert_close(stacked_state["env"], apart_state["env"], rtol=0, atol=0)
        for part in ("actor", "critic", "optimizer"):
            torch.testing.assert_close(stacked_state[part], apart_state[part], rtol=0, atol=1e-3)
        apart_metrics, stacked_metrics = read_metrics(apart_run), read_metrics(stacked_run)
        assert apart_metrics.keys() == stacked_metrics.keys()
        for name in ("losses/policy", "losses/value", "losses/approx_kl", "losses/entropy", "losses/grad_norm"):
            torch.testing.assert_close(torch.tensor(stacked_metrics[name]), torch.tensor(apart_metrics[name]),
                                       rtol=1e-3, atol=1e-6, msg=name)


@pytest.mark.parametrize("architecture", ["mlp", "gnn"])
def test_a_stacked_loss_gives_each_team_its_own_losses_and_gradients(tmp_path, architecture):
    """One vmapped computation over three teams' stacked parameters: each team's loss terms and metrics, and the
    gradient of the teams' summed losses on each team's weights, are those of its own loss on its own minibatch."""
    from test_ppo import team_and_minibatch
    from torchrl.modules import set_recurrent_mode

    from torch_kitchen.teams import StackedLoss
    from trainers.ppo.step import total_loss

    teams, minibatches = zip(*[team_and_minibatch(tiny_config(tmp_path / str(seed), f"seed={seed}",
                                                              f"architecture={architecture}"), tmp_path / str(seed))
                               for seed in range(3)])
    stacked = StackedLoss([team.loss_module for team in teams])
    with set_recurrent_mode(True):
        losses = stacked(torch.stack(minibatches))
        total_loss(losses).sum().backward()
        stacked_gradients = [[parameter.grad.clone() for parameter in team.parameters] for team in teams]
        for team, minibatch, gradients in zip(teams, minibatches, stacked_gradients):
            team.loss_module.zero_grad()
            own = team.loss_module(minibatch)
            total_loss(own).backward()
            for key in ("loss_objective", "loss_critic", "loss_entropy", "entropy", "kl_approx", "clip_fraction"):
                index = teams.index(team)
                torch.testing.assert_close(losses[key][index], own[key].mean(), rtol=1e-5, atol=1e-7, msg=key)
            for parameter, gradient in zip(team.parameters, gradients):
                torch.testing.assert_close(gradient, parameter.grad, rtol=1e-4, atol=1e-7)
    assert not torch.equal(losses["loss_critic"][0], losses["loss_critic"][1])  # the teams differ


@pytest.mark.parametrize(("overrides", "stacks"), [
    ([], True),
    (["architecture=gnn"], True),
    (["runtime.device=cpu"], False),  # a CPU's teams learn each on its own, with its sparse first layer
    (["architecture=mlp_lstm"], False),  # TorchRL's LSTM branches on its input's values
    (["share_params=false"], False),  # per-agent networks are vmapped by TorchRL already
    (["algorithm=e3t", "architecture=e3t_mlp"], False),  # each team's partner predictor and seats
    (["runtime.minibatch_shards=2"], False),
])
def test_teams_learn_as_one_where_the_gpu_model_and_algorithm_allow(tmp_path, overrides, stacks):
    from trainers.ppo.runtime import learns_stacked
    from trainers.ppo.team import build_team, make_env

    configs = team_configs(tiny_config(tmp_path, "runtime.teams=2", *overrides))
    kitchen = make_env(configs[0], num_envs=2 * configs[0].num_envs, seed=[c.seed for c in configs])
    teams = [build_team(c, tmp_path / str(c.seed), kitchen, k) for k, c in enumerate(configs)]
    on_gpu = configs[0]
    if "runtime.device=cpu" not in overrides:
        on_gpu = dataclasses.replace(on_gpu, runtime=dataclasses.replace(on_gpu.runtime, device="cuda"))
    assert learns_stacked(on_gpu, teams) is stacks
    assert learns_stacked(on_gpu, teams[:1]) is False  # one team alone


def _stacked_team_policy(tmp_path, architecture, compile_mode=None):
    from torch_kitchen.teams import TeamPolicy
    from trainers.ppo.team import build_team, make_env

    config = tiny_config(tmp_path, f"architecture={architecture}", "levels=infinite", "runtime.teams=2")
    configs = team_configs(config)
    kitchen = make_env(configs[0], num_envs=2 * config.num_envs, seed=[c.seed for c in configs])
    teams = [build_team(c, tmp_path / str(c.seed), kitchen, k) for k, c in enumerate(configs)]
    policy = TeamPolicy([team.policy for team in teams], [team.stream for team in teams], config.num_envs, True,
                        compile_mode)
    return kitchen, policy


@pytest.mark.parametrize("architecture", ["mlp", "ego_mlp"])
def test_the_stacked_networks_compile_whole_and_equal_eager(tmp_path, architecture):
    import torch._dynamo

    kitchen, policy = _stacked_team_policy(tmp_path, architecture, compile_mode="default")
    observation = kitchen.reset().get(("agents", "observation"))
    by_team = observation.reshape(2, -1, *observation.shape[1:])
    torch._dynamo.reset()
    for networks in policy.stacked:  # fullgraph=True: a graph break would raise
        eager = networks._layers(by_team, networks.stacked)
        torch.testing.assert_close(networks(by_team), eager, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("kind", ["torchrl", "kitchen"])
def test_a_collector_keeps_every_step_of_stacked_networks_whose_outputs_share_one_buffer(tmp_path, kind):
    """A CUDA graph writes its outputs into the same buffers at every replay, and TorchRL's collector keeps each
    step's outputs by reference until it stacks the batch: the stacked networks copy them out in that mode, so each
    stored step holds its own logits (without the copy, every step would hold the last one's). The kitchens'
    collector copies every step into the batch as it comes, so it keeps each step either way."""
    from trainers.ppo.collection import make_collector

    def replaying_into_one_buffer(networks):
        buffer = {}

        def run(x, stacked):
            out = networks._layers(x, stacked)
            buffer.setdefault("out", torch.empty_like(out)).copy_(out)
            return buffer["out"]
        return run

    for mode, keeps_each_step in (("reduce-overhead", True), (None, False)):
        kitchen, policy = _stacked_team_policy(tmp_path / str(mode), "mlp", compile_mode=mode)
        for networks in policy.stacked:
            networks.compile_mode, networks._run = mode, replaying_into_one_buffer(networks)
        collector = make_collector(kitchen, policy, frames_per_batch=8 * 4, total_frames=8 * 4, kind=kind)
        batch = next(iter(collector))
        collector.shutdown()
        logits = batch["agents", "logits"]  # [8 kitchens, 4 steps, 2, 6]
        stored_last_everywhere = all(torch.equal(logits[:, t], logits[:, -1]) for t in range(4))
        assert stored_last_everywhere is not (keeps_each_step or kind == "kitchen"), mode
        if keeps_each_step or kind == "kitchen":
            with torch.no_grad():
                for step in range(4):
                    again = policy(batch[:, step].select(("agents", "observation")).clone())
                    torch.testing.assert_close(again["agents", "logits"], logits[:, step])


def test_one_team_compiled_for_cuda_graphs_marks_each_step_and_keeps_its_outputs(tmp_path, monkeypatch):
    """With one team there is nothing to stack, so its own acting pass is compiled, in "reduce-overhead" on a GPU:
    a replay overwrites the last one's output buffers, so each call marks a step and returns copies (stood in for
    here by a compiled function that writes every output into one buffer)."""
    from torch_kitchen.teams import TeamPolicy
    from trainers.ppo.team import build_team, make_env

    def replaying_into_one_buffer(function, mode):
        buffers = {}

        def run(observation):
            return tuple(buffers.setdefault(index, torch.empty_like(output)).copy_(output)
                         for index, output in enumerate(function(observation)))
        return run

    marks = []
    monkeypatch.setattr(torch, "compile", replaying_into_one_buffer)
    monkeypatch.setattr(torch.compiler, "cudagraph_mark_step_begin", lambda: marks.append(1))
    config = tiny_config(tmp_path, "architecture=mlp", "levels=infinite")
    kitchen = make_env(config)
    team = build_team(config, tmp_path / "run", kitchen, 0)
    policy = TeamPolicy([team.policy], [team.stream], config.num_envs, stack=True, compile_mode="reduce-overhead")
    first_observation = kitchen.reset().get(("agents", "observation"))
    first = policy.act(first_observation)
    kept = {key: value.clone() for key, value in first.items()}
    policy.act(torch.zeros_like(first_observation))
    assert len(marks) == 2
    for key, value in first.items():
        assert torch.equal(value, kept[key]), key  # the first step's outputs, not the second's


def test_clipping_per_team_on_stacked_gradients_is_clip_grad_norm_of_each_team():
    from trainers.ppo.step import clip_per_team

    torch.manual_seed(0)
    stacked = [torch.randn(3, 4, 5), torch.randn(3, 5) * 0.01, torch.randn(3, 2)]
    stacked[0][1, 2, 3] = float("nan")  # team 1's: zeroed first
    teams = [[gradient[team].clone().nan_to_num_(0.0, 0.0, 0.0) for gradient in stacked] for team in range(3)]
    given = [gradient.clone() for gradient in stacked]
    clipped, norms = clip_per_team(stacked, max_norm=0.5)
    for mine, before in zip(stacked, given):  # new tensors: autograd's outputs are left as they were
        torch.testing.assert_close(mine, before, equal_nan=True, rtol=0, atol=0)
    for team, gradients in enumerate(teams):
        parameters = [torch.nn.Parameter(torch.zeros_like(gradient)) for gradient in gradients]
        for parameter, gradient in zip(parameters, gradients):
            parameter.grad = gradient
        norm = torch.nn.utils.clip_grad_norm_(parameters, 0.5)
        torch.testing.assert_close(norms[team], norm)
        for parameter, gradient in zip(parameters, clipped):
            torch.testing.assert_close(gradient[team], parameter.grad)
    assert (norms > 0.5).all()  # every team was clipped

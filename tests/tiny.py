"""What the tests share: the tiny training run, a few seconds per run (4 kitchens x 16 steps per update, 16-step
episodes, narrow networks, no progress bar, no final evaluation, the kitchens' collector), and real observations for
the models, and a zoo file drawn again with one cook changed."""

import dataclasses
import functools
import sys
from pathlib import Path

TINY = [
    "num_envs=4",
    "rollout_steps=16",
    "max_steps=16",
    "hidden=16",
    "ppo.minibatches=2",
    "ppo.epochs=2",
    "runtime.threads=1",
    "progress=false",
    "eval_episodes=0",
    "levels=cramped_room_7x7",
    "distill.kitchens=4",
    "init_from=",  # from scratch, whatever the config starts from
    # Collected by the kitchens' collector: a tiny run compiles the XLA rollout for longer than it trains (6 s of a
    # 16 s run); the tests of the XLA collector name it (runtime.collector=xla).
    "runtime.collector=kitchen",
]


def infinite_observations(count: int, seed: int, steps: int = 3):
    """Real Infinite Kitchen observations, uint8 torch [count, 2, 7, 7, 26], `steps` random steps into their
    episodes: a copy of one made once per process (each takes a JAX compilation)."""
    return _infinite_observations(count, seed, steps).clone()


@functools.cache
def _infinite_observations(count: int, seed: int, steps: int):
    import jax
    import numpy as np
    import torch

    from jax_env import Overcooked

    env = Overcooked("infinite", max_steps=256)
    key = jax.random.PRNGKey(seed)
    obs, states = env.reset_batch(key, count)
    for _ in range(steps):
        key, act = jax.random.split(key)
        obs, states, *_ = env.step_batch(key, states, jax.random.randint(act, (count, 2), 0, 6))
    return torch.from_numpy(np.array(obs))


@functools.cache
def script_module(name: str):
    """A script of scripts/ (a folder of scripts, not a package) as a module, loaded from its file."""
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(name, Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # as an import would: dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def compiled_with_operator(layer, inputs, operator: str, grad_out):
    """`layer(inputs)` compiled whole, its graph calling the named operator (a CPU kernel kept whole in the graph),
    and its backward run on `grad_out`: returns the output, the layer's parameters' gradients left in place."""
    import torch

    explained = torch._dynamo.explain(layer)(inputs)
    assert explained.graph_break_count == 0
    targets = {str(node.target) for graph in explained.graphs for node in graph.graph.nodes}
    assert any(operator in target for target in targets), targets
    out = torch.compile(layer, fullgraph=True)(inputs)
    out.backward(grad_out)
    return out


def redraw_zoo(source, name: str, out) -> Path:
    """The zoo file `source` written to `out` with its convention `name` changed (noise 0.5) and every other member
    as it was: a zoo redrawn under the same name, whose cook `name` is another by content."""
    from torch_kitchen.partners.conventions import load_zoo, save_zoo

    zoo = load_zoo(source)
    members = [dataclasses.replace(member, convention=dataclasses.replace(member.convention, noise=0.5))
               if member.name == name else member for member in zoo.members]
    return save_zoo(dataclasses.replace(zoo, members=members), out)

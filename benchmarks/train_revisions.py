"""Training throughput of the working tree against an earlier revision, in one run, as a ratio.

Checks out `REVISION` into a temporary git worktree and runs `benchmarks/train.py` (modes `throughput`, `e3t` and
`reference`) from each checkout in turn, alternating (earlier, current, earlier, current, ...) so that both see the
same machine state; every measurement is a separate process. Prints, and writes to `--out`, a Markdown table of
the median steps/s of each side and current / earlier. With `--reference`, each side also runs the pure-JAX
yardstick of `benchmarks/jax_ppo.py` beside it, and the rows give ours / yardstick of each side. With `--main`, each
side also times the main job's IPPO phase (`configs/main.yaml`'s team and batch after its distilled start: the
agent-centred MLP at hidden 128, 32 kitchens x 256 steps of the Infinite Kitchen) with its default collector.

    python benchmarks/train_revisions.py 93900fa --archs mlp gnn --e3t mlp --repeats 2 --out results.md
    python benchmarks/train_revisions.py 901da01 --archs --e3t --reference jaxmarl ik protocol --threads 1
    python benchmarks/train_revisions.py 8587591 --archs --e3t --main --repeats 3
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from trainers.machine import THREADS_HELP, machine_name

ROOT = Path(__file__).resolve().parents[1]


# Updates per `reference` measurement (ours times all but the first): enough for a few seconds of timed work.
REFERENCE_UPDATES = {"jaxmarl": 20, "ik": 4, "protocol": 3, "protocol_gnn": 2, "protocol_sk": 3}

# The main job's IPPO phase as `train.py`'s `throughput` runs it (the same function at every revision since its
# overrides were added): configs/main.yaml's network and batch; its distilled start changes no step's cost.
MAIN_IPPO = ("ego_mlp", 32, 256)
MAIN_IPPO_OVERRIDES = ("hidden=128", "share_params=true", "regime=ik")


def _run(checkout: Path, arguments: list[str]) -> str:
    """The output of `benchmarks/train.py ARGUMENTS` run from `checkout`, on that checkout's code."""
    environment = {**os.environ, "PYTHONPATH": str(checkout)}
    return subprocess.run([sys.executable, "benchmarks/train.py", *arguments], cwd=checkout, env=environment,
                          capture_output=True, text=True, check=True).stdout


def measure_main(checkout: Path, updates: int, threads: int) -> dict[str, float]:
    """The main job's IPPO steps/s (`MAIN_IPPO`, updates 2..`updates`) from `checkout`, with its default collector."""
    architecture, envs, steps = MAIN_IPPO
    call = (f"from train import throughput; print(throughput({architecture!r}, {envs}, {steps}, {updates}, 'cpu', "
            f"{threads}, overrides={list(MAIN_IPPO_OVERRIDES)!r}))")
    environment = {**os.environ, "PYTHONPATH": os.pathsep.join([str(checkout), str(checkout / "benchmarks")])}
    output = subprocess.run([sys.executable, "-c", call], cwd=checkout, env=environment, capture_output=True,
                            text=True, check=True).stdout
    return {"main job's IPPO phase (ego_mlp, hidden 128)": float(output.strip().splitlines()[-1])}


def measure_reference(checkout: Path, settings: list[str], threads: int, collector: str) -> dict[str, float]:
    """Ours (collecting with `collector`) and the yardstick's steps/s, and their ratio, per setting of `train.py
    reference`, from `checkout`."""
    rates = {}
    for setting in settings:
        output = _run(checkout, ["reference", "--setting", setting, "--updates", str(REFERENCE_UPDATES[setting]),
                                 "--threads", str(threads), "--collector", collector])
        fields = output.strip().splitlines()[-1].split()  # ours, yardstick, ratio; or ours alone (no yardstick)
        rates[f"{setting}: ours"] = float(fields[0].replace(",", ""))
        if len(fields) == 3:
            rates[f"{setting}: yardstick"] = float(fields[1].replace(",", ""))
            rates[f"{setting}: ours / yardstick"] = float(fields[2])
    return rates


def measure(checkout: Path, mode: str, names: list[str], envs: int, updates: int, threads: int) -> dict[str, float]:
    """Steps/s per measured configuration of one `benchmarks/train.py` run (`throughput` or `e3t`) from `checkout`."""
    option = "--archs" if mode == "throughput" else "--encoders"
    output = _run(checkout, [mode, option, *names, "--envs", str(envs), "--updates", str(updates), "--threads",
                             str(threads)])
    rates = {}
    for line in output.splitlines():
        fields = line.split()
        if mode == "throughput" and len(fields) == 4 and fields[0] in names:
            rates[f"IPPO {fields[0]}"] = float(fields[3].replace(",", ""))
        elif mode == "e3t" and len(fields) == 5 and fields[0] in names:
            rates[f"IPPO {fields[0]} (e3t run)"] = float(fields[2].replace(",", ""))
            rates[f"E3T e3t_{fields[0]}"] = float(fields[3].replace(",", ""))
    return rates


def table_lines(args: argparse.Namespace, argv, runs: dict[str, dict[str, list[float]]]) -> list[str]:
    """The table's caption (shape, runs, machine, command) and its rows: each configuration's median steps/s on
    either side and their ratio."""
    machine = f"{machine_name()}, torch threads {args.threads}"
    shape = f"{args.envs} kitchens x 256 steps, hidden 256, Infinite Kitchen" if args.archs or args.e3t else ""
    shape += (f"{'; ' if shape else ''}reference settings {', '.join(args.reference)}, ours collecting with "
              f"runtime.collector={args.collector}" if args.reference else "")
    shape += (f"{'; ' if shape else ''}the main job's IPPO phase: {MAIN_IPPO[1]} kitchens x {MAIN_IPPO[2]} steps, "
              f"{MAIN_IPPO[0]}, {', '.join(MAIN_IPPO_OVERRIDES)}" if args.main else "")
    lines = [
        f"Training steps/s ({shape}); median of {args.repeats} alternating runs per side; {machine}.",
        f"Earlier: `{args.revision}`. Command: `python benchmarks/train_revisions.py {' '.join(argv or sys.argv[1:])}`",
        "",
        "| configuration | earlier steps/s | current steps/s | current / earlier |",
        "|---|---:|---:|---:|",
    ]
    for name in runs["earlier"]:
        before, after = statistics.median(runs["earlier"][name]), statistics.median(runs["current"][name])
        digits = 3 if name.endswith("/ yardstick") else 0  # a ratio, not steps/s
        lines.append(f"| {name} | {before:,.{digits}f} | {after:,.{digits}f} | {after / before:.2f} |")
    return lines


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("revision", help="the earlier git revision to compare against")
    parser.add_argument("--archs", nargs="*", default=["mlp", "gnn"], help="IPPO architectures")
    parser.add_argument("--e3t", nargs="*", default=["mlp"], help="E3T encoders (each also runs IPPO beside it)")
    parser.add_argument("--reference", nargs="*", default=[], choices=list(REFERENCE_UPDATES),
                        help="settings of `train.py reference`: ours beside the pure-JAX yardstick")
    parser.add_argument("--collector", choices=["kitchen", "torchrl", "xla"], default="xla",
                        help="ours with this runtime.collector in the reference settings (default: the trainer's)")
    parser.add_argument("--main", action="store_true", help="also the main job's IPPO phase (MAIN_IPPO)")
    parser.add_argument("--envs", type=int, default=32)
    parser.add_argument("--updates", type=int, default=3, help="updates per measurement (the first is not timed)")
    parser.add_argument("--threads", type=int, default=1, help=THREADS_HELP)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", help="also write the Markdown table here")
    args = parser.parse_args(argv)

    runs = {"earlier": {}, "current": {}}
    with tempfile.TemporaryDirectory() as scratch:
        earlier = Path(scratch) / "earlier"
        subprocess.run(["git", "worktree", "add", "--detach", str(earlier), args.revision], cwd=ROOT, check=True,
                       capture_output=True)
        try:
            for repeat in range(args.repeats):
                for side, checkout in (("earlier", earlier), ("current", ROOT)):
                    measurements = {
                        "throughput": args.archs and (lambda: measure(checkout, "throughput", args.archs, args.envs,
                                                                      args.updates, args.threads)),
                        "e3t": args.e3t and (lambda: measure(checkout, "e3t", args.e3t, args.envs, args.updates,
                                                             args.threads)),
                        "reference": args.reference and (lambda: measure_reference(checkout, args.reference,
                                                                                   args.threads, args.collector)),
                        "main": args.main and (lambda: measure_main(checkout, args.updates, args.threads)),
                    }
                    for mode, measured in measurements.items():
                        if measured:
                            rates = measured()
                            for name, rate in rates.items():
                                runs[side].setdefault(name, []).append(rate)
                            print(f"repeat {repeat + 1} {side:8s} {mode:10s} {rates}", flush=True)
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(earlier)], cwd=ROOT, check=False)

    lines = table_lines(args, argv, runs)
    table = "\n".join(lines) + "\n"
    print(table)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(table)


if __name__ == "__main__":
    main()

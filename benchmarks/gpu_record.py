"""The record of one `benchmarks/gpu_checks.sh` run: its rows (a JSON line each, as the rows wrote them) with the
goals they are held to, as `<out>/<date>_<device>.json` and `.md`, and the raw outputs in `<out>/<date>_<device>/`.

    python benchmarks/gpu_record.py RECORDS.jsonl RAW_DIR --out benchmarks/results/gpu
"""

from __future__ import annotations

import argparse
import datetime
import json
import re
import shutil
from pathlib import Path

# The goals of the GPU path: the paper's protocol at >= 10M env steps per minute and at least the pure-JAX
# yardstick's speed in the same run (the default collector's row), and the main job to its end within 2.5 minutes.
PROTOCOL_STEPS_PER_MINUTE = 10_000_000
PROTOCOL_RATIO = 1.0
MAIN_SECONDS = 150
HEADLINE = "protocol_default"


def verdict(row: dict) -> str:
    """PASS, FAIL, or '' for a row without a goal."""
    if row.get("skipped"):
        return "skipped"
    if row["row"] == HEADLINE:
        fast = row["ours"] * 60 >= PROTOCOL_STEPS_PER_MINUTE
        return "PASS" if fast and (row["ratio"] or 0) >= PROTOCOL_RATIO else "FAIL"
    if row["row"] == "main":
        return "PASS" if row["status"] == 0 and row["seconds"] <= MAIN_SECONDS else "FAIL"
    return ""


def device_name(raw: Path) -> str:
    """The GPU's name as torch gave it in device.txt, else the CPU's."""
    text = (raw / "device.txt").read_text() if (raw / "device.txt").is_file() else ""
    found = re.search(r"^torch \S+ (.+?) \| jax", text, re.MULTILINE)
    if found and found.group(1) != "no CUDA":
        return found.group(1)
    from trainers.machine import machine_name

    return machine_name()


def read_rows(records: Path) -> list[dict]:
    rows = [json.loads(line) for line in records.read_text().splitlines() if line.strip()] if records.is_file() else []
    return [{**row, "verdict": verdict(row)} for row in rows]


def markdown(rows: list[dict], device: str, date: str) -> str:
    lines = [f"# GPU checks, {date}, {device}", "",
             f"Goals: `{HEADLINE}` >= {PROTOCOL_STEPS_PER_MINUTE / 1e6:.0f}M env steps per minute and >= "
             f"{PROTOCOL_RATIO:.1f}x the pure-JAX yardstick in the same run; the main job to its end within "
             f"{MAIN_SECONDS} s.", "",
             "| row | ours (steps/s) | yardstick (steps/s) | ours / yardstick | seconds | verdict | command |",
             "|---|---|---|---|---|---|---|"]
    for row in rows:
        ours = f"{row['ours']:,.0f}" if row.get("ours") is not None else ""
        reference = f"{row['reference']:,.0f}" if row.get("reference") is not None else ""
        ratio = f"{row['ratio']:.3f}" if row.get("ratio") is not None else ""
        seconds = f"{row['seconds']}" + (f" (exit {row['status']})" if row.get("status") else "") \
            if "seconds" in row else ""
        lines.append(f"| {row['row']} | {ours} | {reference} | {ratio} | {seconds} | {row['verdict']} | "
                     f"`{row['command']}` |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("records", type=Path, help="the rows' JSON lines")
    parser.add_argument("raw", type=Path, help="the folder of the rows' outputs and device.txt")
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/gpu"))
    args = parser.parse_args(argv)
    device, date = device_name(args.raw), datetime.date.today().isoformat()
    stem = f"{date}_{re.sub(r'[^A-Za-z0-9]+', '_', device).strip('_')}"
    rows = read_rows(args.records)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"{stem}.json").write_text(json.dumps({"date": date, "device": device, "rows": rows}, indent=1) + "\n")
    (args.out / f"{stem}.md").write_text(markdown(rows, device, date))
    shutil.copytree(args.raw, args.out / stem, dirs_exist_ok=True,
                    ignore=shutil.ignore_patterns("main"))  # the main job's run folder stays behind
    print(markdown(rows, device, date))
    print(f"record: {args.out / stem}.json, .md; outputs in {args.out / stem}/")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

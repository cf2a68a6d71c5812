"""The record of one `benchmarks/gpu_checks.sh` run: every row it started or skipped, with its status, the tail of its
output and its figures, held to the goals, as `<out>/<date>_<device>.json` and `.md`, and the raw outputs in
`<out>/<date>_<device>/`.

    python benchmarks/gpu_record.py status RECORDS.jsonl NAME EXIT|skipped SECONDS COMMAND [--output NAME.txt]
    python benchmarks/gpu_record.py write RECORDS.jsonl RAW_DIR --out benchmarks/results/gpu

`status` appends a row's status line (the script, after each row); a row's figures are the JSON line the benchmark
wrote itself under the same name (`benchmarks/train.py reference --record`). `write` merges them by row.
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
TAIL_LINES = 25
TIMED_OUT = (124, 137)  # `timeout`'s exit status, and a process killed by it


def status_of(exit_status: str) -> str:
    """'finished', 'failed', 'timed out' or 'skipped' from the exit status the script saw (or 'skipped')."""
    if exit_status == "skipped":
        return "skipped"
    code = int(exit_status)
    return "finished" if code == 0 else "timed out" if code in TIMED_OUT else "failed"


def status_line(name: str, exit_status: str, seconds: int, command: str, output: Path | None) -> dict:
    """A row's status as the script appends it: the status, the exit code, the seconds and the output's tail."""
    line = {"row": name, "command": command, "status": status_of(exit_status), "seconds": seconds}
    if exit_status != "skipped":
        line["exit"] = int(exit_status)
    if output is not None and output.is_file():
        kept = [text for text in output.read_text(errors="replace").splitlines() if "Warning" not in text]
        line["tail"] = "\n".join(kept[-TAIL_LINES:])
    return line


def verdict(row: dict) -> str:
    """PASS or FAIL against the row's goal, the status of a row that did not finish, or '' for a row without a goal."""
    if row.get("status", "finished") != "finished":
        return row["status"]
    if row["row"] == HEADLINE and "ours" in row:
        fast = row["ours"] * 60 >= PROTOCOL_STEPS_PER_MINUTE
        return "PASS" if fast and (row["ratio"] or 0) >= PROTOCOL_RATIO else "FAIL"
    if row["row"] == HEADLINE:
        return "FAIL"  # finished without its figures
    if row["row"] == "main":
        return "PASS" if row["seconds"] <= MAIN_SECONDS else "FAIL"
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
    """Each row once, in the order the script reached them: its figures' line and its status line merged."""
    rows: dict[str, dict] = {}
    lines = records.read_text().splitlines() if records.is_file() else []
    for line in filter(str.strip, lines):
        entry = json.loads(line)
        rows.setdefault(entry["row"], {}).update(entry)
    return [{**row, "verdict": verdict(row)} for row in rows.values()]


def markdown(rows: list[dict], device: str, date: str) -> str:
    lines = [f"# GPU checks, {date}, {device}", "",
             f"Goals: `{HEADLINE}` >= {PROTOCOL_STEPS_PER_MINUTE / 1e6:.0f}M env steps per minute and >= "
             f"{PROTOCOL_RATIO:.1f}x the pure-JAX yardstick in the same run; the main job to its end within "
             f"{MAIN_SECONDS} s.", "",
             "| row | status | ours (steps/s) | yardstick (steps/s) | ours / yardstick | seconds | verdict | command |",
             "|---|---|---|---|---|---|---|---|"]
    for row in rows:
        ours = f"{row['ours']:,.0f}" if row.get("ours") is not None else ""
        reference = f"{row['reference']:,.0f}" if row.get("reference") is not None else ""
        ratio = f"{row['ratio']:.3f}" if row.get("ratio") is not None else ""
        status = row.get("status", "") + (f" (exit {row['exit']})" if row.get("exit") else "")
        seconds = row.get("seconds", "") if row.get("status") != "skipped" else ""
        lines.append(f"| {row['row']} | {status} | {ours} | {reference} | {ratio} | {seconds} | {row['verdict']} | "
                     f"`{row['command']}` |")
    for row in rows:
        if row.get("status") in ("failed", "timed out"):
            lines += ["", f"## {row['row']}: {row['status']}, the end of its output", "", "```",
                      row.get("tail", ""), "```"]
    return "\n".join(lines) + "\n"


def write(records: Path, raw: Path, out: Path) -> None:
    device, date = device_name(raw), datetime.date.today().isoformat()
    stem = f"{date}_{re.sub(r'[^A-Za-z0-9]+', '_', device).strip('_')}"
    rows = read_rows(records)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{stem}.json").write_text(json.dumps({"date": date, "device": device, "rows": rows}, indent=1) + "\n")
    (out / f"{stem}.md").write_text(markdown(rows, device, date))
    shutil.copytree(raw, out / stem, dirs_exist_ok=True,
                    ignore=shutil.ignore_patterns("main", "bin"))  # the main job's run folder stays behind
    print(markdown(rows, device, date))
    print(f"record: {out / stem}.json, .md; outputs in {out / stem}/")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="command", required=True)
    status = commands.add_parser("status", help="append a row's status line to RECORDS")
    status.add_argument("records", type=Path)
    status.add_argument("name")
    status.add_argument("exit_status", help="the row's exit status, or 'skipped'")
    status.add_argument("seconds", type=int)
    status.add_argument("row_command", metavar="COMMAND")
    status.add_argument("--output", type=Path, help="the row's output, whose tail is kept")
    record = commands.add_parser("write", help="write the record of RECORDS and RAW_DIR")
    record.add_argument("records", type=Path, help="the rows' JSON lines")
    record.add_argument("raw", type=Path, help="the folder of the rows' outputs and device.txt")
    record.add_argument("--out", type=Path, default=Path("benchmarks/results/gpu"))
    args = parser.parse_args(argv)
    if args.command == "status":
        line = status_line(args.name, args.exit_status, args.seconds, args.row_command, args.output)
        with args.records.open("a") as file:
            file.write(json.dumps(line) + "\n")
    else:
        write(args.records, args.raw, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Two reports of the same protocol (e.g. seeds 0-4 and seeds 5-9) set claim by claim: whether any verdict flipped.

    python scripts/reproduce.py configs/protocols/reduced.yaml --sections planner --jobs 4 --out results/a \
        --results results/a/RESULTS.md
    python scripts/reproduce.py configs/protocols/reduced.yaml --sections planner --jobs 4 seed=5 --out results/b \
        --results results/b/RESULTS.md
    python scripts/compare_claims.py results/a/RESULTS.md results/b/RESULTS.md [--section Planner]

A claim is its family, learner and wording; its verdict the first words of its last cell ("holds", "does not hold",
"inconclusive", or another reading such as "not comparable"). Between the two reports a verdict stays the same,
softens (holds or does not hold, then inconclusive), firms (the other way) or flips (holds against does not hold): the
intervals over seeds promise that no claim flips between two sets of seeds. Prints a table of every claim in both
and exits 1 where one flipped. `--section TITLE` reads the claims of the section whose heading starts with TITLE
(those the run of that section wrote) instead of the table that gathers every section's.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

HOLDS, DOES_NOT_HOLD, INCONCLUSIVE = "holds", "does not hold", "inconclusive"
CLAIMS_TITLE = "## The paper's claims, here"
SECTION_CLAIMS = "<!-- claims -->"  # where a section's own claims table starts


def claims_text(path: Path, section: str | None) -> str:
    """The report's text from its gathered claims table on, or from the claims of the section headed `section`."""
    text = path.read_text()
    if section is None:
        if CLAIMS_TITLE not in text:
            raise ValueError(f"{path} has no claims table ({CLAIMS_TITLE!r}): a RESULTS.md that reproduce.py wrote")
        return text[text.index(CLAIMS_TITLE):]
    heading = f"\n## {section}"
    if heading not in text or SECTION_CLAIMS not in text[text.index(heading):]:
        raise ValueError(f"{path} has no section headed {section!r} with a claims table")
    within = text[text.index(heading):]
    return within[within.index(SECTION_CLAIMS):]


def read_claims(path: Path, section: str | None = None) -> dict[tuple[str, str, str], str]:
    """(family, learner, claim) -> verdict, from a report's gathered claims table, or from the claims of the section
    headed `section`."""
    claims = {}
    for line in claims_text(path, section).splitlines()[1:]:
        if claims and not line.startswith("|"):
            break  # the end of the table
        cells = [cell.strip() for cell in line.strip().strip("|").split(" | ")]
        if len(cells) == 5 and cells[0] != "family" and not set(cells[0]) <= set("-"):
            claims[tuple(cells[:3])] = verdict_of(cells[4])
    return claims


def verdict_of(cell: str) -> str:
    head = cell.split(";")[0].strip()
    return next((word for word in (DOES_NOT_HOLD, HOLDS, INCONCLUSIVE) if head.startswith(word)), head)


def change(first: str, second: str) -> str:
    decided = {HOLDS, DOES_NOT_HOLD}
    if first == second:
        return "same"
    if {first, second} == decided:
        return "FLIPPED"
    if first in decided and second == INCONCLUSIVE:
        return "softened"
    if first == INCONCLUSIVE and second in decided:
        return "firmed"
    return "changed"


def compare(first: dict, second: dict) -> list[tuple[tuple[str, str, str], str, str, str]]:
    """(claim, first verdict, second verdict, change) of every claim both reports hold, in the first's order."""
    return [(claim, verdict, second[claim], change(verdict, second[claim]))
            for claim, verdict in first.items() if claim in second]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("first", type=Path)
    parser.add_argument("second", type=Path)
    parser.add_argument("--section", metavar="TITLE", help="the claims of the section whose heading starts so")
    args = parser.parse_args(argv)
    try:
        first, second = read_claims(args.first, args.section), read_claims(args.second, args.section)
    except (OSError, ValueError) as error:
        print(f"compare_claims: error: {error}", file=sys.stderr)
        return 2
    rows = compare(first, second)
    print(f"| family | learner | claim | {args.first} | {args.second} | change |")
    print("|---|---|---|---|---|---|")
    for (family, learner, claim), a, b, changed in rows:
        print(f"| {family} | {learner} | {claim} | {a} | {b} | {changed} |")
    kinds = ("same", "softened", "firmed", "changed", "FLIPPED")
    counts = {kind: sum(row[3] == kind for row in rows) for kind in kinds}
    only = len(first) + len(second) - 2 * len(rows)
    print(f"\n{len(rows)} claims in both: " + ", ".join(f"{count} {kind}" for kind, count in counts.items())
          + (f"; {only} in one report only" if only else ""))
    return 1 if counts["FLIPPED"] else 0


if __name__ == "__main__":
    sys.exit(main())

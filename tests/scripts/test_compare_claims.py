"""Two reports of one protocol set claim by claim: a flipped verdict is found and fails the command."""

from tiny import script_module

compare_claims = script_module("compare_claims")

HEADER = ["# Results", "", "## The paper's claims, here", "",
          "| family | learner | claim | here: aggregate [95% interval over seeds] | at this budget |",
          "|---|---|---|---|---|"]


def report(path, verdicts):
    rows = [f"| MLP | scratch | claim {i} | +0.10 [-0.2, +0.4] (5 v 5 seeds) | {v} |" for i, v in enumerate(verdicts)]
    section = ["## A section", "", "<!-- claims -->", *HEADER[-2:], rows[0].replace("MLP", "GNN"), "<!-- /claims -->",
               "", "| not | a | claim | row | here |"]
    path.write_text("\n".join([*HEADER, *rows, "", *section]))
    return path


def test_a_flip_is_found_softening_is_not_and_the_command_fails_on_a_flip(tmp_path, capsys):
    first = report(tmp_path / "a.md", ["holds", "holds; per layout holds on 4 of 5 layouts", "inconclusive",
                                       "does not hold", "1.2e+06 steps, not 2e9: not comparable"])
    second = report(tmp_path / "b.md", ["inconclusive", "holds; per layout holds on 3, inconclusive on 2 of 5 layouts",
                                        "holds", "holds", "1.2e+06 steps, not 2e9: not comparable"])
    claims = compare_claims.read_claims(first)
    assert len(claims) == 5 and claims["MLP", "scratch", "claim 1"] == "holds"  # the section's table is not read
    changes = [row[3] for row in compare_claims.compare(claims, compare_claims.read_claims(second))]
    assert changes == ["softened", "same", "firmed", "FLIPPED", "same"]
    assert compare_claims.main([str(first), str(second)]) == 1
    assert "5 claims in both: 2 same, 1 softened, 1 firmed, 0 changed, 1 FLIPPED" in capsys.readouterr().out
    assert compare_claims.main([str(first), str(first)]) == 0
    assert compare_claims.main([str(first), str(tmp_path / "none.md")]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    assert compare_claims.read_claims(first, "A section") == {("GNN", "scratch", "claim 0"): "holds"}  # its own table
    assert compare_claims.main([str(first), str(second), "--section", "A sect"]) == 0
    assert "1 claims in both: 0 same, 1 softened" in capsys.readouterr().out
    assert compare_claims.main([str(first), str(second), "--section", "Elsewhere"]) == 2

"""The stranger benchmark, tiny: it plays both passes with both collectors and writes its table with the goal's
verdict."""

import strangers

from torch_kitchen.partners.conventions import STRANGER, Convention, Zoo, ZooMember, generator_settings, save_zoo


def test_the_stranger_benchmark_times_both_passes_and_writes_its_table(tmp_path):
    members = [ZooMember(Convention(name=name, move_order=order), STRANGER, 1.0, 1.0, {})
               for name, order in (("a", "NSEW"), ("b", "WENS"))]
    zoo = save_zoo(Zoo(0, 7, generator_settings(7), members), tmp_path / "zoo.yaml")
    out = tmp_path / "strangers.md"
    strangers.main(["--zoo", str(zoo), "--heldout", "1", "--rollouts", "1", "--workers", "1", "--out", str(out)])
    table = out.read_text()
    for collector in ("kitchen", "xla"):
        assert f"| {collector} | beside the strangers (and each alone) | 6 | 6 |" in table  # 2 strangers: 6 pairs
        assert f"| {collector} | beside the scripted cook (and it alone): reference | 3 | 3 |" in table
    assert "The stranger pass inside XLA: " in table
    assert "Goal: the stranger pass under 300 s with the default collector (xla): PASS" in table

"""Distillation's rounds benchmark over several seeds: its table decides each fitting against before's by an interval
over the seeds (crafted results: no distillation runs here)."""

import argparse
from pathlib import Path

import distill_rounds

from trainers.config.compose import load_config

ROOT = Path(__file__).resolve().parents[2]


def crafted(total: float, agreement: float) -> dict:
    return {"round": [total / 2] * 2, "fitting": [total / 4] * 2, "agreement": agreement, "total": total}


def test_each_fitting_is_decided_against_before_by_an_interval_over_the_seeds():
    config = load_config(ROOT / "configs" / "main.yaml", ["progress=false"])
    configs = {"before": config, "now": config, "faster": config}
    results = {"before": [crafted(120, a) for a in (0.66, 0.67, 0.68)],
               "now": [crafted(50, a) for a in (0.70, 0.69, 0.71)],  # above before's on every seed
               "faster": [crafted(40, a) for a in (0.60, 0.61, 0.62)]}  # below on every seed
    scores = {"before": [3.0, 3.5, 4.0], "now": [3.2, 3.6, 3.9], "faster": [3.4, 3.5, 3.6]}
    args = argparse.Namespace(config=ROOT / "configs" / "main.yaml", overrides=[], heldout=20, rollouts=4)
    table = distill_rounds.table(results, scores, configs, args)
    assert "seeds 0-2" in table
    assert "| now | xla | 3 | every round | 1024 steps | 25.0 25.0 | 12.5 12.5 | 50.0 | 2.40 | 0.700 | 3.57 |" in table
    assert "| now | +0.030 [" in table and "] holds | +0.067 [" in table  # agreement above; SP within noise
    assert "| faster | -0.060 [" in table and "] does not hold | +0.000 [" in table
    assert table.count("] inconclusive") == 2

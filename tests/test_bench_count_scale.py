"""bench/uq_count_scale.py: each count scale is paired against c = 1 by scene (issue 22's default evidence)."""
from __future__ import annotations

import pytest

ucs = pytest.importorskip("bench.uq_count_scale")


def _row(scene, run, c, cov95_err, nll=-1.0):
    return {"scene": scene, "run": run, "regime": "native", "scatter": "zero", "cov_mode": "relative",
            "count_scale": c, "cov95_err": cov95_err, "ause_rmse": 0.02, "nll": nll, "epi_ause_rmse": 0.03,
            "epi_spearman_sq": 0.4}


def test_paired_against_one_pairs_runs_then_averages_seeds_per_scene():
    rows = []
    for i, scene in enumerate("abcd"):
        for seed in (0, 1):
            rows += [_row(scene, f"s{seed}", 1.0, 0.05 + 0.01 * seed), _row(scene, f"s{seed}", 0.1, 0.03 + 0.01 * seed,
                                                                                  nll=-1.0 + 0.1 * (i % 2))]
    rows.append(_row("e", "s0", 0.1, 0.0))  # no c = 1 run to pair with: left out
    out = {r["metric"]: r for r in ucs.paired_against_one(rows)}
    assert out["cov95_err"]["mean_diff"] == pytest.approx(-0.02) and out["cov95_err"]["better"] == "4/4"
    assert out["cov95_err"]["n_scenes"] == 4 and out["cov95_err"]["p_two_sided"] == pytest.approx(0.125)
    assert out["nll"]["mean_diff"] == pytest.approx(0.05) and out["nll"]["better"] == "0/4"

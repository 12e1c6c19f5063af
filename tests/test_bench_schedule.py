"""bench/schedule.py: imported rows pair on deterministic metrics only, model − base tables, bad arguments."""
from __future__ import annotations

import json

import pytest

schedule = pytest.importorskip("bench.schedule")


def _run_dir(d, psnr, gaussians, time_s, block=None):
    d.mkdir(parents=True)
    m = {"psnr": psnr, "ssim": 0.9, "lpips": 0.1, "num_gaussians": gaussians, "train_time_s": time_s}
    if block:
        m["block_time_s"] = block
    (d / "metrics.json").write_text(json.dumps(m))
    (d / "curve.json").write_text(json.dumps({"points": [{"psnr": 20.0, "train_time_s": 1.0},
                                                         {"psnr": psnr, "train_time_s": time_s}]}))
    return d


def test_read_row_and_block_share(tmp_path):
    d = _run_dir(tmp_path / "r", 25.0, 100, 200.0, block={"niw": 2.0, "dp": 2.0})
    row, pts = schedule.read_row(d, "fox", "dpmm", "dash", 0, "run")
    assert row["block_pct"] == 2.0 and row["source"] == "run" and len(pts) == 2
    assert schedule.read_row(tmp_path / "missing", "fox", "dpmm", "dash", 0, "run") is None


def test_timed_metrics_pair_only_within_one_source():
    rows = []
    for scene, (dp, dt) in {"a": (0.1, -50.0), "b": (0.3, -30.0)}.items():
        rows.append({"scene": scene, "model": "niw", "variant": "constant", "seed": 0, "source": "constant",
                     "psnr": 25.0, "train_time_s": 300.0})
        rows.append({"scene": scene, "model": "niw", "variant": "dash", "seed": 0, "source": "run",
                     "psnr": 25.0 + dp, "train_time_s": 300.0 + dt})
    p = schedule.paired(rows, "dash", "constant", "psnr", True, "niw")
    assert p["n"] == 2 and p["mean"] == pytest.approx(0.2)
    t = schedule.paired(rows, "dash", "constant", "train_time_s", False, "niw")
    assert t["n"] == 0 and t["mean"] is None  # the two sides came from different sessions
    summary = schedule.summarize(rows, {}, ["dash", "constant"], "constant", ["niw"])
    assert summary[0]["time_ratio"] is None and summary[0]["paired"]["psnr"]["mean"] == pytest.approx(0.2)


def test_base_model_tables():
    rows = [{"scene": s, "model": m, "variant": "dash", "seed": 0, "source": "run", "num_gaussians": g, "psnr": 25.0,
             "ssim": 0.9, "lpips": 0.1, "train_time_s": 100.0, "block_pct": 1.0}
            for s, gs in {"a": (100, 60), "b": (200, 150), "c": (50, 45)}.items() for m, g in zip(("standard", "dpmm"), gs)]
    summary = schedule.summarize(rows, {}, ["dash"], "dash", ["standard", "dpmm"], base_model="standard")
    assert len(summary) == 1 and summary[0]["base_model"] == "standard"
    g = summary[0]["paired"]["num_gaussians"]
    assert g["mean"] == pytest.approx(-(40 + 50 + 5) / 3) and g["wins"] == 3  # fewer Gaussians is better
    text = "\n".join(schedule.markdown(rows, summary, ["dash"], "dash", 1, {}))
    assert "## dash: dpmm − standard" in text


@pytest.mark.parametrize("bad", ["constant", "constant=runs/{model}/s{seed}", "=runs/{scene}/s{seed}"])
def test_parse_imports_rejects(bad):
    with pytest.raises(SystemExit, match="--import"):
        schedule.parse_imports([bad])


def test_parse_imports():
    got = schedule.parse_imports(["c=r/{scene}/{model}/s{seed}", "c=q/{scene}/{model}/c/s{seed}"])
    assert got == {"c": ["r/{scene}/{model}/s{seed}", "q/{scene}/{model}/c/s{seed}"]}
    assert schedule.import_source(got["c"][1]) == "q/"


def test_active_view_schedule_compare():
    """bench/active_view_schedule.py: ranks and compute ratios of two studies' tables."""
    avs = pytest.importorskip("bench.active_view_schedule")
    t = lambda ps, total: {"scenes": ["fox"], "table": {p: {"psnr": v, "lpips": 0.1} for p, v in ps.items()},  # noqa: E731
                           "compute": {"fox/s0": {"phase1_s": total / 4, "round2_s": total / 2, "scoring_s": 0.0,
                                                  "total_s": total}}}
    res = avs.compare(t({"uniform": 21.0, "native": 22.0}, 100.0), t({"uniform": 22.5, "native": 22.0, "sh": 1.0}, 60.0),
                      "constant", "dash")
    assert [r["policy"] for r in res["rows"]] == ["uniform", "native"]
    assert res["rows"][0]["rank_constant"] == 2 and res["rows"][0]["rank_dash"] == 1
    assert res["compute"]["fox/s0"]["total_s"]["ratio"] == pytest.approx(0.6)
    assert res["compute"]["fox/s0"]["scoring_s"]["ratio"] is None
    assert "| uniform | 21.000 | 22.500 | +1.500 |" in avs.markdown(res)

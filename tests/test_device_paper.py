"""The paper stage of scripts/device_check.sh (issue 51, bench/device_paper.py): its plan, estimates and tables, and
its dry-run end to end on the CPU (b3dgs on renderer=cpu, the bare gsplat loop on gsplat's Python over the CPU
emulation of tests/gsplat_cpu.py), resumed by a second call."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench import device_paper as dp

ROOT = Path(__file__).resolve().parents[1]


def test_plan_puts_each_part_in_its_priority():
    keys = [r.key for r in dp.plan(["a", "b"], [0, 1], "b")]
    assert len(keys) == 2 * 2 * 3 + 2 * 4 + 1 == len(set(keys))
    # seed 0's parity, then standard beside the loop, then the other seeds, then NIW and DPMM at 7k, then 30k
    assert keys[:6] == [f"parity/{s}/{m}/s0" for s in "ab" for m in ("standard", "niw", "dpmm")]
    assert keys[6:10] == ["paper/a/standard/s0", "paper/a/gsplat_loop/s0", "paper/b/standard/s0", "paper/b/gsplat_loop/s0"]
    assert keys[10:16] == [f"parity/{s}/{m}/s1" for s in "ab" for m in ("standard", "niw", "dpmm")]
    assert keys[-1] == "long/b/standard/s0"
    assert [r.key for r in dp.plan(["a"], [0], None, parts=("paper",))] == [
        "paper/a/standard/s0", "paper/a/gsplat_loop/s0", "paper/a/niw/s0", "paper/a/dpmm/s0"]


def test_estimates_learn_from_the_runs_of_this_call():
    run = dp.Run("paper", "a", "dpmm", 0)
    prior = dp.estimate_s(run, [], None)
    assert prior == pytest.approx(dp.OVERHEAD_S + 7000 * dp.PRIOR_S_PER_STEP["paper"] * dp.FACTOR["dpmm"])
    std = {"part": "paper", "model": "standard", "wall_s": 70.0, "steps": 7000}
    assert dp.estimate_s(run, [std], None) == pytest.approx(70.0 * dp.FACTOR["dpmm"])
    same = {"part": "paper", "model": "dpmm", "wall_s": 90.0, "steps": 7000}
    assert dp.estimate_s(run, [std, same], None) == 90.0


def test_paper_check_needs_psnr_within_a_tenth_and_time_within_1_3x():
    def row(scene, model, psnr, t):
        return {"part": "paper", "scene": scene, "model": model, "psnr": psnr, "train_time_s": t}

    rows = [row("a", dp.LOOP, 25.0, 40.0), row("a", "standard", 24.95, 50.0), row("a", "dpmm", 25.2, 70.0),
            row("b", dp.LOOP, 25.0, 40.0), row("b", "standard", 24.8, 50.0),
            row("c", dp.LOOP, 25.0, 40.0), row("c", "standard", 25.5, 53.0)]
    side, checks = dp.paper_tables(rows, "paper")
    assert [c["met"] for c in checks] == [True, False, False]  # a: both; b: 0.2 dB below; c: 1.325x the time
    assert [r["model"] for r in side if r["scene"] == "a"] == [dp.LOOP, "standard", "dpmm"]
    assert next(r for r in side if r["model"] == "dpmm")["x_loop_time"] == 1.75


def test_overrides_select_the_protocols():
    gpu = dp.overrides(dp.Run("paper", "fox", dp.LOOP, 0), None)
    assert "experiment=paper" in gpu and "trainer.max_steps=7000" in gpu and "renderer=gsplat" in gpu
    assert "model=standard" in gpu  # the loop reads the standard model's scene, split and initial points
    quick = dp.overrides(dp.Run("parity", "fox", "dpmm", 1), None)
    assert "experiment=study" in quick and "seed=1" in quick and not any("max_steps" in o for o in quick)
    assert "posterior=[niw,dp,noise,opacity,color]" in quick  # the archived blocks, as bench.train pins them
    dry = dp.overrides(dp.Run("paper", "fox", "standard", 0), "cpu")
    assert "renderer=cpu" in dry and "data.max_side=32" in dry and "trainer.max_steps=12" in dry
    assert dp.card_name("cpu") == "cpu"


def _stage(out: Path, work: Path, *extra: str, timeout: int = 1500) -> subprocess.CompletedProcess:
    env = dict(os.environ, OUT=str(out), DEADLINE="1400", PYTHONPATH=str(ROOT),
               PAPER_ARGS=" ".join(["--work", str(work), *extra]))
    return subprocess.run(["bash", "scripts/device_check.sh", "paper", "--dry-run"], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_dry_run_deadline_skips_and_lists(tmp_path):
    """A deadline that no run fits: nothing trains, every planned run is listed as skipped in both files."""
    res = subprocess.run([sys.executable, "-m", "bench.device_paper", "--dry-run", "--scenes", "synthetic",
                          "--deadline-s", "0", "--work", str(tmp_path / "w"), "--out", str(tmp_path / "o")],
                         cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True, text=True,
                         timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    for root in (tmp_path / "w" / "results", tmp_path / "o"):
        data = json.loads((root / "device_cpu.json").read_text())
        assert data["runs"] == [] and len(data["skipped"]) == 3 * 2 + 4 + 1
        assert "Not run in this call" in (root / "device_cpu.md").read_text()
    assert not (tmp_path / "w" / "runs").exists()


@pytest.mark.slow
def test_dry_run_end_to_end_and_resumed(tmp_path):
    """``bash scripts/device_check.sh paper --dry-run`` on the synthetic scene: every part runs, the JSON holds the
    parity ratios per scene with both seeds and the loop's row beside b3dgs's; a second call keeps every run."""
    out, work = tmp_path / "out", tmp_path / "work"
    res = _stage(out, work, "--scenes", "synthetic")
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    data = json.loads((out / "device_cpu.json").read_text())
    assert {"card", "dry_run", "machine", "protocols", "ratios", "paper_7k", "paper_checks", "long_30k", "runs",
            "skipped"} <= set(data)
    assert data["card"] == "cpu" and data["dry_run"] is True and data["skipped"] == []
    per_scene = [r for r in data["ratios"] if r["scene"] == "synthetic"]
    assert {r["model"] for r in per_scene} == {"niw", "dpmm"}
    assert all(r["seeds"] == 2 and r["seed_list"] == [0, 1] for r in per_scene)
    assert {r["model"] for r in data["ratios"] if r["scene"] == "mean over scenes"} == {"niw", "dpmm"}
    side = {r["model"]: r for r in data["paper_7k"]}
    assert set(side) == {dp.LOOP, "standard", "niw", "dpmm"}
    loop = side[dp.LOOP]
    assert loop["psnr"] > 5 and loop["num_gaussians"] > 0 and loop["train_time_s"] > 0 and loop["steps"] == 12
    assert side["standard"]["x_loop_time"] > 0 and len(data["paper_checks"]) == 1
    assert [r["steps"] for r in data["long_30k"]] == [16]
    assert len(data["runs"]) == 11
    loop_metrics = json.loads((work / "runs" / "paper" / "synthetic" / dp.LOOP / "s0" / "loop.json").read_text())
    assert loop_metrics["num_test_views"] > 0 and loop_metrics["num_initial"] <= dp.DRY["init_points"]
    md = (out / "device_cpu.md").read_text()
    assert "gsplat_loop" in md and "(a) Training time against standard" in md and "(c) Standard at 30k" in md
    assert (out / "log.txt").is_file()

    again = _stage(out, work, "--scenes", "synthetic", timeout=600)  # the warm machine's second call
    assert again.returncode == 0, again.stderr[-3000:]
    assert "warm-up" not in again.stdout  # nothing left to train
    data2 = json.loads((out / "device_cpu.json").read_text())
    assert data2["runs"] == data["runs"]

"""bench.reproduce: every committed table is rebuilt from its archive (or listed with the reason it cannot be), the
rebuilt tables equal the committed ones, and an altered archived record makes the check fail with its difference."""
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from bench.reproduce import (NOT_REBUILDABLE, REBUILDS, TOLERATED, _comparable, committed_tables,
                             first_json_difference, missing_scenes)

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "bench" / "results"


def reproduce(*args: str, timeout: int = 1800) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, "-m", "bench.reproduce", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=timeout)


def test_every_committed_table_is_rebuilt_or_says_why_not():
    rebuilt = [t for rb in REBUILDS.values() for t in rb.tables]
    assert len(rebuilt) == len(set(rebuilt)) and not set(rebuilt) & set(NOT_REBUILDABLE)
    assert set(committed_tables()) == set(rebuilt) | set(NOT_REBUILDABLE)
    assert all(len(why) > 30 for why in NOT_REBUILDABLE.values())
    # every rebuild writes under the temporary root, never where it reads the committed results
    for rb in REBUILDS.values():
        out = [a for a in rb.command if "{out}" in a]
        assert out and all(a.startswith("{out}") for a in out), rb.command
    # the JSON comparison tolerates exactly the listed top-level keys, and names the first differing path
    assert set(TOLERATED) == {"/machine", "/config/out"}
    assert first_json_difference({"rows": [{"psnr": 1.0}]}, {"rows": [{"psnr": 1.0}]}) is None
    assert first_json_difference({"rows": [{"psnr": 1.0}]}, {"rows": [{"psnr": 1.5}]}) == \
        ".json /rows/0/psnr: committed 1.0, rebuilt 1.5"
    assert first_json_difference({"a": 1}, {"a": 1.0}) == ".json /a: committed 1, rebuilt 1.0"
    # a run path records where the checkout was (the report's /work/main/...), compared from bench/results/ on
    a = {"machine": {"threads": 2}, "config": {"out": "/x/r", "seed": 0},
         "runs": ["/work/main/bench/results/runs/f/s0"]}
    b = {"machine": {"threads": 1}, "config": {"out": "/tmp/r", "seed": 0}, "runs": [str(RESULTS / "runs/f/s0")]}
    assert first_json_difference(_comparable(a, RESULTS), _comparable(b, RESULTS)) is None
    b["runs"] = ["/work/main/bench/results/runs/f/s1"]
    assert first_json_difference(_comparable(a, RESULTS), _comparable(b, RESULTS)) == \
        '.json /runs/0: committed "bench/results/runs/f/s0", rebuilt "bench/results/runs/f/s1"'


def _check_all_identical(res: subprocess.CompletedProcess, names: list[str]) -> None:
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    for t in names:
        assert f"  {t}: identical" in res.stdout, (t, res.stdout[-4000:])


def test_the_quick_tables_reproduce_from_the_committed_archive():
    """The rebuilds not marked slow (about a minute on two cores): each table identical to the committed one."""
    res = reproduce("--skip-slow", "--jobs", "2")  # two at once: the tables do not depend on it
    _check_all_identical(res, [t for rb in REBUILDS.values() if not rb.slow for t in rb.tables])
    order = [ln.split(":")[0].strip() for ln in res.stdout.splitlines() if ln.startswith("  ") and "identical" in ln]
    assert order == [t for rb in REBUILDS.values() if not rb.slow for t in rb.tables]  # reported in the listed order


@pytest.mark.slow
def test_the_slow_tables_reproduce_from_the_committed_archive():
    """The report, the active-view tables and the counts (minutes on two cores; most read the scenes' cameras)."""
    slow = {n: rb for n, rb in REBUILDS.items() if rb.slow and not (rb.scenes and missing_scenes())}
    if not slow:
        pytest.skip(missing_scenes())
    res = reproduce("--only", *slow, "--jobs", "2", timeout=3600)
    _check_all_identical(res, [t for rb in slow.values() for t in rb.tables])


def _snapshot(root: Path) -> dict:
    return {p.relative_to(root).as_posix(): (p.stat().st_size, p.stat().st_mtime_ns) for p in root.rglob("*")}


def test_an_altered_archived_record_fails_the_check_with_its_difference(tmp_path):
    """A copy of the committed results reproduces, and nothing is written into it; one archived run's PSNR altered
    there makes bench.reproduce exit 1 and name the table and the first line that changed."""
    res_dir = tmp_path / "results"
    shutil.copytree(RESULTS / "schedule_screen3_runs", res_dir / "schedule_screen3_runs")
    for f in ("schedule_screen3.md", "schedule_screen3.json", "count_cost.md", "count_cost.json"):
        shutil.copy2(RESULTS / f, res_dir / f)
    before = _snapshot(res_dir)
    res = reproduce("--only", "schedule_screen3", "count_cost", "--results", str(res_dir), "--jobs", "2")
    _check_all_identical(res, ["schedule_screen3", "count_cost"])
    assert _snapshot(res_dir) == before  # the rebuilds wrote under their temporary root only

    m = res_dir / "schedule_screen3_runs" / "fox" / "standard" / "dash" / "s0" / "metrics.json"
    rec = json.loads(m.read_text())
    assert round(rec["psnr"], 3) == 25.539  # the committed table's row
    m.write_text(json.dumps({**rec, "psnr": 31.25}))
    out = tmp_path / "out"
    res = reproduce("--only", "schedule_screen3", "count_cost", "--results", str(res_dir), "--out", str(out), "--jobs",
                    "2")
    assert res.returncode == 1, res.stdout[-3000:]
    assert "  count_cost: identical" in res.stdout
    assert "1 of 2 tables differ from the committed ones: schedule_screen3" in res.stderr
    line = next(ln for ln in (out / "reproduce.md").read_text().splitlines() if ln.startswith("| schedule_screen3 |"))
    assert "| **no** | .md line " in line and "committed '" in line and "rebuilt '" in line, line
    rebuilt = (out / "schedule_screen3.md").read_text()
    assert "| fox | standard | dash | 0 | 31.250 |" in rebuilt


def test_floats_equal_to_round_off_are_identical_and_said_a_float32_gap_is_not():
    """Another kind of CPU may give a float64 LAPACK result's last bits differently: such floats count as equal and
    are collected (the row says how many and how close); a difference at float32 round-off (the camera centres'
    1e-7 of this session's new machine) is still a difference, and so is 0 against a tiny number."""
    from bench.reproduce import ROUNDOFF

    seen: list = []
    a = {"ood": {"views": [{"support": 0.20856518864409718}, {"support": 0.5}]}}
    b = {"ood": {"views": [{"support": 0.20856518864409718 * (1 + 4e-16)}, {"support": 0.5}]}}
    assert first_json_difference(a, b, roundoff=seen) is None
    assert [p for p, _, _ in seen] == ["/ood/views/0/support"] and ROUNDOFF <= 1e-12
    b["ood"]["views"][0]["support"] = 0.20856517312148667
    assert first_json_difference(a, b) == \
        ".json /ood/views/0/support: committed 0.20856518864409718, rebuilt 0.20856517312148667"
    assert first_json_difference({"d": 0.0}, {"d": 1e-300}) is not None

"""Exact resume: a run interrupted at a random step, then killed inside its final evaluation and final writes,
and resumed with ``resume=auto`` each time, ends bit for bit like the uninterrupted run (metrics.json apart
from its wall-clock fields, curve.json, point_cloud.ply), with no temp file left.

The kills come from a test callback added through the configurable callbacks (``tests/kill_hooks.py``): the
training process sends itself a signal right after step K, after training (``final``) or once the temp file
of ``<file>`` is written but before its rename (``write:<file>``); the signal is SIGKILL (a real ``kill -9``:
no handler, no cleanup) unless TERM or INT is named. Each run is first interrupted (SIGTERM / SIGINT: a checkpoint at
that step, exit 143 / 130, one line) right after one of steps 14..20, then killed at a random later step,
then twice after the last checkpoint. The steps are printed on failure. A finished run is left untouched
by ``resume=auto``.
"""
import json
import random
import signal
import subprocess
import sys
from pathlib import Path

import pytest

import torch

from tests.kill_hooks import kill_args

ROOT = Path(__file__).resolve().parents[1]
STEPS, CKPT_EVERY, N_TRAIN = 60, 7, 14
BASE = ["data.max_side=32", "+data.n_views=16", f"trainer.max_steps={STEPS}", "trainer.eval_every=20",
        f"trainer.checkpoint_every={CKPT_EVERY}", "trainer.checkpoint_every_s=0", "trainer.enable_progress_bar=false",
        "logger=none", "strategy.refine_start=10", "strategy.refine_every=10", "strategy.refine_stop=50",
        "model.sh_increase_every=20", "seed=3", "threads=1"]
#: wall-clock fields, the only ones allowed to differ
TIMING = {"train_time_s", "render_fps", "block_time_s", "posterior_pass_s"}


def _train(run_dir: Path, extra: list[str], kill_at: int | str | None = None, sig: str = "KILL"
           ) -> subprocess.CompletedProcess:
    """``kill_at``: a step, or a point of :class:`tests.kill_hooks.KillAt` (``final``, ``write:<file>``)."""
    if kill_at is not None:
        extra = [*extra, *(kill_args(step=kill_at, sig=sig) if isinstance(kill_at, int)
                           else kill_args(point=kill_at, sig=sig))]
    cmd = [sys.executable, "-m", "b3dgs.train", *BASE, *extra, f"hydra.run.dir={run_dir}"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT)


def _strip(obj):
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in TIMING}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


def _files(d: Path) -> dict:
    return {str(p.relative_to(d)): (p.stat().st_mtime_ns, p.read_bytes()) for p in sorted(d.rglob("*")) if p.is_file()}


#: per model: the interrupting signal (and its exit code), then two kill points after the last checkpoint
PLANS = {"standard": ("TERM", 143, ["write:point_cloud.ply", "write:metrics.json"]),
         "dpmm": ("INT", 130, ["final", "write:{render}"])}


@pytest.mark.slow
@pytest.mark.parametrize("model", ["standard", "dpmm"])
def test_kill9_then_resume_is_bit_identical(tmp_path, model):
    extra = [f"model={model}"]
    ref, cut = tmp_path / "ref", tmp_path / "cut"
    res = _train(ref, extra)
    assert res.returncode == 0, res.stderr[-3000:]
    sig, code, finals = PLANS[model]
    render = sorted(p.name for p in (ref / "renders").iterdir())[0]
    finals = [f.format(render=render) for f in finals]

    rng = random.Random(f"resume-{model}")  # fixed kill steps per model: a failure reproduces
    k1 = rng.randint(2 * CKPT_EVERY, 3 * CKPT_EVERY - 1)
    k2 = rng.randint(k1 + 1, STEPS - 1)
    k = (k1, k2)
    # SIGTERM / SIGINT: a checkpoint at that very step, one line, exit 143 / 130
    res = _train(cut, extra, kill_at=k1, sig=sig)
    assert res.returncode == code, (k, res.returncode, res.stderr[-3000:])
    assert res.stderr.strip().splitlines()[-1] == (f"b3dgs-train: interrupted by SIG{sig} at step {k1}; "
                                                   "resume with resume=auto"), res.stderr[-3000:]
    assert torch.load(cut / "checkpoints" / "last.ckpt", weights_only=False)["global_step"] == k1
    assert not (cut / "metrics.json").exists(), k  # not done
    res = _train(cut, extra + ["resume=auto"], kill_at=k2)
    assert res.returncode == -signal.SIGKILL, (k, res.returncode, res.stderr[-3000:])
    for point in finals:  # after the last checkpoint: inside the final evaluation and the final writes
        res = _train(cut, extra + ["resume=auto"], kill_at=point, sig="INT" if point == "final" else "KILL")
        if point == "final":  # Ctrl-C during the final evaluation: one line, exit 130
            assert res.returncode == 130 and res.stderr.strip().splitlines()[-1] == (
                f"b3dgs-train: interrupted by SIGINT at step {STEPS}; resume with resume=auto"), res.stderr[-3000:]
        else:
            assert res.returncode == -signal.SIGKILL, (k, point, res.returncode, res.stderr[-3000:])
            assert list(cut.rglob(f".{point[6:]}.*.tmp")), point  # the kill left the temp file
        assert not (cut / "metrics.json").exists(), (k, point)
    res = _train(cut, extra + ["resume=auto"])
    assert res.returncode == 0, (k, res.stderr[-3000:])
    assert not list(cut.rglob("*.tmp")), "stale temp files were not removed"

    a, b = (json.loads((d / "metrics.json").read_text()) for d in (ref, cut))
    assert a["steps"] == b["steps"] == STEPS and a["num_train_views"] == N_TRAIN
    assert a["added"] and a["removed"]  # densification counters survive every re-entry
    assert _strip(a) == _strip(b), f"killed after steps {k}, then at {finals}"
    assert set(a["block_time_s"]) == set(b["block_time_s"])
    ca, cb = (json.loads((d / "curve.json").read_text())["points"] for d in (ref, cut))
    assert _strip(ca) == _strip(cb), f"killed after steps {k}"
    assert (ref / "point_cloud.ply").read_bytes() == (cut / "point_cloud.ply").read_bytes(), f"killed after steps {k}"
    assert sorted(p.name for p in (cut / "checkpoints").iterdir()) == ["last.ckpt"]

    # a finished run is immutable: resume=auto says so, exits 0 and rewrites nothing
    before = _files(cut)
    res = _train(cut, extra + ["resume=auto"])
    assert res.returncode == 0 and "holds a finished run" in res.stdout + res.stderr, res.stderr[-3000:]
    assert _files(cut) == before


def test_a_checkpoint_changed_on_disk_is_refused_on_resume_and_on_load(tmp_path):
    """Issue 46 (class: a checkpoint whose bytes changed since it was written, on every path that reads it): a
    checkpoint records a digest of its parameters, optimizer state and plugin states when written; a resume and a
    load for evaluation recompute it and refuse a checkpoint edited on disk (here one Adam moment, which the metrics'
    parameter digest does not cover) in one line, before anything is trained or written."""
    from b3dgs.errors import B3dgsError
    from b3dgs.runs import load_run

    d = tmp_path / "run"
    r = _train(d, ["trainer.max_steps=12", "trainer.checkpoint_every=100"], kill_at=5, sig="TERM")
    assert r.returncode == 143, r.stderr[-2000:]
    last = d / "checkpoints" / "last.ckpt"
    ck = torch.load(last, map_location="cpu", weights_only=False)
    assert ck["b3dgs"]["content"]["parts"] == ["state_dict", "optimizer_states"]
    load_run(d, checkpoint=last)  # untouched: loads (an unfinished run: its checkpoint named)
    state = ck["optimizer_states"][0]["state"]
    first = next(iter(state.values()))
    first["exp_avg"].view(-1)[0] += 1.0
    torch.save(ck, last)
    before = _files(d)
    r = _train(d, ["trainer.max_steps=12", "trainer.checkpoint_every=100", "resume=auto"])
    assert r.returncode == 2, r.stderr[-2000:]
    line = r.stderr.strip().splitlines()[-1]
    assert "changed since it was written" in line and "(fix:" in line, line
    assert {k: v for k, v in _files(d).items() if not k.endswith(".log")} == \
        {k: v for k, v in before.items() if not k.endswith(".log")}  # nothing trained or written
    with pytest.raises(B3dgsError, match="changed since it was written"):
        load_run(d, checkpoint=last)

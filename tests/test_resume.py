"""Exact resume: a run killed by SIGKILL at a random step and resumed with ``resume=auto`` ends bit for bit
like the uninterrupted run (metrics.json apart from its wall-clock fields, curve.json, point_cloud.ply).

The kill is the test hook of :class:`b3dgs.callbacks.RunCheckpoint`: ``B3DGS_TEST_KILL_AT_STEP=K`` makes the
training process ``os.kill`` itself with SIGKILL right after step K (a real ``kill -9``: no handler, no
cleanup). Each run is killed twice: first right after one of steps 14..20, so that it resumes from the
checkpoint at step 14, an epoch boundary (14 train views); then at a random later step. The steps are
printed on failure.
"""
import json
import os
import random
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from b3dgs.callbacks import KILL_ENV

STEPS, CKPT_EVERY, N_TRAIN = 60, 7, 14
BASE = ["data.max_side=32", "+data.n_views=16", f"trainer.max_steps={STEPS}", "trainer.eval_every=20",
        f"trainer.checkpoint_every={CKPT_EVERY}", "trainer.checkpoint_every_s=0", "trainer.progress_bar=false",
        "logger=none", "strategy.refine_start=10", "strategy.refine_every=10", "strategy.refine_stop=50",
        "model.sh_increase_every=20", "seed=3", "threads=1"]
#: wall-clock fields, the only ones allowed to differ
TIMING = {"train_time_s", "render_fps", "block_time_s"}


def _train(run_dir: Path, extra: list[str], kill_at: int | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env.pop(KILL_ENV, None)
    if kill_at is not None:
        env[KILL_ENV] = str(kill_at)
    cmd = [sys.executable, "-m", "b3dgs.train", *BASE, *extra, f"hydra.run.dir={run_dir}"]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env)


def _strip(obj):
    if isinstance(obj, dict):
        return {k: _strip(v) for k, v in obj.items() if k not in TIMING}
    if isinstance(obj, list):
        return [_strip(v) for v in obj]
    return obj


@pytest.mark.parametrize("model", ["standard", "dpmm"])
def test_kill9_then_resume_is_bit_identical(tmp_path, model):
    extra = [f"model={model}"]
    ref, cut = tmp_path / "ref", tmp_path / "cut"
    res = _train(ref, extra)
    assert res.returncode == 0, res.stderr[-3000:]

    rng = random.Random()
    k1 = rng.randint(2 * CKPT_EVERY, 3 * CKPT_EVERY - 1)  # resumes from step 14 = N_TRAIN: an epoch boundary
    k2 = rng.randint(k1 + 1, STEPS - 1)
    k = (k1, k2)
    res = _train(cut, extra, kill_at=k1)
    assert res.returncode == -signal.SIGKILL, (k, res.returncode, res.stderr[-3000:])
    assert (cut / "checkpoints" / "last.ckpt").exists(), k
    assert not (cut / "metrics.json").exists(), k  # not done
    res = _train(cut, extra + ["resume=auto"], kill_at=k2)
    assert res.returncode == -signal.SIGKILL, (k, res.returncode, res.stderr[-3000:])
    res = _train(cut, extra + ["resume=auto"])
    assert res.returncode == 0, (k, res.stderr[-3000:])

    a, b = (json.loads((d / "metrics.json").read_text()) for d in (ref, cut))
    assert a["steps"] == b["steps"] == STEPS and a["num_train_views"] == N_TRAIN
    assert _strip(a) == _strip(b), f"killed after steps {k}"
    assert set(a["block_time_s"]) == set(b["block_time_s"])
    ca, cb = (json.loads((d / "curve.json").read_text())["points"] for d in (ref, cut))
    assert _strip(ca) == _strip(cb), f"killed after steps {k}"
    assert (ref / "point_cloud.ply").read_bytes() == (cut / "point_cloud.ply").read_bytes(), f"killed after steps {k}"
    assert sorted(p.name for p in (cut / "checkpoints").iterdir()) == ["last.ckpt"]

"""End-to-end training through the Hydra app: run dir contents, PSNR bound, run-dir guard, resume checks,
multirun (the kill -9 exact-resume test is tests/test_resume.py)."""
import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.inproc import train_here

QUICK = ["data.max_side=64", "+data.n_views=24", "trainer.enable_progress_bar=false", "logger=none"]


def run_train(tmp_path: Path, overrides: list[str]) -> dict:
    return train_here(tmp_path, overrides)


def test_short_training_improves_and_writes_run_dir(tmp_path):
    m = run_train(tmp_path, QUICK + ["trainer.max_steps=300", "trainer.eval_every=100", "strategy.refine_start=100",
                                     "strategy.refine_stop=250", "strategy.refine_every=50"])
    # stated bound: 300 steps on the 64px synthetic scene reach well above a blank image (~11 dB)
    assert m["psnr"] > 20.0, m["psnr"]
    for name in ["metrics.json", "curve.json", "curve.png", "point_cloud.ply", "checkpoints/last.ckpt"]:
        assert (tmp_path / name).exists(), name
    assert list((tmp_path / "renders").glob("*.png"))
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    for key in ["psnr", "ssim", "lpips", "num_gaussians", "train_time_s", "render_fps", "steps", "seed", "per_view"]:
        assert key in metrics
    assert metrics["steps"] == 300
    assert metrics["lpips"] is not None or metrics["lpips_reason"]
    # where it ran: bits reproduce on the same kind of machine, so the run says which kind
    assert metrics["machine"]["torch"] == torch.__version__
    assert metrics["machine"]["cpu_capability"] == torch.backends.cpu.get_cpu_capability()
    curve = json.loads((tmp_path / "curve.json").read_text())["points"]
    assert [p["step"] for p in curve] == [100, 200, 300]
    assert curve[-1]["psnr"] > curve[0]["psnr"]
    assert all(b["train_time_s"] > a["train_time_s"] for a, b in zip(curve, curve[1:]))


def test_run_dir_guard_resume_identity_and_eval_check(tmp_path):
    """One run dir: the final checkpoint is always last.ckpt; a second fresh run is refused; a resume
    with another max_steps / model / scene is refused and leaves config.yaml alone; resume=auto of a
    finished run keeps its results; b3dgs-eval refuses a last.ckpt that is not the metrics.json model;
    overwrite=true replaces the run."""
    from b3dgs.runs import load_run

    over = QUICK + ["trainer.max_steps=60", "trainer.checkpoint_every=30", "trainer.eval_every=30",
                    "trainer.keep_checkpoints=true", "trainer.save_renders=false"]
    m = run_train(tmp_path, over)
    ck = torch.load(tmp_path / "checkpoints" / "last.ckpt", weights_only=False)
    assert ck["global_step"] == 60 and m["checkpoint"]["global_step"] == 60
    assert ck["b3dgs"]["identity"]["model"] == "standard"
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["last.ckpt", "step30.ckpt", "step60.ckpt"]
    config = (tmp_path / "config.yaml").read_text()

    with pytest.raises(ValueError, match=r"already holds a run .*fix: pass resume=auto"):
        run_train(tmp_path, over)
    with pytest.raises(ValueError, match=r"trainer.max_steps=60, this run has trainer.max_steps=90 \(fix: pass trainer.max_steps=60"):
        run_train(tmp_path, [o for o in over if "max_steps" not in o] + ["trainer.max_steps=90", "resume=auto"])
    with pytest.raises(ValueError, match=r"model=standard run, this run is model=niw"):
        run_train(tmp_path, over + ["model=niw", "resume=auto"])
    with pytest.raises(ValueError, match=r"another scene"):
        run_train(tmp_path, [o for o in over if "n_views" not in o] + ["+data.n_views=20", "resume=auto"])
    with pytest.raises(ValueError, match=r"contradict"):
        run_train(tmp_path, over + ["overwrite=true", "resume=auto"])
    assert (tmp_path / "config.yaml").read_text() == config and (tmp_path / "metrics.json").exists()

    m2 = run_train(tmp_path, over + ["resume=auto"])  # finished: nothing left to train, same results
    assert m2["steps"] == 60 and m2["psnr"] == m["psnr"] and m2["checkpoint"] == m["checkpoint"]
    curve = json.loads((tmp_path / "curve.json").read_text())["points"]
    assert [p["step"] for p in curve] == [30, 60]
    assert not list((tmp_path / "checkpoints").glob("last-v*"))

    run = load_run(tmp_path)
    assert run.module.num_gaussians == m["num_gaussians"]
    (tmp_path / "checkpoints" / "step30.ckpt").replace(tmp_path / "checkpoints" / "last.ckpt")  # a stale model
    with pytest.raises(ValueError, match=r"last.ckpt is not the model of .*metrics.json: global_step 30"):
        load_run(tmp_path)

    m3 = run_train(tmp_path, over + ["overwrite=true", "trainer.max_steps=30", "trainer.keep_checkpoints=false"])
    assert m3["steps"] == 30
    assert sorted(p.name for p in (tmp_path / "checkpoints").iterdir()) == ["last.ckpt"]
    assert load_run(tmp_path).module.num_gaussians == m3["num_gaussians"]


def test_checkpoints_bounded_by_time(monkeypatch):
    """trainer.checkpoint_every_s saves last.ckpt between the step multiples, once the time has passed (a fake
    clock: the test does not depend on how fast the machine is)."""
    import time

    from b3dgs.callbacks import RunCheckpoint

    clock = [100.0]
    monkeypatch.setattr(time, "monotonic", lambda: clock[0])

    class FakeTrainer:
        global_step = 0
        saved: list = []

        def save_checkpoint(self, path, weights_only=None):
            self.saved.append(self.global_step)

    t, cb = FakeTrainer(), RunCheckpoint(Path("/nonexistent"), every_n_steps=1000, every_s=0.05)
    cb.on_train_start(t, None)
    for step in range(1, 4):
        t.global_step = step
        cb.on_train_batch_end(t, None, None, None, step - 1)
    assert t.saved == []
    clock[0] += 0.06
    t.global_step = 4
    cb.on_train_batch_end(t, None, None, None, 3)
    assert t.saved == [4]
    cb.on_train_end(t, None)  # already saved at this step
    assert t.saved == [4]
    t.global_step = 5
    cb.on_train_end(t, None)
    assert t.saved == [4, 5]


def test_multirun_two_seeds(tmp_path):
    cmd = [sys.executable, "-m", "b3dgs.train", "-m", "seed=0,1", "trainer.max_steps=20", "trainer.eval_every=10",
           "data.max_side=32", "+data.n_views=16", "trainer.enable_progress_bar=false", "logger=none",
           f"hydra.sweep.dir={tmp_path}", "hydra.sweep.subdir=${seed}"]
    res = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    m0 = json.loads((tmp_path / "0" / "metrics.json").read_text())
    m1 = json.loads((tmp_path / "1" / "metrics.json").read_text())
    assert (m0["seed"], m1["seed"]) == (0, 1)
    assert m0["psnr"] != m1["psnr"]  # independent runs


def test_pure_torch_renderer_trains_like_the_cpu_backend(tmp_path):
    """renderer=torch (pure PyTorch projection, binning, rasterizer and SSIM) follows the same
    trajectory as the C++ path up to float32 rounding."""
    over = ["data.max_side=32", "+data.n_views=16", "trainer.enable_progress_bar=false", "logger=none", "trainer.max_steps=40",
            "trainer.eval_every=20", "strategy.refine_start=10", "strategy.refine_every=10", "strategy.refine_stop=30",
            "trainer.save_renders=false"]
    a = run_train(tmp_path / "cpu", over + ["renderer=cpu"])
    b = run_train(tmp_path / "torch", over + ["renderer=torch"])
    assert b["psnr"] > 12.0
    assert abs(a["psnr"] - b["psnr"]) < 0.3, (a["psnr"], b["psnr"])
    assert abs(a["num_gaussians"] - b["num_gaussians"]) <= 0.05 * a["num_gaussians"]

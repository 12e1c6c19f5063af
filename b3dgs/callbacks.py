"""Lightning callbacks: training clock, PSNR-vs-time curve, atomic checkpoint writing."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Optional

import lightning as L
import torch
from lightning.pytorch.plugins.io import TorchCheckpointIO

from b3dgs.device import timed_clock
from b3dgs.io import atomic_path, write_json

log = logging.getLogger(__name__)


class AtomicCheckpointIO(TorchCheckpointIO):
    """Checkpoints are written to a temporary file and renamed, so a crash never leaves half a file."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Optional[Any] = None) -> None:
        with atomic_path(path) as tmp:
            torch.save(checkpoint, tmp)


class CurveCallback(L.Callback):
    """Accumulates training wall-clock time (evaluation excluded) and records test PSNR and the
    Gaussian count every ``eval_every`` steps: the user's "error against run time" curve."""

    def __init__(self, cameras, eval_every: int, out_dir: Path, max_eval_views: Optional[int] = None, log_images: bool = True):
        self.cameras = list(cameras)[: max_eval_views] if max_eval_views else list(cameras)
        self.eval_every = int(eval_every)
        self.out_dir = Path(out_dir)
        self.log_images = log_images
        self.train_time_s = 0.0
        self.points: list[dict] = []
        self._t0: Optional[float] = None

    def state_dict(self) -> dict:
        return {"train_time_s": self.train_time_s, "points": self.points}

    def load_state_dict(self, state_dict: dict) -> None:
        self.train_time_s = float(state_dict.get("train_time_s", 0.0))
        self.points = list(state_dict.get("points", []))

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        self._t0 = timed_clock(pl_module.device)  # CUDA: queued work is waited for before reading the clock

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        if self._t0 is not None:
            self.train_time_s += timed_clock(pl_module.device) - self._t0
            self._t0 = None
        step = trainer.global_step
        if self.eval_every > 0 and step % self.eval_every == 0 and self.cameras:
            self.evaluate(trainer, pl_module, step)

    def on_train_end(self, trainer, pl_module) -> None:
        step = trainer.global_step
        if self.cameras and (not self.points or self.points[-1]["step"] != step):
            self.evaluate(trainer, pl_module, step)
        self.write()

    @torch.no_grad()
    def evaluate(self, trainer, pl_module, step: int) -> None:
        from b3dgs.metrics.image import psnr

        vals = []
        first = None
        for cam in self.cameras:
            pred = pl_module.render_eval(cam).cpu()
            vals.append(float(psnr(pred, cam.image)))
            if first is None:
                first = (pred, cam.image)
        point = {"step": int(step), "train_time_s": round(self.train_time_s, 4), "psnr": sum(vals) / len(vals),
                 "num_gaussians": pl_module.num_gaussians}
        self.points.append(point)
        exp = getattr(trainer.logger, "experiment", None) if trainer.logger is not None else None
        if hasattr(exp, "add_scalar"):
            exp.add_scalar("test/psnr", point["psnr"], global_step=step)
            exp.add_scalar("test/num_gaussians", point["num_gaussians"], global_step=step)
            exp.add_scalar("test/psnr_vs_time", point["psnr"], global_step=int(round(point["train_time_s"] * 1000)))
        if self.log_images and first is not None and hasattr(exp, "add_image"):
            img = torch.cat([first[0], first[1]], dim=1).permute(2, 0, 1)
            exp.add_image("test/render_vs_gt", img, global_step=step)
        self.write()

    def write(self) -> None:
        if not self.points:
            return
        write_json(self.out_dir / "curve.json", {"x": "train_time_s", "points": self.points})
        plot_curve(self.points, self.out_dir / "curve.png")


def plot_curve(points: list[dict], path: Path, title: str = "Test PSNR and #Gaussians vs training time") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = [p["train_time_s"] for p in points]
    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=110)
    ax.plot(t, [p["psnr"] for p in points], "o-", color="tab:blue")
    ax.set_xlabel("training wall-clock time (s)")
    ax.set_ylabel("test PSNR (dB)", color="tab:blue")
    ax2 = ax.twinx()
    ax2.plot(t, [p["num_gaussians"] for p in points], "s--", color="tab:orange")
    ax2.set_ylabel("#Gaussians", color="tab:orange")
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)

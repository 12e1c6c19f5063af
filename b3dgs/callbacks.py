"""Lightning callbacks: training clock, PSNR-vs-time curve, checkpoints and exact resume.

* :class:`CurveCallback`: training wall-clock time and the test PSNR / #Gaussians curve.
* :class:`ResumeState`: every RNG, the numerical-guard counters and the view sampler's position go into each
  checkpoint and come back right before the first step after a resume (a resumed run is bit-identical).
* :class:`RunCheckpoint`: ``checkpoints/last.ckpt`` (overwritten atomically) every ``every_n_steps`` steps, every
  ``every_s`` seconds and at the end; after a SIGINT / SIGTERM (:func:`b3dgs.signals.interrupt_handlers`) at the next
  step boundary, then it raises :class:`b3dgs.signals.Interrupted`.
* :class:`RunFiles`: the files the trainer's loggers write join the run manifest (:mod:`b3dgs.rundir`).
* :class:`StepProgressBar`: one bar over the run's global steps with the Gaussian count, loss and last test PSNR.
"""
from __future__ import annotations

import logging
import os
import random
import shutil
import sys
import time
from pathlib import Path
from typing import Any, Optional

import lightning as L
import numpy as np
import torch
from lightning.pytorch.callbacks import Checkpoint, TQDMProgressBar
from lightning.pytorch.plugins.io import TorchCheckpointIO
from tqdm.std import tqdm as std_tqdm

from b3dgs.device import timed_clock
from b3dgs.io import atomic_path, save_figure, write_json
from b3dgs.progress import LINE_EVERY_S, is_terminal
from b3dgs.rundir import LOCK_NAME, MANIFEST_NAME, record_written
from b3dgs.signals import PENDING, Interrupted

log = logging.getLogger(__name__)


class AtomicCheckpointIO(TorchCheckpointIO):
    """Checkpoints are written to a temporary file and renamed, so a crash never leaves half a file."""

    def save_checkpoint(self, checkpoint: dict[str, Any], path, storage_options: Optional[Any] = None) -> None:
        with atomic_path(path) as tmp:
            torch.save(checkpoint, tmp)


def _train_sampler(trainer) -> Any:
    """The train loader's resumable sampler (``None`` for another loader)."""
    from b3dgs.data.datamodule import ResumableRandomSampler

    try:
        loader = trainer.train_dataloader
    except Exception:  # noqa: BLE001 - no loader yet
        return None
    sampler = getattr(loader, "sampler", None)
    return sampler if isinstance(sampler, ResumableRandomSampler) else None


def rng_state() -> dict[str, Any]:
    """Every RNG the training may draw from."""
    state = {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate()}
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict[str, Any]) -> None:
    torch.set_rng_state(state["torch"])
    np.random.set_state(state["numpy"])
    random.setstate(state["python"])
    if state.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


class ResumeState(L.Callback):
    """Saves the RNG states and the numerical-guard counters with every checkpoint and restores them at
    the first training step after a resume; tells the train sampler how many views each step consumed
    (its own ``state_dict`` is saved by Lightning with the train loader)."""

    def __init__(self) -> None:
        self._pending: Optional[dict] = None

    def state_dict(self) -> dict:
        from b3dgs.numerics import guard_calls, guard_counts

        return {"rng": rng_state(), "guards": guard_counts(), "guard_calls": guard_calls()}

    def load_state_dict(self, state_dict: dict) -> None:
        self._pending = dict(state_dict)

    def _restore(self) -> None:
        if self._pending is None:
            return
        from b3dgs import numerics as guards

        st, self._pending = self._pending, None
        set_rng_state(st["rng"])
        with guards._lock:  # noqa: SLF001 - the counters are module state; restore them as saved
            guards._pending.clear()
            guards._counts.clear()
            guards._counts.update({str(k): int(v) for k, v in st.get("guards", {}).items()})
            guards._fired_calls.clear()
            guards._fired_calls.update({str(k): int(v) for k, v in st.get("guard_calls", {}).items()})

    def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:
        # restored here, not at load time: nothing between the load and this step may draw from them
        self._restore()

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        sampler = _train_sampler(trainer)
        if sampler is not None:
            sampler.mark_consumed(batch_idx + 1)

    def on_fit_end(self, trainer, pl_module) -> None:
        self._restore()  # a resumed run that had nothing left to train (Lightning then skips on_train_end)


class RunCheckpoint(Checkpoint):
    """``dirpath/last.ckpt`` every ``every_n_steps`` steps, every ``every_s`` seconds of wall-clock (``None`` / 0: off)
    and at the end of training, overwritten atomically (never a ``last-v1.ckpt``); with ``keep``, also ``step<N>.ckpt``
    at each multiple of ``every_n_steps``. Runs after the other callbacks: a checkpoint holds their state at its step.

    Not ``ModelCheckpoint``: that takes only one of ``every_n_train_steps`` / ``train_time_interval``, versions a
    clashing name, and cannot save at the step boundary where a signal is acted on."""

    def __init__(self, dirpath: Path, every_n_steps: Optional[int] = None, every_s: Optional[float] = None,
                 keep: bool = False):
        self.dirpath = Path(dirpath)
        self.every_n_steps = int(every_n_steps or 0)
        self.every_s = float(every_s or 0.0)
        self.keep = bool(keep)
        self.last_path = self.dirpath / "last.ckpt"
        self._saved_step = -1
        self._t_last: Optional[float] = None

    def save(self, trainer) -> None:
        step = int(trainer.global_step)
        self._saved_step = step  # the step this process last saved
        trainer.save_checkpoint(self.last_path, weights_only=False)
        if self.keep and self.every_n_steps and step % self.every_n_steps == 0:
            # listed in the run manifest before it exists (a run dir's ``checkpoints/``; elsewhere nothing to list)
            record_written(self.dirpath.parent, [f"{self.dirpath.name}/step{step}.ckpt"])
            with atomic_path(self.dirpath / f"step{step}.ckpt") as tmp:
                shutil.copyfile(self.last_path, tmp)
        self._t_last = time.monotonic()

    def on_save_checkpoint(self, trainer, pl_module, checkpoint: dict) -> None:
        """The scene's normalisation goes into every checkpoint: a model can be exported in the scene's own frame
        from its checkpoint alone (:func:`b3dgs.data.scene.scene_transform`)."""
        from b3dgs.data.scene import scene_transform

        if getattr(pl_module, "scene", None) is not None:
            checkpoint["scene_transform"] = scene_transform(pl_module.scene).to_dict()

    def on_train_start(self, trainer, pl_module) -> None:
        self._t_last = time.monotonic()
        PENDING.deferred = True  # a signal now stops training at the next step boundary

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        step = int(trainer.global_step)
        due = bool(self.every_n_steps) and step % self.every_n_steps == 0
        if not due and self.every_s > 0 and self._t_last is not None:
            due = time.monotonic() - self._t_last >= self.every_s
        signum = PENDING.signum
        if (due or signum is not None) and step != self._saved_step:
            self.save(trainer)
        if signum is not None:
            PENDING.deferred = False
            raise Interrupted(signum, step)

    def on_train_end(self, trainer, pl_module) -> None:
        PENDING.deferred = False
        if int(trainer.global_step) != self._saved_step:
            self.save(trainer)
        if PENDING.signum is not None:  # came after the last step's check
            raise Interrupted(PENDING.signum, int(trainer.global_step))

    def on_exception(self, trainer, pl_module, exception) -> None:
        PENDING.deferred = False


class RunFiles(L.Callback):
    """The files the trainer's loggers write inside ``run_dir`` join its run manifest (:mod:`b3dgs.rundir`), by
    name: ``hparams.yaml`` before it is written, and the files of a logger's folder that are new or changed since
    this callback was made, before the trainer started (TensorBoard's ``events.out.tfevents.<time>.<host>.<pid>.<n>``,
    created when the trainer sets up, is listed right then). A file the run did not write is never listed."""

    def __init__(self, run_dir: Path):
        self.run_dir = Path(run_dir)
        self._before = self._stats(self.run_dir)

    @staticmethod
    def _stats(folder: Path) -> dict[str, tuple[int, int]]:
        out = {}
        for d, _, files in os.walk(folder):  # symlinked folders are not followed
            for name in files:
                p = Path(d) / name
                try:
                    st = p.lstat()
                except OSError:
                    continue
                out[p.relative_to(folder).as_posix()] = (st.st_mtime_ns, st.st_size)
        return out

    def _record(self, trainer, planned: bool = False) -> None:
        root = self.run_dir.resolve()
        names = []
        for logger in trainer.loggers:
            d = getattr(logger, "log_dir", None)
            folder = Path(d).resolve() if d else None
            if folder is None or not folder.is_relative_to(root):
                continue
            rel = folder.relative_to(root)
            hparams = getattr(logger, "NAME_HPARAMS_FILE", None)
            if planned and hparams:
                names.append((rel / hparams).as_posix())
            for f, st in self._stats(folder).items():
                name = (rel / f).as_posix()
                temp = f.rpartition("/")[2].startswith(".") and f.endswith(".tmp")  # an atomic write in flight
                if name not in (MANIFEST_NAME, LOCK_NAME) and not temp and self._before.get(name) != st:
                    names.append(name)
        if names:
            record_written(self.run_dir, names)

    def setup(self, trainer, pl_module, stage: str) -> None:
        self._record(trainer, planned=True)

    def on_train_start(self, trainer, *_: Any) -> None:
        self._record(trainer)

    on_fit_end = on_exception = on_train_start


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

        vals, first = [], None
        for cam in self.cameras:
            pred = pl_module.render_eval(cam).cpu()
            vals.append(float(psnr(pred, cam.image)))
            first = first or (pred, cam.image)
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
    save_figure(fig, path)


class _Sink:
    """A file that drops what tqdm writes (the bar is printed as lines instead)."""

    def write(self, _s: str) -> int:
        return 0

    def flush(self) -> None:
        pass


class StepProgressBar(TQDMProgressBar):
    """Lightning's tqdm bar over global steps instead of epochs: ``train 12%|██ | 360/3000 steps [01:02<07:40 ETA,
    5.7 steps/s, gaussians=12,345, loss=0.0831, test PSNR=24.12 dB]`` (a resumed run starts at its step). Outside a
    terminal it prints whole lines: the first step, then every ``line_every_s`` seconds, and the last. With
    ``final_after_eval`` the last line waits for the final evaluation's metrics (:meth:`show_final`)."""

    BAR_FORMAT = "{desc} {percentage:3.0f}%|{bar:16}| {n_fmt}/{total_fmt} steps [{elapsed}<{remaining} ETA, {rate_fmt}{postfix}]"

    def __init__(self, *args, line_every_s: float = LINE_EVERY_S, **kwargs):
        super().__init__(*args, **kwargs)
        self.line_every_s = float(line_every_s)
        self.final_after_eval = False
        self._lines = False
        self._last_line: Optional[float] = None
        self._shown: dict = {}  # the postfix last shown
        self._held: Optional[dict] = None  # the bar's state at the end of training, until show_final

    def init_train_tqdm(self):
        from lightning.pytorch.callbacks.progress.tqdm_progress import Tqdm

        step = int(self.trainer.global_step)
        self._lines, self._last_line = not is_terminal(sys.stdout), None
        return Tqdm(desc="train", total=int(self.trainer.max_steps), initial=step, position=2 * self.process_position,
                    disable=self.is_disabled, leave=True, dynamic_ncols=not self._lines,
                    file=_Sink() if self._lines else sys.stdout, smoothing=0.05, unit=" steps",
                    bar_format=self.BAR_FORMAT)

    def on_train_start(self, trainer, *_: Any) -> None:
        self.train_progress_bar = self.init_train_tqdm()

    def on_train_epoch_start(self, *_: Any) -> None:
        pass  # one bar for the whole run, not one per pass over the views

    on_train_epoch_end = on_train_epoch_start

    def on_train_end(self, *_: Any) -> None:
        bar = self.train_progress_bar
        if not self.final_after_eval or bar is None or bar.disable:
            super().on_train_end()
            return
        self._held = bar.format_dict  # the elapsed time stops here (the final evaluation is not training)
        bar.leave = False  # a terminal's bar is cleared: show_final prints its last line
        bar.close()

    def show_final(self, metrics: dict) -> None:
        """Print the bar's last line with the final evaluation's ``metrics`` (``metrics.json``'s values)."""
        held, self._held = self._held, None
        if held is None:
            return

        def fmt(key: str, spec: str, unit: str = "") -> Optional[str]:
            v = metrics.get(key)
            return None if v is None else f"{format(float(v), spec)}{unit}"

        final = {"gaussians": f"{int(metrics['num_gaussians']):,}" if metrics.get("num_gaussians") is not None else None,
                 "test PSNR": fmt("psnr", ".2f", " dB"), "SSIM": fmt("ssim", ".4f"), "LPIPS": fmt("lpips", ".4f")}
        shown = {**self._shown, **{k: v for k, v in final.items() if v is not None}}
        postfix = ", ".join(f"{k}={v}" for k, v in shown.items())
        print(std_tqdm.format_meter(**{**held, "postfix": postfix, "ncols": None}), file=sys.stdout, flush=True)

    #: a terminal bar's postfix (which reads the loss back from the device) is redrawn at most this often
    REDRAW_EVERY_S = 0.25

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        bar, n = self.train_progress_bar, int(trainer.global_step)
        if bar is not None and self._should_update(n, bar.total):
            bar.n = n
            now = time.monotonic()
            every = self.line_every_s if self._lines else self.REDRAW_EVERY_S
            if not (self._last_line is None or n >= bar.total or now - self._last_line >= every):
                return  # the metrics are read (a host sync on a GPU) only when they are shown
            self._last_line = now
            self._shown = self.get_metrics(trainer, pl_module)
            bar.set_postfix(self._shown, refresh=False)
            if not self._lines:
                bar.refresh()
            elif not (self.final_after_eval and n >= bar.total):  # else the last line waits for show_final
                print(str(bar), file=sys.stdout, flush=True)

    def get_metrics(self, trainer, pl_module) -> dict:
        shown = super().get_metrics(trainer, pl_module)
        shown.pop("v_num", None)
        out = {}
        if "gaussians" in shown:
            out["gaussians"] = f"{int(round(float(shown.pop('gaussians')))):,}"
        if "loss" in shown:
            out["loss"] = f"{float(shown.pop('loss')):.4f}"
        curve = next((c for c in trainer.callbacks if isinstance(c, CurveCallback)), None)
        if curve is not None and curve.cameras:
            out["test PSNR"] = f"{curve.points[-1]['psnr']:.2f} dB" if curve.points else "—"
        return {**out, **shown}

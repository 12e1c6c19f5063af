"""``SplatModule``: the LightningModule that owns the Gaussians, the renderer and the optimizer."""
from __future__ import annotations

import logging
import math
import time
from collections import OrderedDict
from typing import Any, Mapping, Optional, Sequence

import lightning as L
import torch
from torch import Tensor, nn

from b3dgs.checkpoint import (PARAM_ORDER, check_sealed, identity_mismatch, run_identity, scene_fingerprint,
                              seal_checkpoint)
from b3dgs.device import move_tree
from b3dgs.errors import B3dgsError
from b3dgs.host_sync import scope
from b3dgs.init import init_gaussians
from b3dgs.numerics import on_device_path
from b3dgs.ops import TopologyOps
from b3dgs.plugin import Plugin, PosteriorBlock, ViewAccumulator, validate_once
from b3dgs.render.render import RenderOutput
from b3dgs.render.renderers import Renderer, make_renderer
from b3dgs.schedule import ConstantSchedule, TrainingSchedule
from b3dgs.types import Camera, Scene

log = logging.getLogger(__name__)

_DIVERGED_FIX = "lower the learning rates, e.g. model.lr_means, or check the data"


class SplatModule(L.LightningModule):
    """3DGS training with manual optimization.

    One Adam optimizer holds one parameter group per Gaussian attribute (each with its own learning
    rate and independent moments, equivalent to one Adam per group) so that Lightning's
    ``global_step`` equals the training iteration. The means' learning rate decays exponentially and
    is scaled by the scene extent, as in 3DGS. Loss: (1-λ)·L1 + λ·(1-SSIM), with the SSIM the renderer
    prefers. The renderer is a plugin object (``renderer=auto|cpu|torch|gsplat``); plugin states and
    cameras follow the module to its device.
    """

    def __init__(self, strategy: Plugin, posterior: Optional[Mapping[str, PosteriorBlock]] = None, sh_degree: int = 3,
                 sh_increase_every: int = 1000, lambda_dssim: float = 0.2, lr_means: float = 1.6e-4,
                 lr_means_final: float = 1.6e-6, lr_scales: float = 5e-3, lr_quats: float = 1e-3,
                 lr_opacities: float = 5e-2, lr_sh0: float = 2.5e-3, lr_shN: float = 2.5e-3 / 20,
                 background: Sequence[float] = (0.0, 0.0, 0.0), renderer: "Renderer | str" = "auto",
                 init_max_points: Optional[int] = None, init_num_random: int = 20000, init_opacity: float = 0.1,
                 init_scale: float = 1.0, max_steps: int = 30000, seed: int = 0, name: str = "standard",
                 schedule: Optional[TrainingSchedule] = None) -> None:
        super().__init__()
        self.automatic_optimization = False
        if not 0.0 <= lambda_dssim <= 1.0:
            raise B3dgsError(f"model.lambda_dssim must be in [0, 1], got {lambda_dssim}",
                             fix="pass model.lambda_dssim in [0, 1], e.g. the default 0.2 (0 = L1 only, 1 = D-SSIM "
                                 "only)")
        if not 0 <= sh_degree <= 3:
            raise B3dgsError(f"model.sh_degree must be in 0..3, got {sh_degree}",
                             fix="pass model.sh_degree=0, 1, 2 or 3 (the default is 3)")
        if max_steps <= 0:
            raise B3dgsError(f"trainer.max_steps must be > 0, got {max_steps}",
                             fix="pass trainer.max_steps as a positive number of steps, e.g. trainer.max_steps=30000")
        self.save_hyperparameters(ignore=["strategy", "posterior", "renderer", "schedule"])
        self.renderer: Renderer = make_renderer(renderer)
        self.strategy = strategy
        self.schedule: TrainingSchedule = schedule if schedule is not None else ConstantSchedule()
        self.posterior: "OrderedDict[str, PosteriorBlock]" = OrderedDict(posterior or {})
        for p in (self.schedule, self.strategy, *self.posterior.values()):  # unless the config check did
            validate_once(p, max_steps=max_steps, sh_degree=sh_degree)
        self.splats = nn.ParameterDict()
        self.states: dict[str, dict] = {}
        self.scene: Optional[Scene] = None
        self.ops: Optional[TopologyOps] = None
        self.block_time_s: dict[str, float] = {name: 0.0 for name in self.posterior}
        self._camera_cache: dict[int, tuple[Camera, Camera]] = {}
        # True when the next checkpoint load starts a new training round whose training set may have grown
        # (views acquired from the candidate pool): the identity check then compares the view pool
        self.allow_new_views = False
        self.register_buffer("bg", torch.tensor(list(background), dtype=torch.float32), persistent=False)

    # ------------------------------------------------------------------ set-up
    @property
    def plugins(self) -> "OrderedDict[str, Plugin]":
        p: "OrderedDict[str, Plugin]" = OrderedDict(strategy=self.strategy)
        p.update(self.posterior)
        return p

    @property
    def num_gaussians(self) -> int:
        return int(self.splats["means"].shape[0]) if "means" in self.splats else 0

    def setup(self, stage: str) -> None:
        if "means" in self.splats:
            return
        dm = self.trainer.datamodule if self._trainer is not None else None
        if dm is None or getattr(dm, "scene", None) is None:
            raise B3dgsError("SplatModule needs a datamodule exposing `.scene` (set up before the module)",
                             "pass the trainer a b3dgs data module (b3dgs.lifecycle.data_module), or call "
                             "init_from_scene(scene) before fitting")
        self.init_from_scene(dm.scene)

    def init_from_scene(self, scene: Scene) -> None:
        """Create the Gaussians and every plugin's state for ``scene``."""
        self.scene = scene
        g = torch.Generator().manual_seed(int(self.hparams.seed))
        params = init_gaussians(
            scene, self.hparams.sh_degree, self.hparams.init_max_points, self.hparams.init_num_random,
            self.hparams.init_opacity, self.hparams.init_scale, generator=g,
        )
        self._set_params(params)
        self.schedule.initialize(scene.train, int(self.hparams.max_steps))
        self._init_states()
        self.states = move_tree(self.states, self.splats["means"].device)

    def _set_params(self, params: Mapping[str, Tensor]) -> None:
        self.splats = nn.ParameterDict({k: nn.Parameter(params[k].contiguous()) for k in PARAM_ORDER})

    def _init_states(self) -> None:
        n = self.num_gaussians
        dev = self.splats["means"].device
        self.states = {"core": {"ids": torch.arange(n, device=dev), "parent_ids": torch.full((n,), -1, dtype=torch.long, device=dev),
                                "next_id": torch.tensor(n, device=dev)}}
        info = self._static_info()
        for name, plugin in self.plugins.items():
            self.states[name] = plugin.initialize_state(splats=self.splats, scene=self.scene, info=info)

    def _static_info(self) -> dict:
        extent = float(self.scene.extent) if self.scene is not None else 1.0
        # max_steps: the run's TOTAL budget (schedules continue across training rounds); num_train_views:
        # the current training set, which grows when views are acquired between rounds
        return {"scene_extent": extent, "max_steps": int(self.hparams.max_steps),
                "num_train_views": len(self.scene.train) if self.scene is not None else None}

    def configure_optimizers(self):
        hp = self.hparams
        extent = float(self.scene.extent) if self.scene is not None else 1.0
        lrs = {"means": hp.lr_means * extent, "scales": hp.lr_scales, "quats": hp.lr_quats,
               "opacities": hp.lr_opacities, "sh0": hp.lr_sh0, "shN": hp.lr_shN}
        groups = [{"params": [self.splats[k]], "lr": lrs[k], "name": k} for k in PARAM_ORDER]
        return torch.optim.Adam(groups, eps=1e-15, fused=True)  # fused CPU kernel: ~3.5x faster steps

    def _torch_optimizers(self) -> dict[str, torch.optim.Optimizer]:
        opt = self.optimizers()
        opt = opt.optimizer if hasattr(opt, "optimizer") else opt
        return {"gaussians": opt}

    def _get_ops(self) -> TopologyOps:
        """The topology ops of the live parameters, states and optimizer: rebuilt whenever any of them was
        replaced (a second ``trainer.fit`` or a checkpoint load makes a new Adam), so clone, split and prune
        always edit the optimizer that steps next; the removed/added counters carry over."""
        optimizers = self._torch_optimizers()
        ops = self.ops
        if (ops is None or ops.splats is not self.splats or ops.states is not self.states
                or set(ops.optimizers) != set(optimizers)
                or any(ops.optimizers[k] is not v for k, v in optimizers.items())):
            self.ops = TopologyOps(self.splats, optimizers, self.states, dict(self.plugins))
            if ops is not None:
                self.ops.removed.update(ops.removed)
                self.ops.added.update(ops.added)
        return self.ops

    def means_lr(self, step: int) -> float:
        """Exponential decay from ``lr_means`` to ``lr_means_final`` over ``max_steps`` (the TOTAL budget,
        also when trained in rounds: ``step`` is the global step, which continues), times the extent."""
        hp = self.hparams
        t = self.schedule.lr_progress(step, int(hp.max_steps))
        lr = math.exp((1 - t) * math.log(hp.lr_means) + t * math.log(hp.lr_means_final))
        extent = float(self.scene.extent) if self.scene is not None else 1.0
        return lr * extent

    def active_sh_degree(self, step: Optional[int] = None) -> int:
        if step is None:
            # a module loaded from a checkpoint has no trainer: use the checkpoint's step
            step = self.global_step if self._trainer is not None else getattr(self, "_loaded_step", self.hparams.max_steps)
        return min(self.hparams.sh_degree, step // max(self.hparams.sh_increase_every, 1))

    # ------------------------------------------------------------------ rendering
    def params(self) -> dict[str, Tensor]:
        return {k: self.splats[k] for k in PARAM_ORDER}

    def render_camera(self, camera: Camera, params: Optional[Mapping[str, Tensor]] = None, **kw) -> RenderOutput:
        return self.renderer.render(
            params if params is not None else self.params(), self.device_camera(camera),
            sh_degree=kw.pop("sh_degree", self.active_sh_degree()), background=self.bg, **kw,
        )

    def device_camera(self, camera: Camera) -> Camera:
        """``camera`` on the splats' device; device copies are cached per camera object."""
        dev = self.splats["means"].device if "means" in self.splats else self.bg.device
        if camera.viewmat.device == dev:
            return camera
        hit = self._camera_cache.get(id(camera))
        if hit is not None and hit[0] is camera and hit[1].viewmat.device == dev:
            return hit[1]
        moved = camera.to(dev)
        self._camera_cache[id(camera)] = (camera, moved)
        return moved

    def transfer_batch_to_device(self, batch, device, dataloader_idx):
        return self.device_camera(batch) if isinstance(batch, Camera) else batch

    def _apply(self, fn, *args, **kwargs):
        # plugin states are plain dicts of tensors: they follow the parameters' device (never their dtype)
        out = super()._apply(fn, *args, **kwargs)
        if "means" in self.splats and self.states:
            dev = self.splats["means"].device
            for name in list(self.states):
                self.states[name].update(move_tree(self.states[name], dev))
        return out

    # ------------------------------------------------------------------ training
    def training_step(self, batch: Camera, batch_idx: int):
        with scope("core"):  # host-sync attribution (b3dgs.host_sync); a no-op context unless a counter is installed
            return self._training_step(batch, batch_idx)

    def _training_step(self, batch: Camera, batch_idx: int):
        cam = batch[0] if isinstance(batch, (list, tuple)) else batch
        step = int(self.global_step)
        opt, optimizers = self.optimizers(), self._torch_optimizers()
        for group in optimizers["gaussians"].param_groups:
            if group.get("name") == "means":
                group["lr"] = self.means_lr(step)
        ops = self._get_ops()
        ops.step = step
        # the per-Gaussian pair sums only on steps where a plugin reads them (Plugin.reads_pair_sums)
        static = self._static_info()
        need_weights = any(p.reads_pair_sums(step, static) for p in self.plugins.values())
        cam = self.schedule.camera(self.device_camera(cam), step)  # the step's resolution (schedule=dash)
        try:
            with scope("render"):
                out = self.render_camera(cam, retain_means2d_grad=True, return_weights=need_weights)
        except ValueError as e:
            if "NaN or Inf" not in str(e):
                raise
            raise B3dgsError(f"step {step}, camera {cam.name}: the optimisation diverged (NaN/Inf Gaussian attributes "
                             f"reached the renderer: {getattr(e, 'problem', e)})", _DIVERGED_FIX) from e
        cam = self.device_camera(cam)
        gt = cam.image
        l1 = (out.rgb - gt).abs().mean()
        ssim = self.renderer.ssim(out.rgb, gt)
        lam = self.hparams.lambda_dssim
        loss = (1 - lam) * l1 + lam * (1 - ssim)
        if on_device_path(loss):  # no host read per step: the first non-finite step is kept on the device
            self._note_nonfinite(loss, step)
            if step % max(self.trainer.log_every_n_steps, 1) == 0:
                self.check_finite()
        elif not torch.isfinite(loss):
            raise B3dgsError(f"non-finite loss at step {step} (camera {cam.name})", _DIVERGED_FIX)
        ops.per_gaussian = {}
        info = {
            **static, "ops": ops, "camera": cam, "render": out, "per_gaussian": ops.per_gaussian,
            "width": cam.width, "height": cam.height, "gt": gt, "loss": loss.detach(),
            "l1": l1.detach(), "num_values": gt.numel(), "loss_terms": [], **self.schedule.step_info(step),
            "view_sums": self.view_sums,  # a pass over the training views, for plugins that need one (rarely)
        }
        if any(p.needs_residuals for p in self.plugins.values()):
            info["sq_err_sum"] = ((out.rgb.detach() - gt) ** 2).sum()
        self._call_hooks("step_pre_backward", optimizers, step, info)
        if info["loss_terms"]:  # differentiable scalars plugins add (e.g. the MCMC opacity / scale regularisers)
            loss = loss + torch.stack([t.reshape(()) for t in info["loss_terms"]]).sum()
        self.manual_backward(loss)
        # per-Gaussian data of this step (S, N, ...), kept aligned by the topology ops
        pg = ops.per_gaussian
        pg["radii"] = out.radii
        m2g = out.means2d_grad
        if m2g is not None:
            pg["means2d_grad"] = m2g
        if out.weight_sum is not None:
            pg["weight_sum"] = out.weight_sum
            pg["weight_sq_sum"] = out.weight_sq_sum
        # posterior blocks read gradients; densification (strategy) runs last, then Adam steps
        # (parameters replaced by a topology change have no gradient and skip this one step, as in 3DGS)
        self._call_hooks("step_post_backward", optimizers, step, info)
        opt.step()
        opt.zero_grad(set_to_none=True)
        if self.logger is not None and step % max(self.trainer.log_every_n_steps, 1) == 0:
            self.log_dict(
                {"train/loss": loss.detach(), "train/l1": l1.detach(), "train/num_gaussians": float(self.num_gaussians),
                 "train/lr_means": self.means_lr(step)},
                on_step=True, prog_bar=False, logger=True, batch_size=1,
            )
        if self.trainer.progress_bar_callback is not None:  # values shown only in the progress bar
            self.log("gaussians", float(self.num_gaussians), prog_bar=True, logger=False, batch_size=1)
            self.log("loss", loss.detach(), prog_bar=True, logger=False, batch_size=1)
        return loss.detach()

    def _note_nonfinite(self, loss: Tensor, step: int) -> None:
        first = getattr(self, "_first_nonfinite", None)
        if first is None or first.device != loss.device:
            first = torch.full((), -1, dtype=torch.long, device=loss.device)
        bad = ~torch.isfinite(loss) & (first < 0)
        self._first_nonfinite = torch.where(bad, torch.full_like(first, step), first)

    def check_finite(self) -> None:
        """Raise if a training step's loss was not finite (the device path checks once per logging interval and at
        the end of training, reading one value; the CPU path checks every step)."""
        first = getattr(self, "_first_nonfinite", None)
        if first is not None and int(first) >= 0:
            raise B3dgsError(f"non-finite loss at step {int(first)} (found at step {int(self.global_step)})",
                             _DIVERGED_FIX)

    def on_train_end(self) -> None:
        self.check_finite()

    def _call_hooks(self, hook: str, optimizers, step: int, info: dict) -> None:
        # the strategy runs after the posterior blocks so that blocks see the pre-densification set
        for name in list(self.posterior.keys()) + ["strategy"]:
            plugin = self.plugins[name]
            t0 = time.perf_counter()
            with scope(name):
                getattr(plugin, hook)(splats=self.splats, optimizers=optimizers, state=self.states[name], step=step,
                                      info=info)
            if name in self.block_time_s:
                self.block_time_s[name] += time.perf_counter() - t0

    # ------------------------------------------------------------------ checkpoints
    def run_identity(self) -> dict:
        """Model, posterior blocks, strategy, scene fingerprint and renderer: what a checkpoint must share with
        the run that resumes or evaluates it (:mod:`b3dgs.checkpoint`; the renderer for resumes only)."""
        return run_identity(self.hparams, self.strategy, self.posterior, self.scene, self.schedule, self.renderer)

    def check_checkpoint_identity(self, checkpoint: Mapping[str, Any], what: str, fix: str,
                                  suggest: bool = True) -> None:
        """Refuse a checkpoint of another model, posterior, strategy, scene or schedule with a one-line
        ``ValueError`` ``"<what> does not match: <reason> (fix: pass <key=value> or <fix>)"``; ``suggest=False``
        (a command that takes no training options, e.g. b3dgs-export): ``fix`` alone."""
        extra = checkpoint.get("b3dgs") or {}
        saved, current = extra.get("identity"), self.run_identity()
        if self.allow_new_views and saved:
            # a new round: the training set may hold acquired views; the pool (train + candidates + test) must agree
            if extra.get("pool") is not None and extra.get("pool") != self.pool_fingerprint():
                raise B3dgsError(f"{what} does not match this run: it was trained on another view pool (scene "
                                 "name, train + candidate + test cameras)", fix)
            saved, current = {k: v for k, v in saved.items() if k != "scene"}, {k: v for k, v in current.items() if k != "scene"}
        bad = identity_mismatch(saved, current)
        if bad is not None:
            problem, want = bad
            raise B3dgsError(f"{what} does not match this run: {problem}", f"pass {want}, or {fix}" if suggest else fix)

    def pool_fingerprint(self) -> Optional[str]:
        """Fingerprint of the whole view pool (train + candidates, and test): what training rounds share."""
        from types import SimpleNamespace

        sc = self.scene
        if sc is None:
            return None
        pool = sorted(list(sc.train) + list(getattr(sc, "candidates", None) or []), key=lambda c: c.name)
        return scene_fingerprint(SimpleNamespace(name=sc.name, train=pool, test=sc.test))

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint["b3dgs"] = {
            "identity": self.run_identity(),
            "pool": self.pool_fingerprint(),
            "train_views": [c.name for c in self.scene.train] if self.scene is not None else None,
            "states": self.states,
            "removed": dict(self.ops.removed) if self.ops else {},
            "added": dict(self.ops.added) if self.ops else {},
            "block_time_s": dict(self.block_time_s),
            "scene_extent": float(self.scene.extent) if self.scene is not None else None,
        }
        seal_checkpoint(checkpoint)  # a digest of what a resume or an evaluation reads back (checked on load)

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        check_sealed(checkpoint, "the checkpoint",
                     "train the run again (overwrite=true), or resume from an earlier checkpoint of it "
                     "(resume=RUN/checkpoints/step<N>.ckpt, written with trainer.keep_checkpoints=true)")
        sd = checkpoint["state_dict"]
        shapes = {k: sd[f"splats.{k}"] for k in PARAM_ORDER if f"splats.{k}" in sd}
        if len(shapes) != len(PARAM_ORDER):
            raise B3dgsError("Checkpoint has no Gaussian parameters (splats.*); is it a b3dgs checkpoint?",
                             fix="pass the last.ckpt of a b3dgs-train run dir (run=<run dir>), not a checkpoint of "
                                 "another program")
        # niw -> standard would keep the niw state, standard -> dpmm would fail later with a KeyError
        self.check_checkpoint_identity(checkpoint, "the checkpoint",
                                       "use a checkpoint of this model, posterior, strategy and scene")
        # resize before Lightning loads the state dict (the Gaussian count changes during training)
        self.splats = nn.ParameterDict({k: nn.Parameter(torch.empty_like(v)) for k, v in shapes.items()})
        extra = checkpoint.get("b3dgs", {})
        self.states = extra.get("states", self.states)
        self.block_time_s.update(extra.get("block_time_s", {}))
        self.ops = None
        self._restored_counts = (extra.get("removed", {}), extra.get("added", {}))

    def on_train_start(self) -> None:
        self._apply_restored_counts()

    def on_fit_end(self) -> None:
        # a resume from the final checkpoint trains nothing: Lightning skips on_train_start
        self._apply_restored_counts()

    def _apply_restored_counts(self) -> None:
        removed, added = getattr(self, "_restored_counts", ({}, {}))
        self._restored_counts = ({}, {})  # applied once (a later fit of this module carries the live counters)
        if removed or added or self.ops is None:
            ops = self._get_ops()
            ops.removed.update(removed)
            ops.added.update(added)

    # ------------------------------------------------------------------ view passes
    def view_sums(self, cameras: Optional[Sequence[Camera]] = None, accumulators: Sequence[ViewAccumulator] = (), *,
                  seed: int = 0) -> dict[str, Tensor]:
        """Per-Gaussian sums over ``cameras`` (default: the training views), one render each at the active SH
        degree, in float64 on the splats' device, in the pixels of the cameras given: ``weight_sum`` (N,):
        Σ_views Σ_p w_kp, the compositing weight T·α Gaussian k contributes (how many pixels it explains);
        ``visible_views`` (N,): in how many of the views it is drawn; and every entry of each accumulator's
        ``result()`` (:class:`b3dgs.plugin.ViewAccumulator`, started with ``seed``)."""
        cams = list(self.scene.train if cameras is None else cameras)
        sp = self.params()
        dev = sp["means"].device
        n = sp["means"].shape[0]
        out = {"weight_sum": torch.zeros(n, dtype=torch.float64, device=dev),
               "visible_views": torch.zeros(n, dtype=torch.float64, device=dev)}
        degree = self.active_sh_degree()
        accs = list(accumulators)
        detached = {k: v.detach() for k, v in sp.items()}
        for acc in accs:
            acc.start(params=detached, sh_degree=degree, seed=int(seed))
        grad = any(acc.needs_means_grad for acc in accs)
        for cam in cams:
            params = {**detached, "means": sp["means"].detach().requires_grad_(True)} if grad else detached
            with torch.set_grad_enabled(grad):
                ro = self.render_camera(cam, params=params, sh_degree=degree, return_weights=True)
                for acc in accs:
                    acc.add(camera=cam, render=ro, params=params, sh_degree=degree)
            if ro.weight_sum is not None:
                out["weight_sum"] += ro.weight_sum.detach().reshape(-1).double()
            out["visible_views"] += (ro.radii.detach().reshape(-1) > 0).double()
        for acc in accs:
            for k, v in acc.result().items():
                if k in out:
                    raise B3dgsError(f"view pass: two sums are named {k!r} ({type(acc).__name__} and another "
                                     "accumulator or the core)", "give the accumulator's result a name of its own")
                out[k] = v
        return out

    def prepare_posterior(self, cameras: Optional[Sequence[Camera]] = None, blocks=None) -> bool:
        """Give every posterior block that asks for one (:meth:`b3dgs.plugin.PosteriorBlock.view_pass`) the sums of
        one pass over ``cameras`` (default: the training views), which feeds every block's accumulators (equal keys
        merged, run once); called before the posterior is used (the end of training, ``uq=native``, acquisition).
        ``blocks``: (name, block, state) triples to prepare instead of the model's own (e.g. copies with another
        count). Deterministic: accumulators are started with the run's seed. Returns whether a pass ran (False: no
        block asked for one)."""
        triples = blocks if blocks is not None else [(n, b, self.states[n]) for n, b in self.posterior.items()]
        reqs = [(b, st, b.view_pass(state=st)) for _, b, st in triples]
        reqs = [r for r in reqs if r[2] is not None]
        if not reqs:
            return False
        accs: dict[str, ViewAccumulator] = {}
        for _, _, wanted in reqs:
            for acc in wanted:
                accs[acc.key] = accs[acc.key].merge(acc) if acc.key in accs else acc
        sums = self.view_sums(cameras, list(accs.values()), seed=int(self.hparams.seed))
        for blk, st, _ in reqs:
            blk.absorb_view_sums(splats=self.splats, state=st, sums=sums)
        return True

    # ------------------------------------------------------------------ evaluation
    @torch.no_grad()
    def render_eval(self, camera: Camera) -> Tensor:
        return self.render_camera(camera, sh_degree=self.active_sh_degree()).rgb.clamp(0, 1)

    def export_extras(self) -> dict[str, Tensor]:
        extras: dict[str, Tensor] = {}
        for name, blk in self.posterior.items():
            extras.update(blk.export(splats=self.splats, state=self.states[name]))
        return extras

"""``b3dgs-study compress``: the compression ladder on matched checkpoints (paper appendix, compression follow-up,
with the matched PUP comparator).

Protocol per base run (a finished standard run: its scene and seed come from its own ``config.yaml``): every
pruning score (``conf/pruning/<name>.yaml``) and keep ratio starts from the same base checkpoint; a score with
``rounds`` = r prunes to keep^(1/r) of the current Gaussians, fine-tunes ``finetune_steps`` with the standard
trainer (no densification, no posterior blocks), rescores the fine-tuned model, and so on; the last round lands
on exactly round(keep × N_base) Gaussians. The row is evaluated on the test views (PSNR, SSIM, LPIPS, render
FPS) with its compression time (scoring + fine-tuning) next to the base's training time. The first round's
scores of a base are computed once and shared by every keep ratio (``scores/<name>.pt``).

Resumable: finished rows (``result.json``) are never recomputed; the tables (``compression.json``,
``compression.md``, ``plots/``) are rebuilt from the rows on disk (:mod:`b3dgs.study.compression_tables`).
"""
from __future__ import annotations

import glob
import json
import logging
import os
import time
import warnings
from pathlib import Path
from typing import Any, Optional

import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from b3dgs.compression import keep_top
from b3dgs.io import atomic_path, write_json
from b3dgs.protocol import check_stored_protocol, flatten

log = logging.getLogger(__name__)

#: settings that change a row or a cached score (conf/compress.yaml)
PROTOCOL_KEYS = ("finetune_steps", "finetune_overrides", "strategy_settings", "score_max_side")

def load_pruning(name: str, settings: Optional[DictConfig] = None):
    """The pruning score ``name`` from ``conf/pruning/<name>.yaml`` (or a package's), with ``settings[name]``."""
    from hydra.utils import instantiate

    from b3dgs.study.active import option_node

    node = option_node("compress", "pruning", name, settings,
                       "pass strategies=[...] of conf/pruning/<name>.yaml (random, opacity, gradient, dp_mass, "
                       "posterior_importance, pup) or a package's")
    score = instantiate(node, _convert_="all")
    score.check_sanity()
    return score


def round_targets(n_base: int, keep: float, rounds: int) -> list[int]:
    """Gaussian counts after each round: keep^(i/r) × N_base, the last exactly round(keep × N_base) (>= 1)."""
    if not 0 < keep <= 1:
        raise ValueError(f"keep ratios must be in (0, 1], got {keep}")
    out = [max(1, int(round(n_base * keep ** ((i + 1) / rounds)))) for i in range(rounds)]
    out[-1] = max(1, int(round(n_base * keep)))
    return out


def _atomic_save(obj: Any, path: Path) -> None:
    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


class CompressionStudy:
    def __init__(self, cfg: DictConfig):
        from b3dgs.errors import B3dgsError

        self.cfg = cfg
        self.out = Path(str(cfg.out_dir))
        self.keeps = [float(k) for k in cfg.keep]
        for k in self.keeps:
            if not 0 < k < 1:
                raise B3dgsError(f"keep ratio {k} is not in (0, 1)", "pass keep=[0.55,0.35,0.2,0.1] (fractions kept)")
        self.strategies = [(str(n), load_pruning(str(n), cfg.get("strategy_settings"))) for n in cfg.strategies]
        runs: list[Path] = []
        for pat in list(cfg.base_runs or []):
            hits = sorted(glob.glob(str(pat))) or ([str(pat)] if Path(str(pat)).exists() else [])
            runs += [Path(h) for h in hits if (Path(h) / "metrics.json").exists()]
        if not runs:
            raise B3dgsError(f"no finished base runs match base_runs={list(cfg.base_runs or [])}",
                             "pass finished standard run dirs, e.g. base_runs=[outputs/bench/fox/standard/*] "
                             "(train them with b3dgs-train first)")
        self.base_runs = sorted(dict.fromkeys(runs))
        if int(cfg.finetune_steps) < 1:
            raise B3dgsError(f"finetune_steps={cfg.finetune_steps}", "pass finetune_steps >= 1")

    # ------------------------------------------------------------------ one base run
    def base_dir(self, loaded) -> Path:
        return self.out / str(loaded.cfg.data.name) / f"s{int(loaded.cfg.seed)}"

    def finetune_cfg(self, base_cfg: DictConfig) -> DictConfig:
        """The base run's config with the fine-tune's budget, no posterior blocks and no densification."""
        cfg = OmegaConf.create(OmegaConf.to_container(base_cfg, resolve=True))
        with open_dict(cfg):
            cfg.posterior = {}
            cfg.trainer.max_steps = int(self.cfg.finetune_steps)
            cfg.trainer.eval_every = 10 ** 9
            cfg.merge_with(OmegaConf.from_dotlist([str(o) for o in (self.cfg.finetune_overrides or [])]))
            if self.cfg.get("threads"):
                cfg.threads = int(self.cfg.threads)
        return cfg

    def finetune(self, cfg: DictConfig, scene, params: dict, seed: int):
        """A fresh standard module holding ``params``, trained ``cfg.trainer.max_steps`` steps (new Adam state, as
        PUP's refine stage); returns it on its renderer's device."""
        import lightning as L

        from b3dgs.data.datamodule import SceneDataModule
        from b3dgs.train import build_module, build_plugins, build_renderer, build_trainer

        os.environ.pop("PL_GLOBAL_SEED", None)
        L.seed_everything(int(seed), workers=True, verbose=False)
        strategy, blocks = build_plugins(cfg)
        renderer = build_renderer(cfg.get("renderer"))
        module = build_module(cfg, strategy, blocks, renderer)
        module.scene = scene
        module._set_params({k: v.detach().cpu().clone() for k, v in params.items()})
        module._init_states()
        trainer = build_trainer(cfg.trainer, renderer, [], enable_progress_bar=False, enable_checkpointing=False,
                                default_root_dir=str(self.out / ".lightning"))
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*does not have many workers.*")
            warnings.filterwarnings("ignore", message=".*`training_step` returns.*")
            trainer.fit(module, datamodule=SceneDataModule(scene=scene))
        module.eval()
        return module

    def context(self, module, scene, seed: int):
        from b3dgs.acquisition import ScoringContext

        return ScoringContext([module], scene.train, score_max_side=self.cfg.get("score_max_side"),
                              extent=float(scene.extent), seed=int(seed))

    def first_scores(self, name: str, score_fn, loaded, info: dict) -> tuple[torch.Tensor, float, dict]:
        """Round-1 scores of the base model (cached on disk: the same for every keep ratio)."""
        path = self.base_dir(loaded) / "scores" / f"{name}.pt"
        if path.exists():
            d = torch.load(path, map_location="cpu", weights_only=False)
            return d["score"], float(d["time_s"]), d.get("state", {})
        state: dict = {}
        t0 = time.perf_counter()
        s = score_fn.score(splats=loaded.module.params(), optimizers=None, state=state, step=0, info=info)
        dt = time.perf_counter() - t0
        s = s.detach().cpu()
        _check_score(name, s, loaded.module.num_gaussians)
        _atomic_save({"score": s, "time_s": dt, "state": _plain(state)}, path)
        return s, dt, _plain(state)

    def run_row(self, name: str, score_fn, keep: float, loaded, base_eval: dict, lp) -> dict:
        from b3dgs.metrics.views import evaluate_views

        d = self.base_dir(loaded) / f"{name}_k{int(round(keep * 100)):02d}"
        if (d / "result.json").exists():
            return json.loads((d / "result.json").read_text())
        seed = int(loaded.cfg.seed)
        n_base = loaded.module.num_gaussians
        targets = round_targets(n_base, keep, int(score_fn.rounds))
        ft_cfg = self.finetune_cfg(loaded.cfg)
        module, state, per_round = loaded.module, {}, []
        score_s = finetune_s = 0.0
        for r, target in enumerate(targets):
            info = {"ctx": self.context(module, loaded.scene, seed), "cache": {},
                    "generator": torch.Generator().manual_seed(seed * 1000003 + 7919 * r + 1)}
            if r == 0:
                s, dt, state = self.first_scores(name, score_fn, loaded, info)
            else:
                t0 = time.perf_counter()
                s = score_fn.score(splats=module.params(), optimizers=None, state=state, step=r, info=info).detach().cpu()
                dt = time.perf_counter() - t0
                _check_score(name, s, module.num_gaussians)
            score_s += dt
            mask = keep_top(s, target)
            params = {k: v.detach().cpu()[mask] for k, v in module.params().items()}
            t0 = time.perf_counter()
            module = self.finetune(ft_cfg, loaded.scene, params, seed)
            ft = time.perf_counter() - t0
            finetune_s += ft
            per_round.append({"round": r, "kept": int(mask.sum()), "score_s": dt, "finetune_s": ft})
            log.info("%s %s keep %.2f round %d: %d Gaussians (score %.1f s, fine-tune %.1f s)",
                     d.parent.name, name, keep, r, int(mask.sum()), dt, ft)
        ev = evaluate_views(module, loaded.scene.test, lpips_model=lp)
        res = {"scene": str(loaded.cfg.data.name), "seed": seed, "base_run": str(loaded.path), "strategy": name,
               "keep": keep, "rounds": int(score_fn.rounds), "finetune_steps": int(self.cfg.finetune_steps),
               "num_base": n_base, "num_gaussians": module.num_gaussians,
               "kept_fraction": module.num_gaussians / max(n_base, 1),
               "psnr": ev.get("psnr"), "ssim": ev.get("ssim"), "lpips": ev.get("lpips"), "render_fps": ev.get("render_fps"),
               "score_s": score_s, "finetune_s": finetune_s, "time_s": score_s + finetune_s,
               "per_round": per_round, "guards": {k: v for k, v in state.items() if isinstance(v, (int, float))},
               "base": base_eval, "score_max_side": self.cfg.get("score_max_side")}
        write_json(d / "result.json", res)
        return res

    def base_row(self, loaded, lp) -> dict:
        from b3dgs.metrics.views import evaluate_views

        from b3dgs.errors import B3dgsError

        p = self.base_dir(loaded) / "base.json"
        if p.exists():
            old = json.loads(p.read_text())
            if Path(old["base_run"]).resolve() != Path(loaded.path).resolve():
                raise B3dgsError(f"{p.parent} holds rows of base run {old['base_run']}, not {loaded.path}",
                                 "pass another out_dir, or remove that directory to recompute it")
            return old
        ev = evaluate_views(loaded.module, loaded.scene.test, lpips_model=lp)
        m = loaded.metrics or {}
        res = {"scene": str(loaded.cfg.data.name), "seed": int(loaded.cfg.seed), "base_run": str(loaded.path),
               "num_gaussians": loaded.module.num_gaussians, "psnr": ev.get("psnr"), "ssim": ev.get("ssim"),
               "lpips": ev.get("lpips"), "render_fps": ev.get("render_fps"), "train_time_s": m.get("train_time_s"),
               "model": str(loaded.cfg.model.get("name"))}
        write_json(p, res)
        return res

    # ------------------------------------------------------------------ all
    def run(self) -> dict:
        from tqdm.auto import tqdm

        from b3dgs.metrics.lpips import get_lpips
        from b3dgs.runs import load_run
        from b3dgs.study.compression_tables import write_report

        lp, _ = get_lpips()
        scenes: dict[str, Any] = {}
        bar = tqdm(total=len(self.base_runs) * len(self.strategies) * len(self.keeps), desc="compression rows", disable=not self.cfg.get("progress_bar", True))
        seen: dict[tuple, Path] = {}
        for run in self.base_runs:
            cfg = OmegaConf.load(run / "config.yaml")
            ident = (str(cfg.data.name), int(cfg.seed))
            if ident in seen:
                from b3dgs.errors import B3dgsError

                raise B3dgsError(f"base runs {seen[ident]} and {run} are both scene {ident[0]!r} seed {ident[1]}",
                                 "pass one base run per scene and seed (e.g. only the standard runs)")
            seen[ident] = run
            key = json.dumps(OmegaConf.to_container(cfg.data, resolve=True), sort_keys=True)
            loaded = load_run(run, scene=scenes.get(key))
            scenes[key] = loaded.scene
            # rows and cached scores in the base's folder are of these settings only
            settings = {k: OmegaConf.to_container(self.cfg, resolve=True).get(k) for k in PROTOCOL_KEYS}
            settings["base_checkpoint"] = (loaded.metrics or {}).get("checkpoint")  # a retrained base: other rows
            check_stored_protocol(self.base_dir(loaded), flatten(settings),
                                  fix="pass another out_dir, or the settings of the rows there (their protocol.json)")
            base = self.base_row(loaded, lp)
            for name, fn in self.strategies:
                for keep in self.keeps:
                    self.run_row(name, fn, keep, loaded, base, lp)
                    bar.update(1)
        bar.close()
        write_json(self.out / "meta.json", {"base_runs": [str(r) for r in self.base_runs], "keep": self.keeps,
                                           "strategies": [n for n, _ in self.strategies],
                                           "finetune_steps": int(self.cfg.finetune_steps),
                                           "finetune_overrides": list(self.cfg.finetune_overrides or []),
                                           "score_max_side": self.cfg.get("score_max_side")})
        return write_report(self.out, plots=bool(self.cfg.get("plots", True)))


def _check_score(name: str, s: torch.Tensor, n: int) -> None:
    if s.shape != (n,):
        raise ValueError(f"pruning score {name!r} returned shape {tuple(s.shape)}, expected ({n},)")
    if torch.isnan(s).any():
        raise ValueError(f"pruning score {name!r} returned NaN for {int(torch.isnan(s).sum())} Gaussians")


def _plain(state: dict) -> dict:
    return {k: v for k, v in state.items() if isinstance(v, (int, float, str, bool))}


def hydra_main() -> None:
    """Run the study from the command line (``b3dgs-study compress ...``)."""
    from b3dgs.study.cli import study_app

    study_app("compress", CompressionStudy)()

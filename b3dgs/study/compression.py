"""``b3dgs-study compress``: the compression ladder on matched checkpoints (paper appendix, compression follow-up,
with the matched PUP comparator).

Protocol per base run (a finished standard run: its scene and seed come from its own ``config.yaml``): every
pruning score (``conf/pruning/<name>.yaml``) and keep ratio starts from the same base checkpoint; a score with
``rounds`` = r prunes to keep^(1/r) of the current Gaussians, fine-tunes ``finetune_steps`` with the standard
trainer (no densification, no posterior blocks), rescores the fine-tuned model, and so on; the last round lands
on exactly round(keep × N_base) Gaussians. The row is evaluated on the test views (PSNR, SSIM, LPIPS, render
FPS) with its compression time (scoring + fine-tuning) next to the base's training time. The first round's
scores of a base are computed once and shared by every keep ratio (``scores/<name>.pt``).

Each row keeps its pruned, fine-tuned model (``<row>/point_cloud.ply``, in the scene's own frame like
``b3dgs-train``'s). Resumable: finished rows (``result.json``) are never recomputed; the tables (``compression.json``,
``compression.md``, ``plots/``) are rebuilt from the rows on disk (:func:`write_report`, below).
"""
from __future__ import annotations

import glob
import json
import logging
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf, open_dict

from b3dgs.acquisition import ScoringContext
from b3dgs.compression import keep_top
from b3dgs.errors import B3dgsError
from b3dgs.io import atomic_path, save_figure, write_json
from b3dgs.labels import method_label
from b3dgs.lifecycle import Run
from b3dgs.protocol import check_stored_protocol, check_stored_scene, flatten
from b3dgs.report.document import fmt, markdown_table
from b3dgs.report.stats import mean_sem, paired_stats

log = logging.getLogger(__name__)

#: a row's done marker (:meth:`b3dgs.lifecycle.Run.record`)
ROW_DONE = "result.json"

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
    score.validate()
    return score


def round_targets(n_base: int, keep: float, rounds: int) -> list[int]:
    """Gaussian counts after each round: keep^(i/r) × N_base, the last exactly round(keep × N_base) (>= 1)."""
    if not 0 < keep <= 1:
        raise B3dgsError(f"keep ratios must be in (0, 1], got {keep}", "pass keep=[0.55,0.35,0.2,0.1] (fractions kept)")
    out = [max(1, int(round(n_base * keep ** ((i + 1) / rounds)))) for i in range(rounds)]
    out[-1] = max(1, int(round(n_base * keep)))
    return out


class CompressionStudy:
    def __init__(self, cfg: DictConfig):
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
                             "pass finished standard run dirs, e.g. base_runs='[outputs/train/*_standard_*]' "
                             "(train them first: b3dgs-train scene=NAME model=standard)")
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
            cfg.callbacks = {}  # the base run's extra callbacks are not the fine-tune's
            cfg.trainer.max_steps = int(self.cfg.finetune_steps)
            cfg.trainer.eval_every = 10 ** 9
            cfg.merge_with(OmegaConf.from_dotlist([str(o) for o in (self.cfg.finetune_overrides or [])]))
            if self.cfg.get("threads"):
                cfg.threads = int(self.cfg.threads)
        return cfg

    def finetune(self, cfg: DictConfig, scene, params: dict, seed: int):
        """A fresh standard module holding ``params``, trained ``cfg.trainer.max_steps`` steps (new Adam state, as
        PUP's refine stage); returns it on its renderer's device."""
        run = Run(cfg, self.out / ".lightning")  # the base run's config, validated when it trained
        # the study's threads stay as they are; the fine-tune's guard counters are not recorded
        module = run.start(scene, seed=seed, threads=False, reset_guards=False, init=False)
        module._set_params({k: v.detach().cpu().clone() for k, v in params.items()})
        module._init_states()
        run.fit(enable_progress_bar=False, enable_checkpointing=False)
        module.eval()
        return module

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
        with atomic_path(path) as tmp:
            torch.save({"score": s, "time_s": dt, "state": _plain(state)}, tmp)
        return s, dt, _plain(state)

    def run_row(self, name: str, score_fn, keep: float, loaded, base_eval: dict, lp) -> dict:
        targets = round_targets(loaded.module.num_gaussians, keep, int(score_fn.rounds))
        return self._rounds(self.base_dir(loaded) / f"{name}_k{int(round(keep * 100)):02d}", name, keep, targets,
                            score_fn, loaded, base_eval, lp)

    def _rounds(self, d: Path, name: str, keep: float, targets: list, score_fn, loaded, base_eval: dict, lp,
                **control) -> dict:
        """The row in ``d``: per round, prune to its target by ``score_fn`` (None: nothing pruned) and fine-tune."""
        done = Run(run_dir=d).recorded(ROW_DONE)
        if done is not None:  # a finished row is never recomputed
            return done
        seed = int(loaded.cfg.seed)
        ft_cfg = self.finetune_cfg(loaded.cfg)
        module, state, per_round = loaded.module, {}, []
        score_s = finetune_s = 0.0
        for r, target in enumerate(targets):
            params, dt = {k: v.detach().cpu() for k, v in module.params().items()}, 0.0
            if score_fn is not None:
                ctx = ScoringContext([module], loaded.scene.train, score_max_side=self.cfg.get("score_max_side"),
                                     extent=float(loaded.scene.extent), seed=seed)
                info = {"ctx": ctx, "cache": {},
                        "generator": torch.Generator().manual_seed(seed * 1000003 + 7919 * r + 1)}
                if r == 0:
                    s, dt, state = self.first_scores(name, score_fn, loaded, info)
                else:
                    t0 = time.perf_counter()
                    s = score_fn.score(splats=module.params(), optimizers=None, state=state, step=r,
                                       info=info).detach().cpu()
                    dt = time.perf_counter() - t0
                    _check_score(name, s, module.num_gaussians)
                mask = keep_top(s, target)
                params = {k: v[mask] for k, v in params.items()}
            score_s += dt
            t0 = time.perf_counter()
            module = self.finetune(ft_cfg, loaded.scene, params, seed)
            ft = time.perf_counter() - t0
            finetune_s += ft
            kept = module.num_gaussians if score_fn is None else int(mask.sum())
            per_round.append({"round": r, "kept": kept, "score_s": dt, "finetune_s": ft})
            log.info("%s %s keep %.2f round %d: %d Gaussians (score %.1f s, fine-tune %.1f s)",
                     d.parent.name, name, keep, r, kept, dt, ft)
        return self.write_row(d, module, loaded, lp, name, keep, len(targets), score_s, finetune_s, per_round,
                              {k: v for k, v in state.items() if isinstance(v, (int, float))}, base_eval, **control)

    def write_row(self, d: Path, module, loaded, lp, name: str, keep: float, rounds: int, score_s: float,
                  finetune_s: float, per_round: list, guards: dict, base_eval: dict, **control) -> dict:
        """A finished row: its model evaluated on the test views and kept (:func:`keep_ply`), then ``result.json`` (the
        row's done marker, :meth:`b3dgs.lifecycle.Run.record`)."""
        from b3dgs.metrics.views import evaluate_views

        ev = evaluate_views(module, loaded.scene.test, lpips_model=lp)
        keep_ply(d, module, loaded.scene)
        n_base = loaded.module.num_gaussians
        res = {"scene": str(loaded.cfg.data.name), "seed": int(loaded.cfg.seed), "base_run": str(loaded.path),
               "strategy": name, "keep": keep, "rounds": rounds, "finetune_steps": int(self.cfg.finetune_steps),
               "num_base": n_base, "num_gaussians": module.num_gaussians,
               "kept_fraction": module.num_gaussians / max(n_base, 1),
               "psnr": ev.get("psnr"), "ssim": ev.get("ssim"), "lpips": ev.get("lpips"), "render_fps": ev.get("render_fps"),
               "score_s": score_s, "finetune_s": finetune_s, "time_s": score_s + finetune_s, "per_round": per_round,
               "guards": guards, "base": base_eval, **control, "score_max_side": self.cfg.get("score_max_side")}
        return Run(run_dir=d).record(ROW_DONE, res)

    def control_row(self, rounds: int, loaded, base_eval: dict, lp) -> dict:
        """The fine-tune-only control at keep 100 %: ``rounds`` fine-tunes of ``finetune_steps`` (fresh Adam each, as a
        pruning row with that many rounds) with nothing pruned, so a row's PSNR change splits into pruning and the
        extra training steps (row − control, control − base)."""
        name = f"finetune_only_r{rounds}"
        return self._rounds(self.base_dir(loaded) / f"{name}_k100", name, 1.0, [None] * rounds, None, loaded,
                            base_eval, lp, control=True)

    def control_rounds(self) -> list[int]:
        """Round counts of the fine-tune-only controls: one per distinct ``rounds`` of the scores (none when off)."""
        if not self.cfg.get("finetune_control", True):
            return []
        return sorted({int(fn.rounds) for _, fn in self.strategies})

    def base_row(self, loaded, lp) -> dict:
        from b3dgs.metrics.views import evaluate_views

        base = Run(run_dir=self.base_dir(loaded))  # the scene-seed's folder: its record of the base run's evaluation
        old = base.recorded("base.json")
        if old is not None:
            if Path(old["base_run"]).resolve() != Path(loaded.path).resolve():
                raise B3dgsError(f"{base.run_dir} holds rows of base run {old['base_run']}, not {loaded.path}",
                                 "pass another out_dir, or remove that directory to recompute it")
            return old
        ev = evaluate_views(loaded.module, loaded.scene.test, lpips_model=lp)
        m = loaded.metrics or {}
        res = {"scene": str(loaded.cfg.data.name), "seed": int(loaded.cfg.seed), "base_run": str(loaded.path),
               "num_gaussians": loaded.module.num_gaussians, "psnr": ev.get("psnr"), "ssim": ev.get("ssim"),
               "lpips": ev.get("lpips"), "render_fps": ev.get("render_fps"), "train_time_s": m.get("train_time_s"),
               "model": method_label(loaded.cfg)}
        return base.record("base.json", res)

    # ------------------------------------------------------------------ all
    def run(self) -> dict:
        from b3dgs.progress import progress

        from b3dgs.metrics.lpips import get_lpips
        from b3dgs.runs import load_run

        lp, _ = get_lpips()
        scenes: dict[str, Any] = {}
        bar = progress(total=len(self.base_runs) * len(self.strategies) * len(self.keeps), desc="compression rows", disable=not self.cfg.get("progress_bar", True))
        seen: dict[tuple, Path] = {}
        for run in self.base_runs:
            cfg = OmegaConf.load(run / "config.yaml")
            ident = (str(cfg.data.name), int(cfg.seed))
            if ident in seen:
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
            check_stored_scene(self.base_dir(loaded), loaded.scene,
                               fix=f"pass another out_dir (or remove {self.base_dir(loaded)} to recompute its rows)")
            base = self.base_row(loaded, lp)
            for rounds in self.control_rounds():
                self.control_row(rounds, loaded, base, lp)
            for name, fn in self.strategies:
                for keep in self.keeps:
                    self.run_row(name, fn, keep, loaded, base, lp)
                    bar.update(1)
        bar.close()
        write_json(self.out / "meta.json", {"base_runs": [str(r) for r in self.base_runs], "keep": self.keeps,
                                           "strategies": [n for n, _ in self.strategies]
                                           + [f"finetune_only_r{r}" for r in self.control_rounds()],
                                           "finetune_steps": int(self.cfg.finetune_steps),
                                           "finetune_overrides": list(self.cfg.finetune_overrides or []),
                                           "score_max_side": self.cfg.get("score_max_side")})
        return write_report(self.out, plots=bool(self.cfg.get("plots", True)))


def keep_ply(row_dir: Path, module, scene) -> Path:
    """The row's pruned, fine-tuned model as ``<row>/point_cloud.ply`` in the scene's own frame (as b3dgs-train's)."""
    from b3dgs.data.scene import scene_transform
    from b3dgs.ply import frame_comments, write_splats

    frame = scene_transform(scene)
    return write_splats(row_dir / "point_cloud.ply", {k: v.detach() for k, v in module.params().items()},
                        frame.inverse(), comments=frame_comments(frame))


def _check_score(name: str, s: torch.Tensor, n: int) -> None:
    if s.shape != (n,):
        raise B3dgsError(f"pruning score {name!r} returned shape {tuple(s.shape)}, expected ({n},)",
                         "its score() must return one value per Gaussian of the splats it is given")
    if torch.isnan(s).any():
        raise B3dgsError(f"pruning score {name!r} returned NaN for {int(torch.isnan(s).sum())} Gaussians",
                         "its score() must return finite values; check the run it scores, or its settings")


def _plain(state: dict) -> dict:
    return {k: v for k, v in state.items() if isinstance(v, (int, float, str, bool))}


# ------------------------------------------------------------------------------------------------ tables
# The study's outputs: ``compression.json``, ``compression.md`` (laid out like the paper's keep-ratio table, plus
# quality, size, speed and time per row, and paired differences) and ``plots/`` (PSNR against kept Gaussians per
# scene; PSNR against compression time).

# (a, b): report a − b where both are present. The paper's primary contrast, then the dedicated comparator
# against the posterior-aware score.
PAIRS = (("posterior_importance", "opacity"), ("pup", "posterior_importance"), ("pup", "opacity"))
METRICS = ("psnr", "ssim", "lpips", "kept_fraction", "num_gaussians", "render_fps", "time_s", "score_s", "finetune_s")


def load(out: Path) -> tuple[list[dict], list[dict], dict]:
    rows = [json.loads(p.read_text()) for p in sorted(out.glob("*/s*/*_k*/result.json"))]
    bases = [json.loads(p.read_text()) for p in sorted(out.glob("*/s*/base.json"))]
    meta = json.loads((out / "meta.json").read_text()) if (out / "meta.json").exists() else {}
    return rows, bases, meta


def _macro(per_scene: dict[str, list[float]]) -> Optional[float]:
    means = [float(np.mean(v)) for v in per_scene.values() if v]
    return float(np.mean(means)) if means else None


def summarize(out: Path) -> dict:
    rows, bases, meta = load(out)
    strategies = meta.get("strategies") or sorted({r["strategy"] for r in rows})
    keeps = sorted({float(r["keep"]) for r in rows}, reverse=True)
    scenes = sorted({r["scene"] for r in rows})
    cells: dict[str, dict[str, Any]] = {}
    for s in strategies:
        for k in keeps:
            rs = [r for r in rows if r["strategy"] == s and float(r["keep"]) == k]
            if not rs:
                continue
            ent: dict[str, Any] = {"strategy": s, "keep": k, "n_runs": len(rs), "scenes": {}}
            for sc in scenes:
                srs = [r for r in rs if r["scene"] == sc]
                if srs:
                    ent["scenes"][sc] = {m: mean_sem([r.get(m) for r in srs]) for m in METRICS}
                    ent["scenes"][sc]["n_seeds"] = len(srs)
            for m in METRICS:
                ent[m] = _macro({sc: [r[m] for r in rs if r["scene"] == sc and r.get(m) is not None] for sc in scenes})
            cells[f"{s}@{k}"] = ent
    base_metrics = ("psnr", "ssim", "lpips", "num_gaussians", "render_fps", "train_time_s")
    base = {sc: {m: mean_sem([b.get(m) for b in bases if b["scene"] == sc])[0] for m in base_metrics} for sc in scenes}
    base_macro = {m: _macro({sc: [base[sc][m]] for sc in scenes if base[sc].get(m) is not None}) for m in base_metrics}
    pairs = []
    for a, b in PAIRS:
        if a not in strategies or b not in strategies:
            continue
        for k in keeps:
            by = {(r["strategy"], r["scene"], int(r["seed"])): r for r in rows if float(r["keep"]) == k}
            units = sorted({(sc, sd) for (st, sc, sd) in by if st == a} & {(sc, sd) for (st, sc, sd) in by if st == b})
            if not units:
                continue
            d_unit = [by[(a, sc, sd)]["psnr"] - by[(b, sc, sd)]["psnr"] for sc, sd in units]
            per_scene = {sc: float(np.mean([d for (u, d) in zip(units, d_unit) if u[0] == sc])) for sc in scenes
                         if any(u[0] == sc for u in units)}
            st = paired_stats(list(per_scene.values()), higher_is_better=True)
            pairs.append({"a": a, "b": b, "keep": k, "per_scene": per_scene, "scene_seed_wins": int(sum(d > 0 for d in d_unit)),
                          "scene_seed_n": len(d_unit), **st})
    return {"strategies": strategies, "keeps": keeps, "scenes": scenes, "cells": cells, "base": base,
            "base_macro": base_macro, "pairs": pairs, "meta": meta, "n_rows": len(rows), "n_bases": len(bases)}


def _f(v, nd=3, signed=False) -> str:
    return fmt(v, f".{nd}f", signed)


def markdown(s: dict) -> str:
    st, keeps, cells = s["strategies"], s["keeps"], s["cells"]
    meta = s.get("meta", {})
    L = ["# Compression ladder on matched checkpoints", ""]
    L.append(f"{s['n_rows']} rows over scenes {s['scenes']}; every score and keep ratio starts from the same finished "
             f"standard run per scene and seed (base runs: {s.get('n_bases', len(meta.get('base_runs', [])))}). Fine-tune "
             f"{meta.get('finetune_steps')} steps per prune round, training views scored at "
             f"{meta.get('score_max_side') or 'full size'} px. Macro means over scenes of per-scene seed means.")
    L += ["", "## PSNR by keep ratio (the paper's layout)", ""]
    cols = [x for x in st if any(f"{x}@{k}" in cells for k in keeps)]
    extra = [(a, b) for a, b in PAIRS if a in cols and b in cols]
    rows = []
    for k in keeps:
        vals = {c: cells.get(f"{c}@{k}", {}).get("psnr") for c in cols}
        best = max((v for v in vals.values() if v is not None), default=None)
        cell = [("**" + _f(vals[c]) + "**") if vals[c] is not None and vals[c] == best else _f(vals[c]) for c in cols]
        diffs = [_f(None if vals[a] is None or vals[b] is None else vals[a] - vals[b], signed=True) for a, b in extra]
        rows.append([str(int(round(k * 100))), *cell, *diffs])
    L += markdown_table(["Keep %", *cols, *(f"{a} − {b}" for a, b in extra)], rows)
    bm = s["base_macro"]
    L += ["", f"Base (no pruning): PSNR {_f(bm.get('psnr'))}, LPIPS {_f(bm.get('lpips'), 4)}, "
          f"{_f(bm.get('num_gaussians'), 0)} Gaussians, {_f(bm.get('render_fps'), 1)} FPS, trained in "
          f"{_f(bm.get('train_time_s'), 0)} s.", ""]
    controls = [(c, e) for c in st if c.startswith("finetune_only") for e in [cells.get(f"{c}@1.0")] if e]
    if controls:
        L += ["Fine-tune-only controls (keep 100 %, the rounds of fine-tuning a pruning row gets, nothing pruned): "
              + "; ".join(f"{c}: PSNR {_f(e['psnr'])} ({_f(None if bm.get('psnr') is None or e['psnr'] is None else e['psnr'] - bm['psnr'], signed=True)} dB over the base)"
                          for c, e in controls)
              + ". A pruning row's PSNR minus its control's is the effect of pruning alone.", ""]
    L += ["## Quality, size, speed and time per row", ""]
    rows = [[c, str(int(round(k * 100))), _f(e["psnr"]), _f(e["ssim"], 4), _f(e["lpips"], 4),
             _f(100 * e["kept_fraction"] if e["kept_fraction"] is not None else None, 1), _f(e["num_gaussians"], 0),
             _f(e["render_fps"], 1), _f(e["score_s"], 1), _f(e["finetune_s"], 1), _f(e["time_s"], 1), str(e["n_runs"])]
            for c in cols for k in keeps for e in [cells.get(f"{c}@{k}")] if e]
    L += markdown_table(["Score", "Keep %", "PSNR ↑", "SSIM ↑", "LPIPS ↓", "kept % of base", "#Gaussians", "FPS ↑",
                         "score s", "fine-tune s", "compression s", "runs"], rows)
    L += ["", "compression s = scoring (every round; the first round's scores are computed once per base and shared "
          "by the keep ratios, each row still counts them) + fine-tuning; the base's own training time is above.", ""]
    L += ["## Per-scene PSNR (seed mean ± SEM)", ""]
    rows = [[c, str(int(round(k * 100))),
             *(f"{_f(v['psnr'][0])} ± {_f(v['psnr'][1])} (n={v['n_seeds']})" if (v := e["scenes"].get(sc)) else "—"
               for sc in s["scenes"])]
            for c in cols for k in keeps for e in [cells.get(f"{c}@{k}")] if e]
    rows.append(["base", "100", *(_f(s["base"][sc].get("psnr")) for sc in s["scenes"])])
    L += markdown_table(["Score", "Keep %", *s["scenes"]], rows)
    if s["pairs"]:
        L += ["", "## Paired PSNR differences", ""]
        L += markdown_table(["a − b", "Keep %", "mean Δ (scenes)", "CI", "CI method", "scene wins / losses", "p (2-sided)",
                             "p floor", "scene-seed wins"],
                            [[f"{p['a']} − {p['b']}", str(int(round(p["keep"] * 100))), _f(p["mean"], 3, True),
                              f"[{_f(p['ci'].get('low'), 3, True)}, {_f(p['ci'].get('high'), 3, True)}]",
                              p["ci"].get("method", "—"), f"{p['wins']} / {p['losses']}", _f(p["p_two_sided"], 3),
                              _f(p["p_floor"], 3), f"{p['scene_seed_wins']}/{p['scene_seed_n']}"] for p in s["pairs"]])
        L += ["", "Units are scenes (per-scene means over seeds): cluster bootstrap CI and exact sign-flip p "
              "(b3dgs.report.stats); with n scenes no two-sided p can fall below 2/2ⁿ."]
    if s.get("plots"):  # relative to the markdown file
        L += ["", "![PSNR against kept Gaussians](plots/ladder.png)", "",
              "![PSNR against compression time](plots/time.png)"]
    return "\n".join(L) + "\n"


def plot(s: dict, out: Path) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = out / "plots"
    d.mkdir(parents=True, exist_ok=True)
    scenes = s["scenes"]
    fig, axes = plt.subplots(1, max(1, len(scenes)), figsize=(5.2 * max(1, len(scenes)), 4.0), squeeze=False)
    for ax, sc in zip(axes[0], scenes):
        for c in s["strategies"]:
            pts = []
            for k in s["keeps"]:
                e = s["cells"].get(f"{c}@{k}", {}).get("scenes", {}).get(sc)
                if e:
                    pts.append((e["num_gaussians"][0], e["psnr"][0], e["psnr"][1] or 0.0))
            if pts:
                x, y, err = zip(*sorted(pts))
                ax.errorbar(x, y, yerr=err, marker="o", ms=4, capsize=2, label=c)
        b = s["base"].get(sc, {})
        if b.get("psnr") is not None:
            ax.plot([b["num_gaussians"]], [b["psnr"]], marker="*", ms=12, color="k", ls="none", label="base")
        ax.set(xscale="log", xlabel="Gaussians kept", ylabel="test PSNR (dB)", title=sc)
        ax.grid(alpha=0.3)
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, d / "ladder.png", dpi=110)

    fig, ax = plt.subplots(figsize=(6.0, 4.2))
    for c in s["strategies"]:
        pts = [(e["time_s"], e["psnr"], int(round(e["keep"] * 100))) for k in s["keeps"]
               if (e := s["cells"].get(f"{c}@{k}")) and e.get("time_s") is not None]
        if pts:
            x, y, lab = zip(*pts)
            ax.plot(x, y, marker="o", ls="-", label=c)
            for xi, yi, li in pts:
                ax.annotate(f"{li}%", (xi, yi), fontsize=6, xytext=(2, 2), textcoords="offset points")
    ax.set(xlabel="compression time per row (s): scoring + fine-tuning", ylabel="test PSNR (dB), macro over scenes")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    save_figure(fig, d / "time.png", dpi=110)
    return ["plots/ladder.png", "plots/time.png"]


def write_report(out: Path, plots: bool = True) -> dict:
    out = Path(out)
    s = summarize(out)
    if plots and s["n_rows"]:
        s["plots"] = plot(s, out)
    write_json(out / "compression.json", s)
    with atomic_path(out / "compression.md") as tmp:
        Path(tmp).write_text(markdown(s))
    return s


def hydra_main() -> None:
    """Run the study from the command line (``b3dgs-study compress ...``)."""
    from b3dgs.study.cli import study_app

    study_app("compress", CompressionStudy)()

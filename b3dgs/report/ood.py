"""Support-deficit OOD study (the paper's appendix): does a regime's per-view uncertainty flag the
test views that the training cameras support least?

Per test view, support score = distance from its camera centre to the nearest training camera centre,
divided by the scene extent. Views at or below the ``quantile`` of the scores are in-distribution (ID),
views at or above the ``1 - quantile`` one are OOD, the middle band is ignored. A regime's per-view mean
uncertainty (``uq.json`` per_view ``score``, default ``mean_var``) is the detector: AUROC and AUPRC
(scikit-learn, OOD = positive) and the OOD − ID gap of mean uncertainty, per run; then seed means per
scene and the macro mean over scenes. This probes geometric support only, not semantic novelty.

The camera centres are not stored in run dirs, so the scene is reloaded from the run's ``config.yaml``
(``data`` node, train subset included); each distinct data config is loaded once.
"""
from __future__ import annotations

import json
from typing import Optional, Sequence

import numpy as np

from b3dgs.report.collect import ReportError, Run, method_order

__all__ = ["support_distances", "support_scores", "label_views", "detect", "ood_study"]

_SCENES: dict[str, dict[str, float]] = {}


def support_distances(train_centres, test_centres, extent: float) -> np.ndarray:
    """The OOD support score of each test camera: the distance from its centre to the nearest training camera
    centre, / the scene extent (1 where the extent is not positive). Float64 (:mod:`b3dgs.neighbours`)."""
    from b3dgs.neighbours import nearest_distances

    ext = extent if extent > 0 else 1.0
    return nearest_distances(np.asarray(test_centres, dtype=np.float64).reshape(-1, 3),
                             np.asarray(train_centres, dtype=np.float64).reshape(-1, 3)) / ext


def support_scores(data_cfg: dict) -> dict[str, float]:
    """{test view name: nearest-train-centre distance / extent} for the scene of a ``data`` config."""
    key = json.dumps(data_cfg, sort_keys=True, default=str)
    if key not in _SCENES:
        from omegaconf import OmegaConf

        from b3dgs.data.scene import poses_only
        from b3dgs.lifecycle import data_module

        try:
            with poses_only():  # the cameras' centres and the extent only
                dm = data_module(OmegaConf.create(data_cfg))
        except Exception as e:  # missing scene files, changed paths
            raise ReportError(f"OOD study: cannot reload the scene of data={data_cfg.get('name')} "
                              f"(path={data_cfg.get('path')}): {e}",
                              fix="restore the scene at that path (the runs' data.path), or pass ood.enabled=false "
                                  "to skip the OOD study") from e
        scene = dm.scene
        dist = support_distances([c.center64 for c in scene.train], [c.center64 for c in scene.test], scene.extent)
        _SCENES[key] = {c.name: float(d) for c, d in zip(scene.test, dist)}
    return _SCENES[key]


def label_views(scores: Sequence[float], quantile: float) -> np.ndarray:
    """1 for OOD (>= the 1-q quantile), 0 for ID (<= the q quantile), -1 for the ignored middle band."""
    if not 0 < quantile < 0.5:
        raise ReportError(f"ood.quantile={quantile} must lie in (0, 0.5) (ID and OOD bands may not overlap)",
                          fix="pass ood.quantile strictly between 0 and 0.5, e.g. the default 1/3 (the best- and "
                              "worst-supported thirds of the test views)")
    s = np.asarray(scores, dtype=float)
    lo, hi = np.quantile(s, quantile), np.quantile(s, 1 - quantile)
    lab = np.full(s.shape, -1)
    lab[s <= lo] = 0
    lab[s >= hi] = 1
    return lab


def detect(uncertainty: Sequence[float], labels: Sequence[int]) -> Optional[dict]:
    """AUROC, AUPRC and the OOD − ID mean gap of ``uncertainty`` on labelled views (None if a class is empty)."""
    from sklearn.metrics import average_precision_score, roc_auc_score

    u, y = np.asarray(uncertainty, dtype=float), np.asarray(labels)
    keep = y >= 0
    u, y = u[keep], y[keep]
    if y.sum() == 0 or y.sum() == y.size:
        return None
    return {"auroc": float(roc_auc_score(y, u)), "auprc": float(average_precision_score(y, u)),
            "gap": float(u[y == 1].mean() - u[y == 0].mean()), "n_id": int((y == 0).sum()),
            "n_ood": int(y.sum()), "prevalence": float(y.mean())}


def _macro(rows: list[dict], key: str) -> Optional[float]:
    per_scene = {}
    for r in rows:
        if r.get(key) is not None:
            per_scene.setdefault(r["scene"], []).append(r[key])
    return float(np.mean([np.mean(v) for v in per_scene.values()])) if per_scene else None


def ood_study(runs: Sequence[Run], quantile: float = 1 / 3, score: str = "mean_var",
              regimes: Optional[Sequence[str]] = None) -> dict:
    """{"rows": {"method (regime)": {auroc, auprc, gap, n_scenes, n_runs}}, "runs": [...], "views": [...]}."""
    per_run, views, skipped = [], [], []
    for r in runs:
        for regime, summ in r.uq.items():
            if regimes and regime not in regimes:
                continue
            pv = [v for v in summ.get("per_view") or [] if isinstance(v.get(score), (int, float))]
            if not pv:
                continue
            support = support_scores(r.config["data"])
            pv = [v for v in pv if v.get("name") in support]
            if len(pv) < 2:
                skipped.append(f"{r.path} {regime}: fewer than 2 test views matched the scene")
                continue
            s = [support[v["name"]] for v in pv]
            lab = label_views(s, quantile)
            res = detect([v[score] for v in pv], lab)
            label = f"{r.method} ({regime})"
            if res is None:
                skipped.append(f"{r.path} {regime}: ID or OOD band empty (tied support scores)")
                continue
            per_run.append({"row": label, "scene": r.scene, "seed": r.seed, "method": r.method,
                            "regime": regime, "path": str(r.path), **res})
            views += [{"row": label, "scene": r.scene, "seed": r.seed, "name": v["name"], "support": si,
                       "uncertainty": float(v[score]), "label": int(li)} for v, si, li in zip(pv, s, lab)]
    rows = {}
    order = method_order(x["method"] for x in per_run)
    labels = {x["row"]: x["method"] for x in per_run}
    for label in sorted(labels, key=lambda lb: (order.index(labels[lb]), lb)):
        sel = [x for x in per_run if x["row"] == label]
        rows[label] = {k: _macro(sel, k) for k in ("auroc", "auprc", "gap", "prevalence")}
        rows[label].update(n_scenes=len({x["scene"] for x in sel}), n_runs=len(sel))
    return {"quantile": quantile, "score": score, "rows": rows, "runs": per_run, "views": views, "skipped": skipped}


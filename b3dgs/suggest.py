"""``b3dgs-suggest run=RUN n=8``: where to take the next photos: candidate camera poses scored by what the trained
run's posterior does not know, selected with the policy's batch rule and shown (``conf/suggest.yaml``).

Candidates (in the run's normalised frame, every one looking at the scene centre, the point the training cameras look
at): rings around the centre spanning the training cameras' distances and elevations (elevations widened by
``generate.margin_deg``), and the training poses jittered; for a forward-facing capture (every training camera within
90° of their mean direction from the centre: all on one side, as LLFF or fox) only the frontal half-space, widened by
the margin. Or ``candidates=FILE``: a 3DGS ``cameras.json``, a nerfstudio camera path, or another scene folder's
poses. A candidate inside the dense core of the Gaussians (closer to the centre than ``core_quantile`` of the opaque
Gaussians' distances, capped at 0.9 × the nearest training camera's) or whose render covers less than
``min_coverage`` of its pixels is dropped, and counted.

Scoring goes through the acquisition policy's public interface, as ``b3dgs-study`` uses it (``conf/acquisition/
<policy>.yaml``, a :class:`~b3dgs.acquisition.ScoringContext` of the run's model and training views, a batch
selector): ``info_gain`` (default) scores the drop of the targets' predictive colour variance under the directional SH
posterior, with the candidates and a dense ring of novel target poses as its pool (:class:`TargetPool`: the targets
are scored and conditioned on, never suggested), and selects with ``greedy_conditioned``, so suggestions do not stack
on one spot; ``cover``, ``farthest`` and ``uniform`` keep their own batch rule.

Written to ``RUN/suggest/`` (through the run's manifest; a rerun replaces only the files this command writes):
``cameras.json`` (the official 3DGS format, ranked) and ``path.json`` (a nerfstudio camera path, ranked; ``b3dgs-render
path=RUN/suggest/path.json`` renders it), ``preview_<rank>.png`` (the render beside its per-pixel information map,
:func:`information_map`), ``plot.png`` (training cameras, every candidate coloured by score and the picks, from above
and from the side) and ``suggest.json`` (each pose, score and rank, and the dropped counts).
"""
from __future__ import annotations

import json
import logging
import math
import re
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Optional, Sequence

import hydra
import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from torch import Tensor

from b3dgs.acquisition import AcquisitionPolicy, ScoringContext, Selection
from b3dgs.data.scene import infer_data_option, load_scene, scene_frame, scene_transform
from b3dgs.data.scene import unit_rows as _unit
from b3dgs.errors import B3dgsError, cli_main, known_errors
from b3dgs.io import save_figure, write_json
from b3dgs.render_cli import _caption, _look_at as look_at_view, nerfstudio_path
from b3dgs.rundir import claim_in_run, out_dir_lock, read_manifest, remove_listed
from b3dgs.study.active import load_batch, load_policy
from b3dgs.train import CONF_DIR
from b3dgs.types import Camera

log = logging.getLogger(__name__)

__all__ = ["TargetPool", "generate_candidates", "information_map", "main", "read_candidates", "scene_frame",
           "sh_gain_per_gaussian", "suggest"]

#: the files one b3dgs-suggest writes into its folder (a rerun removes exactly these, then writes its own)
OWN_FILE = re.compile(r"(cameras|path|suggest)\.json|plot\.png|preview_\d{2,}\.png")
DEFAULT_BATCH = "greedy_conditioned"


def _look_at(name: str, pos: np.ndarray, target: np.ndarray, up: np.ndarray, ref: Camera) -> Camera:
    """A camera at ``pos`` looking at ``target`` (``up`` roughly up), with ``ref``'s intrinsics and size."""
    f = _unit(target - pos)
    if abs(float(f @ up)) > 0.999:  # looking straight along up: any other up will do
        up = np.array([1.0, 0.0, 0.0]) if abs(f[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    view = look_at_view(pos, target, up)
    return Camera(name, ref.K.detach().float().cpu().clone(), torch.from_numpy(view).float(), ref.width, ref.height)


def _rings(fr: dict, ref: Camera, azimuths: int, elevations: int, distances: Sequence[float], margin_deg: float,
           prefix: str) -> list[Camera]:
    """Poses on rings around the centre (azimuths × elevations spanning the training ones widened by ``margin_deg``,
    clipped to ±80°, × ``distances``), looking at it."""
    m = math.radians(float(margin_deg))
    lo, hi = float(fr["elev"].min()) - m, float(fr["elev"].max()) + m
    lo, hi = max(lo, -math.radians(80)), min(hi, math.radians(80))
    els = [0.5 * (lo + hi)] if int(elevations) == 1 else np.linspace(lo, hi, int(elevations)).tolist()
    out = []
    for di, r in enumerate(distances):
        for ei, e in enumerate(els):
            for ai, t in enumerate(np.linspace(0.0, 2 * math.pi, int(azimuths), endpoint=False)):
                d = math.cos(e) * (math.cos(t) * fr["a"] + math.sin(t) * fr["b"]) + math.sin(e) * fr["up"]
                pos = fr["centre"] + float(r) * d
                out.append(_look_at(f"{prefix}_d{di}_e{ei}_a{ai:03d}", pos, fr["centre"], fr["up"], ref))
    return out


def _reference(train: Sequence[Camera]) -> Camera:
    return sorted(train, key=lambda c: c.name)[0]


def generate_candidates(train: Sequence[Camera], gen, seed: int = 0) -> tuple[list[Camera], dict]:
    """The generated candidates (module doc; before :func:`frontal` drops those behind a forward-facing capture) and
    the frame they were generated in (:func:`scene_frame`)."""
    fr = scene_frame(train, float(gen.margin_deg))
    ref = _reference(train)
    r_lo, r_hi = float(fr["dist"].min()), float(fr["dist"].max())
    k = int(gen.distances)
    dists = [0.5 * (r_lo + r_hi)] if k == 1 or r_hi - r_lo < 1e-6 * max(r_hi, 1e-9) else np.linspace(r_lo, r_hi, k).tolist()
    cands = _rings(fr, ref, int(gen.azimuths), int(gen.elevations), dists, float(gen.margin_deg), "ring")
    rng = np.random.default_rng(int(seed))
    sigma = float(gen.jitter_scale) * float(np.median(fr["dist"]))
    for c in sorted(train, key=lambda c: c.name):
        base = c.center.double().cpu().numpy()
        cup = -c.camtoworld[:3, 1].double().cpu().numpy()
        for j in range(int(gen.jitter_per_camera)):
            pos = base + rng.normal(0.0, sigma, 3)
            if np.linalg.norm(pos - fr["centre"]) < 1e-6:
                continue
            stem = re.sub(r"[^A-Za-z0-9_.-]", "_", Path(c.name).stem)
            cands.append(_look_at(f"jitter_{stem}_{j}", pos, fr["centre"], cup, c.with_image(None)))
    return cands, fr


def frontal(cams: Sequence[Camera], fr: dict) -> list[Camera]:
    """Those of ``cams`` in the frontal half-space of a forward-facing capture widened by the margin (all of them for
    another capture)."""
    return [c for c in cams
            if float(_unit(c.center.double().cpu().numpy() - fr["centre"]) @ fr["axis"]) >= fr["cos_limit"]]


def target_ring(fr: dict, train: Sequence[Camera], targets) -> list[Camera]:
    """info_gain's targets: a dense ring of novel poses at the training cameras' median distance (frontal only for a
    forward-facing capture)."""
    return frontal(_rings(fr, _reference(train), int(targets.azimuths), int(targets.elevations),
                          [float(np.median(fr["dist"]))], 0.0, "target"), fr)


# ---------------------------------------------------------------------------------------------- candidates from a file
def _camera_from_c2w(name: str, R: np.ndarray, centre: np.ndarray, fx: float, fy: float, W: int, H: int) -> Camera:
    view = np.eye(4)
    view[:3, :3], view[:3, 3] = R.T, -R.T @ centre
    K = torch.tensor([[fx, 0.0, W / 2.0], [0.0, fy, H / 2.0], [0.0, 0.0, 1.0]], dtype=torch.float32)
    return Camera(name, K, torch.from_numpy(view).float(), int(W), int(H))


def _move(cams: Sequence[Camera], T) -> list[Camera]:
    """``cams`` mapped by the similarity ``T`` (x' = s R x + t: centres moved, camera axes turned with the world)."""
    R = np.asarray(T.rotation, np.float64)
    out = []
    for c in cams:
        c2w = c.camtoworld.double().cpu().numpy()
        K = c.K.double().cpu().numpy()
        cam = _camera_from_c2w(c.name, R @ c2w[:3, :3], T.apply(c2w[None, :3, 3])[0], K[0, 0], K[1, 1], c.width, c.height)
        out.append(Camera(cam.name, c.K.detach().float().cpu().clone(), cam.viewmat, c.width, c.height))
    return out


def read_candidates(path: str, scene) -> list[Camera]:
    """``candidates=PATH``: a 3DGS ``cameras.json`` (a list of camera entries), a nerfstudio camera path (an object with
    ``camera_path``: :func:`b3dgs.render_cli.nerfstudio_path`), or a scene folder (colmap, transforms, llff: its
    training and test poses), all in the scene's own frame (that of ``point_cloud.ply`` and ``b3dgs-export``), mapped
    into the run's normalised frame. Names are made unique."""
    p = Path(str(path)).expanduser()
    fix = ("pass candidates= a 3DGS cameras.json, a nerfstudio camera-path .json or a scene folder (colmap, "
           "transforms, llff), or null to generate them")
    if not p.exists():
        raise B3dgsError(f"candidates={path}: no such file or folder", fix)
    T = scene_transform(scene)
    if p.is_dir():
        kind, _ = infer_data_option(p, key="candidates")
        other = load_scene("transforms" if kind == "blender" else kind, str(p), test_every=0, normalize=False)
        cams = _move([c.with_image(None) for c in list(other.train) + list(other.test)], T)
    else:
        try:
            data = json.loads(p.read_text())
        except (OSError, ValueError) as e:
            raise B3dgsError(f"candidates={path} is not a readable JSON file ({type(e).__name__}: {e})", fix) from None
        if isinstance(data, dict) and "camera_path" in data:
            cams = nerfstudio_path(p, scene)
        elif isinstance(data, list) and data:
            try:  # position, camera-to-world rotation in OpenCV axes, fx, fy, width, height; the scene's own frame
                cams = _move([_camera_from_c2w(f"{e.get('img_name', e.get('id', i))}",
                                               np.asarray(e["rotation"], np.float64).reshape(3, 3),
                                               np.asarray(e["position"], np.float64).reshape(3), float(e["fx"]),
                                               float(e["fy"]), int(e["width"]), int(e["height"]))
                              for i, e in enumerate(data)], T)
            except (KeyError, TypeError, ValueError) as e:
                raise B3dgsError(f"candidates={path} is not a 3DGS cameras.json ({type(e).__name__}: {e})", fix) from None
        else:
            raise B3dgsError(f"candidates={path} holds neither a 3DGS camera list nor a nerfstudio camera_path", fix)
    if not cams:
        raise B3dgsError(f"candidates={path} holds no cameras", fix)
    seen: dict[str, int] = {}
    out = []
    for c in cams:
        k = seen.get(c.name, 0)
        seen[c.name] = k + 1
        out.append(c if k == 0 else Camera(f"{c.name}#{k}", c.K, c.viewmat, c.width, c.height))
    return out


# ---------------------------------------------------------------------------------------------- filtering
def core_radius(module, fr: dict, quantile: float) -> float:
    """The radius of the dense core: ``quantile`` of the opaque Gaussians' distances from the centre (all of them when
    none is opaque), at most 0.9 × the nearest training camera's distance."""
    means = module.splats["means"].detach().double().cpu().numpy()
    op = torch.sigmoid(module.splats["opacities"].detach().double().cpu()).reshape(-1).numpy()
    pts = means[op > 0.5] if (op > 0.5).any() else means
    if len(pts) == 0:
        return 0.0
    d = np.linalg.norm(pts - fr["centre"], axis=1)
    return float(min(np.quantile(d, float(quantile)), 0.9 * float(fr["dist"].min())))


def filter_candidates(cands: Sequence[Camera], ctx, fr: dict, r_core: float, min_coverage: float
                      ) -> tuple[list[Camera], dict]:
    """The candidates outside the core that see something (render coverage >= ``min_coverage`` at the scoring
    resolution), and the counts of those dropped."""
    kept, core, empty = [], 0, 0
    for c in cands:
        if float(np.linalg.norm(c.center.double().cpu().numpy() - fr["centre"])) <= r_core:
            core += 1
            continue
        with torch.no_grad():
            cover = float(ctx.render(c).alpha.detach().double().mean())
        if not cover >= float(min_coverage):
            empty += 1
            continue
        kept.append(c)
    return kept, {"inside_core": core, "sees_almost_nothing": empty}


# ---------------------------------------------------------------------------------------------- scoring
class TargetPool(AcquisitionPolicy):
    """``policy`` scoring ``candidates`` within the pool candidates + ``targets``: the policy sees the whole pool
    (info_gain's ``targets=pool`` then counts the targets' predictive variance), the batch selector sees the
    candidates only. Every call goes to the policy's public interface (score, score_at, condition,
    conditioned_ratio, reset_conditioning)."""

    def __init__(self, policy: AcquisitionPolicy, candidates: Sequence[Camera], targets: Sequence[Camera]):
        self.policy = policy
        self.family, self.members = policy.family, policy.members
        self.pool = list(candidates) + list(targets)
        self.k = len(candidates)
        self.no_conditioning = policy.no_conditioning

    def score(self, ctx, candidates) -> Tensor:
        return self.policy.score(ctx, self.pool)[: self.k]

    def score_at(self, ctx, candidates, positions) -> Tensor:
        return self.policy.score_at(ctx, self.pool, list(positions))

    def condition(self, ctx, camera) -> bool:
        return self.policy.condition(ctx, camera)

    def conditioned_ratio(self, ctx, candidates, positions) -> Optional[Tensor]:
        return self.policy.conditioned_ratio(ctx, self.pool, list(positions))

    def reset_conditioning(self, ctx) -> None:
        self.policy.reset_conditioning(ctx)


def uses_targets(policy) -> bool:
    """Whether ``policy`` counts a target pool (info_gain's predictive objective, ``targets`` pool or pool+train)."""
    return isinstance(getattr(policy, "targets", None), str) and getattr(policy, "objective", "predictive") == "predictive"


def load_scoring(cfg: DictConfig):
    """(policy, batch selector or None for the policy's own rule, batch name) of ``cfg.policy`` / ``cfg.batch``."""
    name = str(cfg.policy)
    _, policy = load_policy(name, cfg.get("policy_settings"))
    if policy.uses_ground_truth:
        raise B3dgsError(f"policy={name} scores with the candidates' ground truth, which a pose not yet taken has not",
                         "pass policy=info_gain, cover or farthest")
    if int(policy.members) != 1:
        raise B3dgsError(f"policy={name} scores with {policy.members} models; b3dgs-suggest has the run's one",
                         "pass policy=info_gain, cover or farthest")
    bname = cfg.get("batch")
    if policy.selects_batch:
        if bname not in (None, "topk"):
            raise B3dgsError(f"policy {name} builds its batch itself, so batch={bname} does not apply to it",
                             f"pass batch=null (its own rule) or a score policy, e.g. policy=info_gain batch={bname}")
        return policy, None, "own"
    bname = str(bname or DEFAULT_BATCH)
    return policy, load_batch(bname, None), bname


def select(policy, batch, ctx, candidates: Sequence[Camera], targets: Sequence[Camera], n: int) -> Selection:
    """``n`` picks among ``candidates`` (with ``targets`` in the pool of a policy that counts them)."""
    n = min(int(n), len(candidates))
    p = TargetPool(policy, candidates, targets) if uses_targets(policy) else policy
    if batch is None:
        return policy.select(ctx, list(candidates), n)
    return batch.select(p, ctx, list(candidates), n)


# ---------------------------------------------------------------------------------------------- information map
def sh_gain_per_gaussian(policy, ctx, pool: Sequence[Camera], camera: Camera) -> tuple[Tensor, Tensor]:
    """(rows, g) of ``camera``'s score per Gaussian it sees, float64: info_gain's SH term per Gaussian
    (``InfoGainPolicy.sh_gains``, on the SH block's posterior under the policy's current conditioning; the centres'
    term of ``geometry=true`` is not split per pixel)."""
    st = policy.prepare(ctx, list(pool))
    v = st["views"].get(camera.name)
    if v is None:
        v = policy.posterior.view_information(state=st["post"], camera=camera,
                                             render=ctx.render(camera, return_weights=True), means=st["means"])
    if v.idx.numel() == 0:
        return v.idx, torch.zeros(0, dtype=torch.float64)
    return v.idx, policy.sh_gains(st, v)


def information_map(module, camera: Camera, rows: Tensor, gain: Tensor) -> tuple[Tensor, Tensor]:
    """(rgb (H, W, 3), map (H, W) float64) of ``camera`` at its size: the render, and each pixel's share of the
    score, m_p = Σ_k g_k w_kp / Σ_p' w_kp' (w_kp: Gaussian k's compositing weight at pixel p in this render; g_k:
    :func:`sh_gain_per_gaussian`). Each Gaussian's gain is spread over the pixels it shows in in proportion to its
    weight, so the map sums to the score over the Gaussians this render sees. One render for the RGB and Σ_p w_kp,
    one with g_k / Σ_p w_kp as a grey colour (alpha compositing is linear in the colours)."""
    from b3dgs.render.projection import rgb_to_sh0

    with torch.no_grad():
        ro = module.render_camera(camera, return_weights=True)
        W = ro.weight_sum.detach().reshape(-1).double()
        N = W.shape[0]
        f = torch.zeros(N, dtype=torch.float64, device=W.device)
        rows = rows.to(W.device)
        ok = W[rows] > 0
        f[rows[ok]] = gain.to(W)[ok] / W[rows[ok]]
        top = float(f.max()) if N else 0.0
        if not top > 0:
            return ro.rgb.detach().clamp(0, 1).cpu(), torch.zeros(camera.height, camera.width, dtype=torch.float64)
        p = {k: v.detach() for k, v in module.params().items()}
        p["sh0"] = rgb_to_sh0((f / top).float())[:, None, None].expand(-1, 1, 3).contiguous()
        p["shN"] = torch.zeros_like(p["shN"])
        zero = torch.zeros(3, dtype=torch.float32, device=p["sh0"].device)
        out = module.renderer.render(p, module.device_camera(camera), sh_degree=0, background=zero)
        return ro.rgb.detach().clamp(0, 1).cpu(), out.rgb[..., 0].detach().double().cpu() * top


# ---------------------------------------------------------------------------------------------- outputs
def nerfstudio_entries(cams: Sequence[Camera], T) -> dict:
    """A nerfstudio camera path of ``cams`` in the scene's own frame (the inverse of
    :func:`b3dgs.render_cli.nerfstudio_path`, with ``T`` the scene's normalisation)."""
    Rn, s, t = np.asarray(T.rotation, np.float64), float(T.scale), np.asarray(T.translation, np.float64)
    ref = cams[0]
    entries = []
    for c in cams:
        c2w = c.camtoworld.double().cpu().numpy()
        R = Rn.T @ c2w[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # into the own frame, OpenCV -> OpenGL axes
        M = np.eye(4)
        M[:3, :3], M[:3, 3] = R, Rn.T @ (c2w[:3, 3] - t) / s
        fy = float(c.K[1, 1])
        entries.append({"camera_to_world": M.reshape(-1).tolist(), "fov": math.degrees(2 * math.atan(0.5 * c.height / fy)),
                        "aspect": c.width / c.height})
    return {"camera_type": "perspective", "render_height": int(ref.height), "render_width": int(ref.width),
            "fps": 1, "seconds": len(cams), "camera_path": entries}


def _plot(path: Path, fr: dict, train: Sequence[Camera], cands: Sequence[Camera], scores: Optional[Sequence[float]],
          picks: Sequence[int], policy: str) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    def coords(cams):
        rel = np.stack([c.center.double().cpu().numpy() for c in cams]) - fr["centre"] if cams else np.zeros((0, 3))
        return rel @ fr["a"], rel @ fr["b"], rel @ fr["up"]

    fig, axes = plt.subplots(1, 2, figsize=(11, 5))
    ta, tb, tu = coords(train)
    ca, cb, cu = coords(cands)
    for ax, (x, y), (tx, ty), (xlabel, ylabel, title) in ((axes[0], (ca, cb), (ta, tb), ("a", "b", "from above")),
                                                         (axes[1], (ca, cu), (ta, tu), ("a", "up", "from the side"))):
        colour = {"c": "#999999"} if scores is None else {"c": scores, "cmap": "viridis"}
        sc = ax.scatter(x, y, s=14, zorder=2, **colour)
        ax.scatter(tx, ty, marker="^", c="black", s=24, label="training cameras", zorder=3)
        ax.scatter([x[i] for i in picks], [y[i] for i in picks], marker="*", c="#e6553a", s=160, edgecolors="black",
                   label="suggestions", zorder=4)
        for r, i in enumerate(picks):
            ax.annotate(str(r + 1), (x[i], y[i]), xytext=(5, 5), textcoords="offset points", fontsize=9, zorder=5)
        ax.scatter([0], [0], marker="+", c="red", s=60, label="scene centre", zorder=3)
        ax.set(xlabel=xlabel, ylabel=ylabel, title=title)
        ax.set_aspect("equal", adjustable="datalim")
    axes[0].legend(loc="best", fontsize=8)
    if scores is not None:
        fig.colorbar(sc, ax=axes, shrink=0.8, label=f"{policy} score")
    fig.suptitle(f"b3dgs-suggest: {len(picks)} suggestions by {policy} among {len(cands)} candidates")
    return save_figure(fig, path)


def _preview(rgb: Tensor, m: Optional[Tensor], rank: int, score: Optional[float]) -> np.ndarray:
    """The render beside its information map (inferno, 0 to its maximum; a grey panel where the run has none), a
    caption under them."""
    from b3dgs.viewer.modes import colormap_lut

    a = (rgb.numpy() * 255.0 + 0.5).astype(np.uint8)
    tail = "" if score is None else f", score {score:.3g}"
    if m is None:
        b = np.full_like(a, 64)
        text = f"#{rank}: render | no information map (suggest.json says why){tail}"
    else:
        top = float(m.max())
        idx = (np.zeros(m.shape, np.int64) if not top > 0
               else np.clip(m.numpy() / top * 255.0, 0, 255).round().astype(np.int64))
        b = colormap_lut("inferno")[idx]
        text = f"#{rank}: render | information map (max {top:.3g}{tail})"
    img = np.concatenate([a, b], axis=1)
    return np.concatenate([img, _caption(28, img.shape[1], text)], axis=0)


# ---------------------------------------------------------------------------------------------- the command
def _check_cfg(cfg: DictConfig) -> None:
    for key, lo in (("n", 1), ("generate.azimuths", 1), ("generate.elevations", 1), ("generate.distances", 1),
                    ("generate.jitter_per_camera", 0), ("targets.azimuths", 1), ("targets.elevations", 1)):
        v = OmegaConf.select(cfg, key)
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise B3dgsError(f"{key}={v!r} must be an integer >= {lo}", f"pass {key}= an integer >= {lo}")
    for key, lo, hi in (("core_quantile", 0.0, 1.0), ("min_coverage", 0.0, 1.0), ("generate.margin_deg", 0.0, 90.0),
                        ("generate.jitter_scale", 0.0, 10.0)):
        v = OmegaConf.select(cfg, key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:
            raise B3dgsError(f"{key}={v!r} must be a number in [{lo}, {hi}]", f"pass {key}= a number in [{lo}, {hi}]")
    for key in ("score_max_side", "preview_max_side"):
        v = cfg.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 8):
            raise B3dgsError(f"{key}={v!r} is too small", f"pass {key}= an integer >= 8, or null")


@contextmanager
def _claim(folder: Path, run_dir: Path, names: Sequence[str]):
    """Make room for ``names`` in ``folder``: in the run dir (under its lock) the files an earlier b3dgs-suggest
    recorded there go and ``names`` join the manifest before they are written; elsewhere (under the folder's own
    b3dgs-suggest lock) the files named as this command names its own go. Nothing else is touched."""
    if folder.resolve().is_relative_to(run_dir.resolve()) and read_manifest(run_dir) is not None:
        with claim_in_run(run_dir, folder, names, "b3dgs-suggest", OWN_FILE):
            yield
        return
    with out_dir_lock(folder, "b3dgs-suggest"):  # a second suggest into this folder is refused, not interleaved
        remove_listed(folder, [p.name for p in folder.iterdir() if p.is_file() and OWN_FILE.fullmatch(p.name)])
        yield


def suggest(cfg: DictConfig) -> dict:
    """Suggest ``cfg.n`` poses for ``cfg.run`` (module doc); returns what ``suggest.json`` holds."""
    from b3dgs.data.images import save_png
    from b3dgs.export import camera_entries
    from b3dgs.viewer.run import open_run

    t0 = time.perf_counter()
    _check_cfg(cfg)
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    policy, batch, bname = load_scoring(cfg)  # a bad policy is refused before the run is loaded
    renderer = None
    if cfg.get("renderer"):
        from b3dgs.render.renderers import make_renderer

        renderer = make_renderer(str(cfg.renderer))
        renderer.check_available()
    run = open_run(Path(str(cfg.run)), renderer=renderer, data_path=OmegaConf.select(cfg, "data.path"))
    out = Path(str(cfg.out)) if cfg.get("out") else run.path / "suggest"
    if out.exists() and not out.is_dir():
        raise B3dgsError(f"out={out} is a file", "pass out= a folder path")
    if out.resolve().is_relative_to(run.path.resolve()):
        read_manifest(run.path, fix="pass out=DIR to write the suggestions into another folder")
    scene, module = run.scene, run.module
    if hasattr(policy, "sh_gains") and module.active_sh_degree() < 1:
        raise B3dgsError(f"policy={cfg.policy}: the run renders SH degree 0, so its colour has no direction a new view "
                         "could teach", "pass policy=cover or farthest, or train with model.sh_degree >= 1 for more "
                         "than model.sh_increase_every steps")
    train = list(scene.train)
    seed = int(cfg.seed)
    if cfg.get("candidates"):
        raw = read_candidates(str(cfg.candidates), scene)
        fr = scene_frame(train, float(cfg.generate.margin_deg))
        source = str(cfg.candidates)
    else:
        raw, fr = generate_candidates(train, cfg.generate, seed)
        source = "generated"
    ahead = frontal(raw, fr)
    ctx = ScoringContext([module], train, cfg.get("score_max_side"), scene.extent, seed)
    r_core = core_radius(module, fr, float(cfg.core_quantile))
    cands, dropped = filter_candidates(ahead, ctx, fr, r_core, float(cfg.min_coverage))
    dropped = {"behind_forward_capture": len(raw) - len(ahead), **dropped}
    if not cands:
        raise B3dgsError(f"no candidate is left of {len(raw)}: {dropped['behind_forward_capture']} behind a forward-facing"
                         f" capture, {dropped['inside_core']} inside the Gaussians' dense core, "
                         f"{dropped['sees_almost_nothing']} see almost nothing",
                         "pass other candidates= poses, or lower min_coverage (and core_quantile)")
    targets = target_ring(fr, train, cfg.targets) if uses_targets(policy) else []
    n = min(int(cfg.n), len(cands))
    if n < int(cfg.n):
        log.warning("n=%d but only %d candidates are left: suggesting %d", int(cfg.n), len(cands), n)
    sel = select(policy, batch, ctx, cands, targets, n)
    picks = list(sel.indices)
    cond = (sel.info or {}).get("conditioned_scores")
    # the per-pixel information maps: info_gain's own state (conditioned on the earlier picks, as its greedy scores
    # were), or, for another policy, a fresh info_gain's where the run allows it
    map_policy, map_note = (policy if hasattr(policy, "sh_gains") else None), None
    if map_policy is None:
        try:
            _, map_policy = load_policy("info_gain")
            targets = targets or target_ring(fr, train, cfg.targets)
            map_policy.prepare(ctx, list(cands) + list(targets))
        except B3dgsError as e:
            map_policy, map_note = None, f"no information map: {e}"
            log.warning("%s", map_note)
    pool = list(cands) + list(targets)
    side = cfg.get("preview_max_side")
    previews, maps = [], []
    ranked = [None if sel.scores is None else float(cond[r] if cond else sel.scores[i]) for r, i in enumerate(picks)]
    try:
        for r, i in enumerate(picks):
            cam = cands[i].fit(side, upscale=True, min_side=8) if side else cands[i]
            if map_policy is not None:
                rows, g = sh_gain_per_gaussian(map_policy, ctx, pool, cands[i])
                rgb, m = information_map(module, cam, rows, g)
                if map_policy is policy and len(picks) > 1 and bname == DEFAULT_BATCH:
                    map_policy.condition(ctx, cands[i])
            else:
                with torch.no_grad():
                    rgb = module.render_eval(cam).cpu()
                m = None
            maps.append(None if m is None else float(m.sum()))
            previews.append(_preview(rgb, m, r + 1, ranked[r]))
    finally:
        if map_policy is not None:
            map_policy.reset_conditioning(ctx)
    T = scene_transform(scene)
    inv = T.inverse()
    chosen = [cands[i] for i in picks]
    entries = camera_entries(chosen, inv)
    suggestions = []
    for r, (i, e) in enumerate(zip(picks, entries)):
        c = cands[i]
        e.update({"id": r, "img_name": f"suggest_{r + 1:02d}"})
        suggestions.append({
            "rank": r + 1, "name": c.name, "score": ranked[r],
            "first_score": None if sel.scores is None else float(sel.scores[i]),
            "position": e["position"], "rotation": e["rotation"], "fx": e["fx"], "fy": e["fy"],
            "width": int(c.width), "height": int(c.height),
            "viewmat": c.viewmat.double().cpu().numpy().tolist(), "K": c.K.double().cpu().numpy().tolist(),
            "direction": _unit(c.center.double().cpu().numpy() - fr["centre"]).tolist(),
            "preview": f"preview_{r + 1:02d}.png", "information_map_sum": maps[r]})
    record = {
        "run": str(run.path), "policy": str(cfg.policy), "batch": bname, "requested": int(cfg.n), "returned": len(picks),
        "candidates": {"source": source, "total": len(raw), "kept": len(cands), "dropped": dropped},
        "targets": len(targets) if uses_targets(policy) else 0,
        "forward_facing": fr["forward"], "frame": "the run's normalised frame (viewmat, K, direction); position and "
        "rotation in the scene's own frame, as cameras.json",
        "centre": fr["centre"].tolist(), "up": fr["up"].tolist(), "axis": fr["axis"].tolist(), "core_radius": r_core,
        "information_map": map_note or ("info_gain's SH term per pixel: each Gaussian's share of the score spread "
                                        "over its pixels by compositing weight (sums to the score)"),
        "suggestions": suggestions,
        "scores": None if sel.scores is None else {c.name: float(s) for c, s in zip(cands, sel.scores)},
        "candidate_directions": {c.name: _unit(c.center.double().cpu().numpy() - fr["centre"]).tolist() for c in cands},
        "batch_info": sel.info, "seconds": None}
    names = ["cameras.json", "path.json", "suggest.json", "plot.png"] + [s["preview"] for s in suggestions]
    record["seconds"] = time.perf_counter() - t0
    with _claim(out, run.path, names):
        write_json(out / "cameras.json", entries)
        write_json(out / "path.json", nerfstudio_entries(chosen, T))
        for s, img in zip(suggestions, previews):
            save_png(out / s["preview"], img)
        _plot(out / "plot.png", fr, train, cands, sel.scores, picks, str(cfg.policy))
        write_json(out / "suggest.json", record)  # last: its presence says the folder is complete
    log.info("%s: %d suggestions by %s (%s) among %d candidates (%d generated or read; dropped: %s) -> %s", run.path,
             len(picks), cfg.policy, bname, len(cands), len(raw), ", ".join(f"{v} {k}" for k, v in dropped.items()), out)
    record["out"] = str(out)
    return record


@hydra.main(version_base="1.3", config_path=CONF_DIR, config_name="suggest")
def hydra_main(cfg: DictConfig) -> None:
    with known_errors("b3dgs-suggest", cfg, quiet=True):
        w = suggest(cfg)
        print(f"b3dgs-suggest: {w['returned']} suggestions by {w['policy']} -> {w['out']}/cameras.json, path.json, "
              f"plot.png, preview_*.png", flush=True)


main = cli_main("b3dgs-suggest", hydra_main, "suggest")


if __name__ == "__main__":
    main()

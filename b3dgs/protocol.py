"""What defines a stored result: the settings that change it, their digest, and one-line refusals of a mismatch.

Studies keep ``protocol.json`` (the settings and their digest) beside their rows and caches
(:func:`check_stored_protocol`); the report compares the runs it pools (:func:`run_protocol`,
:func:`differing_keys`).
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any, Mapping, Optional

from b3dgs.errors import B3dgsError
from b3dgs.io import write_json
from b3dgs.upgrade import omit_run_defaults

#: keys of a b3dgs-train config that do not change a run's results (bookkeeping, logging, where it ran)
RUN_IGNORED = ("seed", "data_root", "hydra", "resume", "overwrite", "threads", "b3dgs", "logger", "renderer", "data.path",
               "trainer.progress_bar", "trainer.log_every", "trainer.eval_every", "trainer.checkpoint_every",
               "trainer.checkpoint_every_s", "trainer.keep_checkpoints", "trainer.save_renders",
               "trainer.default_root_dir", "trainer.curve_max_views", "trainer.accelerator", "study",
               "trainer._target_", "trainer.enable_progress_bar", "trainer.log_every_n_steps", "trainer.devices",
               "trainer.enable_model_summary", "trainer.limit_val_batches", "trainer.num_sanity_val_steps",
               "callbacks", "lpips_weights")


def flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    """``{"a.b.c": leaf}`` of nested dicts (lists are leaves)."""
    if not isinstance(d, Mapping):
        return {prefix: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, Mapping) and v:
            out.update(flatten(v, key))
        else:
            out[key] = v
    return out


def _ignored(key: str, ignore) -> bool:
    return any(key == p or key.startswith(p + ".") for p in ignore)


def run_protocol(cfg: Mapping, ignore=RUN_IGNORED) -> dict[str, Any]:
    """The flattened settings of a run config that change its results (everything but ``ignore``)."""
    return omit_run_defaults({k: v for k, v in flatten(cfg).items() if not _ignored(k, ignore)})


def digest(settings: Mapping) -> str:
    """sha256 (16 hex digits) of the settings as canonical JSON."""
    return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:16]


def differing_keys(a: Mapping, b: Mapping) -> list[str]:
    """Flattened keys whose values differ (or that only one side has), sorted."""
    fa, fb = flatten(a), flatten(b)
    return sorted(k for k in set(fa) | set(fb) if fa.get(k, "<unset>") != fb.get(k, "<unset>"))


def describe_diff(a: Mapping, b: Mapping, keys: list[str], names=("there", "here"), limit: int = 4) -> str:
    """``"k: x there, y here; ..."`` for the first ``limit`` keys."""
    fa, fb = flatten(a), flatten(b)
    show = lambda v: "unset" if v == "<unset>" else json.dumps(v, default=str)  # noqa: E731
    parts = [f"{k}: {show(fa.get(k, '<unset>'))} {names[0]}, {show(fb.get(k, '<unset>'))} {names[1]}"
             for k in keys[:limit]]
    more = f" (+{len(keys) - limit} more)" if len(keys) > limit else ""
    return "; ".join(parts) + more


def _stored(path: Path, key: str, fix: str, cast=lambda v: v) -> Any:
    """``cast`` of ``key`` of the JSON object in ``path``, refused in one line when the file is damaged."""
    try:
        return cast(json.loads(path.read_text())[key])
    except (ValueError, KeyError, TypeError):
        raise B3dgsError(f"{path} is damaged", fix) from None


def check_stored_protocol(folder: Path, settings: Mapping, fix: str,
                          legacy: Optional[Mapping] = None) -> str:
    """Refuse to add to ``folder`` results made with other ``settings``; record them on first use.

    ``folder/protocol.json`` holds the settings and their digest. ``legacy``: the settings a folder written
    before protocol files is known to hold (compared on the keys it has), or None when it holds nothing yet.
    Returns the digest."""
    settings = json.loads(json.dumps(dict(settings), default=str))
    path = Path(folder) / "protocol.json"
    if path.exists():
        stored = _stored(path, "settings", f"remove it only if the rows in {folder} match this run's settings, or pass "
                         "another out_dir")
    elif legacy is not None:
        stored = {k: settings.get(k) for k in settings}
        stored.update({k: v for k, v in json.loads(json.dumps(dict(legacy), default=str)).items() if v is not None})
    else:
        stored = settings
    keys = differing_keys(stored, settings)
    if keys:
        raise B3dgsError(f"{folder} holds results of other settings ({describe_diff(stored, settings, keys)})", fix)
    if not path.exists():
        write_json(path, {"digest": digest(settings), "settings": settings})
    return digest(settings)


def scene_digest(scene: Any) -> dict[str, str]:
    """Digests of what a study's rows are made from (issue 55 §3): the decoded ``images``, the cameras' ``poses``
    (K, view matrix, size) and the ``split`` (which view is train, test or calibration), each over the views in name
    order, so that a resume can name the part that changed."""
    import numpy as np

    groups = {g: sorted(getattr(scene, g, None) or [], key=lambda c: c.name) for g in ("train", "test", "calib")}
    images, poses = hashlib.sha256(), hashlib.sha256()
    for c in sorted((c for cams in groups.values() for c in cams), key=lambda c: c.name):  # whatever the split
        for h in (images, poses):
            h.update(c.name.encode() + b"\0")
        if c.image is not None:
            images.update(np.ascontiguousarray(c.image.detach().cpu().numpy(), dtype=np.float32).tobytes())
        poses.update(np.asarray([*c.K.flatten().tolist(), *c.viewmat.flatten().tolist(), c.width, c.height],
                                dtype=np.float64).tobytes())
    split = json.dumps({g: [c.name for c in cams] for g, cams in groups.items()}, sort_keys=True)
    return {"images": images.hexdigest()[:16], "poses": poses.hexdigest()[:16],
            "split": hashlib.sha256(split.encode()).hexdigest()[:16]}


def check_stored_scene(folder: Path, scene: Any, fix: str) -> dict[str, str]:
    """Refuse to add to ``folder`` rows made from other data: ``folder/scene.json`` holds :func:`scene_digest` of the
    scene its rows were made from (recorded on first use; a folder from before it gets the current one). ``scene``: a
    scene or its :func:`scene_digest`. Returns the digests."""
    current = dict(scene) if isinstance(scene, Mapping) else scene_digest(scene)
    path = Path(folder) / "scene.json"
    if path.exists():
        stored = _stored(path, "digest", f"remove it only if the rows in {folder} were made from this scene's data, "
                         "or pass another out_dir", dict)
        changed = [k for k in current if stored.get(k) != current[k]]
        if changed:
            raise B3dgsError(f"{folder} holds rows made from other data: the scene's {', '.join(changed)} changed "
                             "since they were made", fix)
    else:
        write_json(path, {"digest": current})
    return current

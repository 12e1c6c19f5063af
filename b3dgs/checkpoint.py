"""What a checkpoint says about its run, so that a resume or an evaluation can refuse a mismatch.

``checkpoint["b3dgs"]["identity"]`` (:func:`run_identity`): the model name and hyper-parameters, the posterior blocks,
the strategy, the schedule, a scene fingerprint and the renderer (which only a resume must keep); a resume and
``b3dgs-eval`` refuse any difference in one line (:func:`identity_mismatch`, :func:`renderer_mismatch`).
``metrics.json`` records the final checkpoint's step, Gaussian count and parameter digest (:func:`params_digest`).
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import zipfile
from pathlib import Path
from typing import Any, Mapping, Optional, Sequence

import torch

from b3dgs.errors import B3dgsError
from b3dgs.upgrade import CONSTANT_SCHEDULE, schedule_node, upgrade_targets

__all__ = ["check_checkpoint", "check_sealed", "checkpoint_record", "content_digest", "seal_checkpoint", "identity_mismatch", "params_digest", "plugin_config", "renderer_identity",
           "renderer_mismatch", "run_identity", "scene_fingerprint"]

PARAM_ORDER = ("means", "scales", "quats", "opacities", "sh0", "shN")


def _plain(v: Any) -> Any:
    """JSON-comparable form of a plugin / hyper-parameter value."""
    if v is None or isinstance(v, (bool, int, str)):
        return v
    if isinstance(v, float):
        return v if math.isfinite(v) else repr(v)
    if isinstance(v, Mapping):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, torch.Tensor):
        return _plain(v.detach().cpu().tolist())
    try:  # OmegaConf containers
        from omegaconf import DictConfig, ListConfig, OmegaConf

        if isinstance(v, (DictConfig, ListConfig)):
            return _plain(OmegaConf.to_container(v, resolve=True))
    except ImportError:  # pragma: no cover
        pass
    return repr(v)


def plugin_config(plugin: Any) -> dict:
    """``{"_target_": class path, field: value, ...}`` of a (dataclass) plugin."""
    cls = type(plugin)
    out: dict[str, Any] = {"_target_": f"{cls.__module__}.{cls.__qualname__}"}
    if dataclasses.is_dataclass(plugin):
        for f in dataclasses.fields(plugin):
            out[f.name] = _plain(getattr(plugin, f.name))
    return out


def _round(x: float) -> float:
    return float(f"{float(x):.6g}")


def scene_fingerprint(scene: Any) -> Optional[str]:
    """sha256 of the scene name, the train / test camera names, image sizes and intrinsics (6 significant
    digits) and the number of train views; ``None`` without a scene."""
    if scene is None:
        return None

    def cams(cs):
        return [[c.name, int(c.width), int(c.height), [_round(v) for v in c.K.reshape(-1)[[0, 4, 2, 5]].tolist()]]
                for c in cs]

    rec = {"name": str(scene.name), "num_train": len(scene.train), "train": cams(scene.train), "test": cams(scene.test)}
    return hashlib.sha256(json.dumps(rec, sort_keys=True).encode()).hexdigest()[:16]


def run_identity(hparams: Mapping[str, Any], strategy: Any, posterior: Mapping[str, Any], scene: Any,
                 schedule: Any = None, renderer: Any = None) -> dict:
    """What must agree between a checkpoint and the run that resumes or evaluates it. The renderer is recorded
    for resumes only (:func:`renderer_mismatch`): an evaluation may score a run with another renderer."""
    hp = _plain(dict(hparams))
    return {"model": hp.get("name"), "posterior": {str(k): plugin_config(b) for k, b in posterior.items()},
            "scene": scene_fingerprint(scene), "strategy": plugin_config(strategy), "hparams": hp,
            "schedule": CONSTANT_SCHEDULE if schedule is None else plugin_config(schedule),
            "renderer": renderer_identity(renderer)}


def renderer_identity(renderer: Any) -> Optional[dict]:
    """The renderer's backend (class), its settings and the type of device it runs on; ``None`` without one."""
    if renderer is None:
        return None
    return {**plugin_config(renderer), "name": str(getattr(renderer, "name", "")), "device": renderer.device.type}


#: renderer settings that do not change results (which GPU of one type)
_RENDERER_IGNORED = ("device_name", "name")


def _renderer_option(target: Any) -> str:
    """The ``renderer=`` option of a renderer class path (``auto`` for the auto_renderer factory)."""
    cls = str(target).rsplit(".", 1)[-1]
    return {"auto_renderer": "auto", "CPURenderer": "cpu", "TorchRenderer": "torch",
            "GsplatRenderer": "gsplat"}.get(cls, cls)


def renderer_mismatch(saved: Optional[Mapping], current: Optional[Mapping],
                      resolved: bool = True) -> Optional[tuple[str, str]]:
    """``(problem, key=value to pass)`` when ``current`` renders differently from the ``saved`` renderer, else
    ``None`` (also when either is unknown). ``resolved``: both are :func:`renderer_identity` records; else both
    are config nodes (``renderer=auto`` unresolved), compared as they are."""
    if not isinstance(saved, Mapping) or not isinstance(current, Mapping) or "_target_" not in saved \
            or "_target_" not in current:
        return None
    saved = upgrade_targets(dict(saved))
    a, b = _renderer_option(saved["_target_"]), _renderer_option(current["_target_"])
    if a != b:
        return f"it was trained with renderer={a}, this run uses renderer={b}", f"renderer={a}"
    if resolved and saved.get("device") != current.get("device"):
        return (f"its renderer ran on {saved.get('device')}, this run's on {current.get('device')}",
                f"renderer.device_name={saved.get('device')}")
    skip = ("_target_", "device", *(_RENDERER_IGNORED if resolved else ()))
    kept = [{k: v for k, v in d.items() if k not in skip} for d in (saved, current)]
    return _field_diff(lambda k: f"renderer.{k}", *kept)


def _hp_path(key: str) -> str:
    return {"max_steps": "trainer.max_steps", "seed": "seed", "name": "model.name"}.get(key, f"model.{key}")


def _field_diff(path, a: Mapping, b: Mapping) -> Optional[tuple[str, str]]:
    """``(problem, key=value to pass)`` for the first key both hold with different values, named ``path(key)`` (a key
    only one side has is a field added or removed by a code change since the checkpoint was written, not a setting)."""
    k = next((k for k in sorted(set(a) & set(b)) if a[k] != b[k]), None)
    if k is None:
        return None
    return f"its {path(k)} is {_show(a[k])}, this run's {_show(b[k])}", f"{path(k)}={_show(a[k])}"


def _show(v: Any) -> str:
    return "null" if v is None else (json.dumps(v) if isinstance(v, (list, dict)) else str(v))


def identity_mismatch(saved: Optional[Mapping], current: Mapping) -> Optional[tuple[str, str]]:
    """``(problem, key=value to pass)`` for the first way ``current`` differs from a checkpoint's
    ``saved`` identity, or ``None`` when they agree (or the checkpoint predates identities)."""
    if not saved:
        return None
    saved = upgrade_targets(saved)
    if saved.get("model") != current.get("model"):
        return (f"it holds a model={saved.get('model')} run, this run is model={current.get('model')}",
                f"model={saved.get('model')}")
    sp, cp = saved.get("posterior") or {}, current.get("posterior") or {}
    if list(sp) != list(cp):
        want = f"posterior=[{','.join(sp)}]"
        return f"its posterior blocks are [{', '.join(sp)}], this run's [{', '.join(cp)}]", want
    if saved.get("scene") and current.get("scene") and saved["scene"] != current["scene"]:
        return ("it was trained on another scene (scene fingerprint: names, image sizes, intrinsics and number "
                "of train views differ)", "the checkpoint's data.* settings")
    sh, ch = saved.get("hparams") or {}, current.get("hparams") or {}
    for key in ("max_steps", "seed"):
        if sh.get(key) != ch.get(key):
            return (f"it was trained with {_hp_path(key)}={_show(sh.get(key))}, this run has {_hp_path(key)}="
                    f"{_show(ch.get(key))}", f"{_hp_path(key)}={_show(sh.get(key))}")
    sc, cc = schedule_node(saved.get("schedule") or None), schedule_node(current.get("schedule") or None)
    if sc.get("_target_") != cc.get("_target_"):
        name = str(sc.get("_target_", "")).rsplit(".", 1)[-1].replace("Schedule", "").lower() or "constant"
        return (f"it was trained with the {sc.get('_target_')} schedule, this run uses {cc.get('_target_')}",
                f"schedule={name}")
    fields = [(lambda k: f"schedule.{k}", sc, cc),
              (lambda k: "strategy" if k == "_target_" else f"strategy.{k}", saved.get("strategy") or {},
               current.get("strategy") or {}),
              *((lambda k, n=name: f"posterior.{n}.{k}", sp[name], cp[name]) for name in sp), (_hp_path, sh, ch)]
    return next((bad for bad in (_field_diff(*f) for f in fields) if bad is not None), None)


def params_digest(tensors: Mapping[str, torch.Tensor], prefix: str = "") -> str:
    """sha256 (16 hex digits) of the Gaussian parameters' dtypes, shapes and bytes."""
    h = hashlib.sha256()
    for k in PARAM_ORDER:
        _feed(h, k, tensors[prefix + k])
    return h.hexdigest()[:16]


#: the parts of a checkpoint whose content :func:`content_digest` covers (those present when it was written)
DIGEST_PARTS = ("state_dict", "optimizer_states")


def _feed(h, key: str, v: Any) -> None:
    if isinstance(v, torch.Tensor):
        t = v.detach().to("cpu").contiguous().reshape(-1)  # 0-d tensors (step counters) too
        h.update(f"{key}:{t.dtype}:{tuple(v.shape)};".encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    elif isinstance(v, Mapping):
        for k in sorted(v, key=str):
            _feed(h, f"{key}.{k}", v[k])
    elif isinstance(v, (list, tuple)):
        for i, x in enumerate(v):
            _feed(h, f"{key}[{i}]", x)
    else:
        h.update(f"{key}={v!r};".encode())


def content_digest(checkpoint: Mapping[str, Any], parts: Sequence[str]) -> str:
    """sha256 (16 hex digits) of ``parts`` of a checkpoint (every tensor's dtype, shape and bytes, every other
    value's repr, in key order) and of the plugin states in ``checkpoint["b3dgs"]["states"]``: what a resume or an
    evaluation reads back, so that bytes changed on disk since the checkpoint was written are caught on load."""
    h = hashlib.sha256()
    for part in parts:
        _feed(h, part, checkpoint.get(part))
    _feed(h, "states", (checkpoint.get("b3dgs") or {}).get("states"))
    return h.hexdigest()[:16]


def seal_checkpoint(checkpoint: dict) -> None:
    """Record :func:`content_digest` in ``checkpoint["b3dgs"]`` (when it is written)."""
    parts = [p for p in DIGEST_PARTS if p in checkpoint]
    checkpoint.setdefault("b3dgs", {})["content"] = {"parts": parts, "sha256": content_digest(checkpoint, parts)}


def check_sealed(checkpoint: Mapping[str, Any], what: str, fix: str) -> None:
    """Refuse a checkpoint whose content differs from the digest recorded when it was written (its bytes changed
    on disk since); a checkpoint written before digests were recorded passes."""
    rec = (checkpoint.get("b3dgs") or {}).get("content")
    if not rec:
        return
    parts = [p for p in rec.get("parts", []) if p in checkpoint]
    if parts != list(rec.get("parts", [])) or content_digest(checkpoint, parts) != rec.get("sha256"):
        raise B3dgsError(f"{what} changed since it was written: its content no longer matches the digest recorded "
                         "in it (damaged or edited on disk)", fix)


def checkpoint_record(checkpoint: Mapping[str, Any]) -> dict:
    """What ``metrics.json`` says about its run's final checkpoint (``"checkpoint"``)."""
    sd = checkpoint["state_dict"]
    return {"global_step": int(checkpoint.get("global_step", 0)), "num_gaussians": int(sd["splats.means"].shape[0]),
            "params_sha256": params_digest(sd, prefix="splats.")}


def check_checkpoint(path: str | Path, fix: str) -> None:
    """Refuse a checkpoint file that is missing or not a readable torch archive (e.g. truncated)."""
    p = Path(path)
    if not p.is_file():
        raise B3dgsError(f"checkpoint {p} does not exist", fix)
    try:
        with zipfile.ZipFile(p) as z:
            if not any(n.endswith("data.pkl") for n in z.namelist()):
                raise zipfile.BadZipFile("no data.pkl")
    except (zipfile.BadZipFile, OSError) as e:
        raise B3dgsError(f"checkpoint {p} is damaged or not a checkpoint ({e})", fix) from None

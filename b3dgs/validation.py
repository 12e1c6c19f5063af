"""Config validation that runs before any scene is loaded.

:func:`validate_config` checks the composed config of ``b3dgs-train`` or ``b3dgs-eval`` and raises
:class:`~b3dgs.errors.B3dgsError` ``(problem, fix)`` for the first bad value. It is generic where it
can be, so that new options and plugins are checked without editing this module:

* **Keys.** A node with a ``_target_`` may hold only the arguments its target accepts (for the data
  module: its own and those of the selected format loader); a group without a ``_target_`` (trainer)
  only the keys that some option file of its group defines. Unknown keys are usually typos added with
  ``+`` (``+trainer.max_stpes=50``) and are refused, with the closest known key.
* **Types.** Each value must have the type of the target's default / the option file's value.
* **Ranges.** Explicit rules for the core values (data, model, trainer, top-level keys, ``uq.samples``);
  the strategy, posterior blocks and uq regimes are built and their own ``check_sanity`` / ``check`` run.
* **Duplicates.** A posterior block listed twice (``posterior=[niw,niw]``) is refused.
* **Files.** ``data.path``, a ``resume`` checkpoint and ``b3dgs-eval``'s run dirs must exist, and a
  checkpoint must be a readable archive.
"""
from __future__ import annotations

import inspect
import math
import zipfile
from functools import lru_cache
from pathlib import Path
from typing import Any, Callable, Iterable, Optional

from omegaconf import DictConfig, ListConfig, OmegaConf

from b3dgs import conf_dir
from b3dgs.errors import B3dgsError, did_you_mean

CONF_DIR = Path(conf_dir())
TRAIN_GROUPS = ("data", "model", "renderer", "strategy", "posterior", "schedule", "trainer", "logger")
EVAL_GROUPS = ("uq",)
_MISSING = object()

__all__ = ["check_checkpoint", "group_option_names", "validate_config"]


# ---------------------------------------------------------------------------------------------- helpers


def _get(node: DictConfig, key: str, path: str) -> Any:
    """A value of ``node``, resolved; ``_MISSING`` for an interpolation that needs a running Hydra app."""
    from omegaconf.errors import MissingMandatoryValue

    if OmegaConf.is_missing(node, key):
        raise B3dgsError(f"{path} is not set", f"pass {path}=VALUE on the command line")
    try:
        v = node[key]
    except MissingMandatoryValue as e:
        raise B3dgsError(f"{path} needs {getattr(e, 'full_key', None) or 'a value'}, which is not set",
                         f"pass {getattr(e, 'full_key', None) or 'it'}=VALUE on the command line") from None
    except Exception as e:  # noqa: BLE001 - unresolvable interpolations (${hydra:...} outside an app)
        if "hydra" in str(e).lower() or "HydraConfig" in str(e):
            return _MISSING
        raise B3dgsError(f"{path} cannot be resolved ({' '.join(str(e).split())[:160]})",
                         f"correct the interpolation in {path}") from None
    if isinstance(v, (DictConfig, ListConfig)):
        return OmegaConf.to_container(v, resolve=True)
    return v


def _is_int(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v: Any) -> bool:
    return (isinstance(v, (int, float)) and not isinstance(v, bool)) and math.isfinite(v)


def _need(ok: bool, path: str, value: Any, what: str, fix: str) -> None:
    if not ok:
        raise B3dgsError(f"{path}={_show(value)} is invalid: it must be {what}", fix)


def _show(v: Any) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_show(x) for x in v) + "]"
    return "null" if v is None else str(v)


def _int_at_least(path: str, v: Any, lo: int, fix: str, allow_none: bool = False) -> None:
    if v is None and allow_none:
        return
    _need(_is_int(v) and v >= lo, path, v, f"an integer >= {lo}" + (" or null" if allow_none else ""), fix)


def _rgb(path: str, v: Any) -> None:
    _need(isinstance(v, (list, tuple)) and len(v) == 3 and all(_is_num(x) and 0.0 <= x <= 1.0 for x in v),
          path, v, "3 numbers in [0, 1] (RGB)", f"pass {path}=[0,0,0] (black) or {path}=[1,1,1] (white)")


def _locate(target: str) -> Callable:
    from hydra.utils import get_object

    try:
        return get_object(target)
    except Exception as e:  # noqa: BLE001
        raise B3dgsError(f"_target_ {target} cannot be imported ({type(e).__name__})",
                         "install the package that provides it, or correct _target_") from None


def _signature(fn: Callable) -> tuple[dict[str, Any], bool]:
    """(parameter name -> default (or inspect.Parameter.empty), accepts **kwargs)."""
    params = inspect.signature(fn).parameters
    names = {n: p.default for n, p in params.items()
             if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
    return names, any(p.kind == p.VAR_KEYWORD for p in params.values())


def _typed_by_annotation(fn: Callable) -> dict[str, Any]:
    """Parameter -> a value of its type for parameters annotated ``bool`` or ``int`` (optionally ``None``),
    ``inspect.Parameter.empty`` (no type check) for the others: types for :func:`_check_type` where the
    default (``None``) says nothing, as in ``lightning.Trainer``'s signature."""
    import typing

    out: dict[str, Any] = {}
    for name, p in inspect.signature(fn).parameters.items():
        a = p.annotation
        kinds = set(typing.get_args(a)) - {type(None)} if typing.get_origin(a) is typing.Union else {a}
        out[name] = {frozenset({bool}): False, frozenset({int}): 0}.get(frozenset(kinds), inspect.Parameter.empty)
    return out


def _check_type(path: str, v: Any, default: Any, example: bool = True) -> None:
    """``v`` must have the type of ``default`` (bool, int, float, str, list); None is always allowed
    where the default is None, and ints where floats are expected. ``example``: whether ``default`` is a real
    default to show in the fix (not a value standing for an annotated type)."""
    if default is inspect.Parameter.empty or default is None or v is None or v is _MISSING:
        return
    fix = f"pass {path}=<{type(default).__name__}>" + (f", like its default {_show(default)}" if example else "")
    if isinstance(default, bool):
        _need(isinstance(v, bool), path, v, "true or false", fix)
    elif isinstance(default, int):
        _need(_is_int(v), path, v, "an integer", fix)
    elif isinstance(default, float):
        _need(_is_num(v), path, v, "a finite number", fix)
    elif isinstance(default, str):
        _need(isinstance(v, str), path, v, "a string", fix)
    elif isinstance(default, (list, tuple)):
        _need(isinstance(v, (list, tuple)), path, v, "a list", fix)


def _unknown(path: str, key: str, known: Iterable[str]) -> B3dgsError:
    return B3dgsError(f"unknown config key {path}.{key}{did_you_mean(key, known)}",
                      f"remove it or correct its spelling (keys of {path}: {', '.join(sorted(known))})")


def _check_target_node(node: DictConfig, path: str, extra: Optional[dict[str, Any]] = None,
                       type_only: Iterable[str] = ()) -> dict[str, Any]:
    """Keys and types of a ``_target_`` node against its target's signature; returns the values. ``type_only``:
    keys whose value in ``extra`` stands for a type, not a default."""
    target = _locate(str(node["_target_"]))
    params, var_kw = _signature(target)
    if extra is not None:  # what the target forwards through **kwargs
        params, var_kw = {**params, **extra}, False
    values = {}
    for key in node.keys():
        key = str(key)
        if key.startswith("_"):
            continue
        if key not in params and not var_kw:
            raise _unknown(path, key, [k for k in params if not k.startswith("_")])
        values[key] = v = _get(node, key, f"{path}.{key}")
        _check_type(f"{path}.{key}", v, params.get(key, inspect.Parameter.empty), example=key not in type_only)
    return values


@lru_cache(maxsize=None)
def _group_options(group: str) -> tuple[tuple[str, dict], ...]:
    """(option name, its keys -> values) for every option file of ``group`` (b3dgs's conf dir and the
    ``b3dgs.conf`` entry points of installed packages)."""
    roots = [CONF_DIR]
    try:
        from importlib import resources
        from importlib.metadata import entry_points

        for ep in entry_points(group="b3dgs.conf"):
            roots.append(Path(str(resources.files(ep.value))))
    except Exception:  # noqa: BLE001 - a broken extension package must not hide b3dgs's own options
        pass
    out = []
    for root in roots:
        for f in sorted((root / group).glob("*.yaml")):
            text = f.read_text()
            data = OmegaConf.to_container(OmegaConf.create(text), resolve=False) or {}
            if any(ln.startswith("#") and "@package _global_" in ln for ln in text.splitlines()[:5]):
                data = data.get(group, {}) or {}
            data.pop("defaults", None)
            out.append((f.stem, data))
    return tuple(out)


def group_option_names(group: str) -> list[str]:
    """The option names of config ``group`` (b3dgs's and installed packages'), e.g. the ``model=`` options."""
    return sorted({name for name, _ in _group_options(group)})


def _check_plain_group(node: DictConfig, group: str) -> dict[str, Any]:
    """Keys and types of a group without ``_target_`` against the keys its option files define."""
    known: dict[str, Any] = {}
    for _, data in _group_options(group):
        for k, v in data.items():
            known.setdefault(str(k), v)
    values = {}
    for key in node.keys():
        key = str(key)
        if key not in known:
            raise _unknown(group, key, known)
        values[key] = v = _get(node, key, f"{group}.{key}")
        d = known[key]
        if not (isinstance(d, str) and "${" in d):
            _check_type(f"{group}.{key}", v, d)
    return values


def _check_group(cfg: DictConfig, group: str) -> dict[str, Any]:
    node = cfg.get(group)
    if not isinstance(node, DictConfig):
        return {}
    if "_target_" in node:
        return _check_target_node(node, group)
    return _check_plain_group(node, group)


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


# ---------------------------------------------------------------------------------------------- groups


def _check_top(cfg: DictConfig, app: str) -> None:
    own = OmegaConf.to_container(OmegaConf.load(CONF_DIR / f"{app}.yaml"), resolve=False)
    known = set(own) | set(TRAIN_GROUPS if app == "train" else EVAL_GROUPS) | {"hydra", "b3dgs"}
    known.discard("defaults")
    for key in cfg.keys():
        if str(key) not in known:
            raise B3dgsError(f"unknown config key {key}{did_you_mean(str(key), known)}",
                             f"remove it or correct its spelling (top-level keys: {', '.join(sorted(known))})")
    b = cfg.get("b3dgs")
    if isinstance(b, DictConfig):
        for key in b.keys():
            if key != "debug":
                raise B3dgsError(f"unknown config key b3dgs.{key}", "the b3dgs node holds only b3dgs.debug")
        _need(isinstance(_get(b, "debug", "b3dgs.debug"), bool), "b3dgs.debug", b.debug, "true or false",
              "pass b3dgs.debug=true for full tracebacks")
    lw = _get(cfg, "lpips_weights", "lpips_weights") if "lpips_weights" in cfg else None
    if lw not in (None, "") and not Path(str(lw)).expanduser().is_file():
        raise B3dgsError(f"lpips_weights={lw}: no such file",
                         f"run `b3dgs-lpips --out {lw}` to build it, or pass lpips_weights=null (then "
                         "$B3DGS_LPIPS_WEIGHTS or the cache ~/.cache/b3dgs/lpips_alex.pth is used)")
    seed = _get(cfg, "seed", "seed")
    _need(_is_int(seed) and 0 <= seed < 2**32, "seed", seed, "an integer in [0, 2^32)", "pass seed=0")
    _int_at_least("threads", _get(cfg, "threads", "threads") if "threads" in cfg else None, 1,
                  "pass threads=2 or threads=null (torch's default)", allow_none=True)


def _check_data(cfg: DictConfig) -> None:
    from b3dgs.data.scene import get_loader, loader_reads_files

    node = cfg.data
    kind = _get(node, "kind", "data.kind")
    loader = get_loader(str(kind))  # b3dgs's formats or package.module:function; one line if neither
    reads_files = loader_reads_files(loader)
    if reads_files and OmegaConf.is_missing(node, "path"):
        raise B3dgsError(f"data={kind} needs a scene folder: data.path is not set", "pass data.path=PATH")
    lparams, _ = _signature(loader)
    lparams = {k: d for k, d in lparams.items() if k != "path"}
    v = _check_target_node(node, "data", extra=lparams)
    path = v.get("path")
    if reads_files:
        if path in (None, ""):
            raise B3dgsError(f"data={kind} needs a scene folder", "pass data.path=PATH")
        if not Path(str(path)).exists():
            raise B3dgsError(f"data.path={path} does not exist", "pass data.path=PATH to an existing scene folder")
    _int_at_least("data.max_side", v.get("max_side"), 1,
                  "pass data.max_side=256 (longest image side in pixels) or null for full resolution", allow_none=True)
    _int_at_least("data.test_every", v.get("test_every", 8), 0,
                  "pass data.test_every=8 (every 8th view held out) or 0 for no test views")
    _int_at_least("data.max_images", v.get("max_images"), 1, "pass data.max_images=N or null for all views",
                  allow_none=True)
    ti = v.get("train_indices")
    _need(ti is None or (isinstance(ti, list) and all(_is_int(i) and i >= 0 for i in ti) and len(set(ti)) == len(ti)),
          "data.train_indices", ti, "null or a list of distinct indices >= 0", "pass data.train_indices=[0,3,5] or null")
    _rgb("data.background", v.get("background", [0.0, 0.0, 0.0]))
    if "near_plane" in v:
        _need(_is_num(v["near_plane"]) and v["near_plane"] > 0, "data.near_plane", v["near_plane"],
              "a positive number (the renderer's near plane)", "pass data.near_plane=0.01")
    for key in ("n_views", "resolution", "supersample", "n_objects"):
        if key in v:
            _int_at_least(f"data.{key}", v[key], 1, f"pass a positive data.{key}")


def _check_model(cfg: DictConfig) -> None:
    v = _check_target_node(cfg.model, "model")
    fix = "see conf/model/standard.yaml for the defaults"
    if "sh_degree" in v:
        _need(_is_int(v["sh_degree"]) and 0 <= v["sh_degree"] <= 3, "model.sh_degree", v["sh_degree"], "0, 1, 2 or 3", fix)
    if "sh_increase_every" in v:
        _int_at_least("model.sh_increase_every", v["sh_increase_every"], 1, fix)
    if "lambda_dssim" in v:
        _need(_is_num(v["lambda_dssim"]) and 0 <= v["lambda_dssim"] <= 1, "model.lambda_dssim", v["lambda_dssim"],
              "in [0, 1]", "pass model.lambda_dssim=0.2")
    for key, val in v.items():
        if key.startswith("lr_"):
            _need(_is_num(val) and val >= 0, f"model.{key}", val, "a finite number >= 0", fix)
    if "background" in v:
        _rgb("model.background", v["background"])
        data_bg = cfg.data.get("background") if isinstance(cfg.get("data"), DictConfig) else None
        if data_bg is not None and [float(x) for x in data_bg] != [float(x) for x in v["background"]]:
            raise B3dgsError(f"model.background={_show(v['background'])} differs from data.background="
                             f"{_show(list(data_bg))}: the model renders over the first, the images are composited on "
                             "the second", "drop the model.background override (it follows data.background)")
    if "init_opacity" in v:
        _need(_is_num(v["init_opacity"]) and 0 < v["init_opacity"] < 1, "model.init_opacity", v["init_opacity"],
              "strictly between 0 and 1 (its logit must be finite)", "pass model.init_opacity=0.1")
    if "init_scale" in v:
        _need(_is_num(v["init_scale"]) and 0 < v["init_scale"] < float("inf"), "model.init_scale", v["init_scale"],
              "a positive number (it multiplies the initial Gaussian sizes; their log must be finite)",
              "pass model.init_scale=1.0")
    _int_at_least("model.init_max_points", v.get("init_max_points"), 1, fix, allow_none=True)
    if "init_num_random" in v:
        _int_at_least("model.init_num_random", v["init_num_random"], 0, fix)


def _trainer_choice(cfg: DictConfig) -> str:
    """The ``trainer=`` option this config was composed with (``default`` where Hydra does not say)."""
    if "hydra" in cfg and OmegaConf.select(cfg, "hydra.runtime.choices.trainer", default=None):
        return str(OmegaConf.select(cfg, "hydra.runtime.choices.trainer"))
    try:
        from hydra.core.hydra_config import HydraConfig

        if HydraConfig.initialized():
            return str(HydraConfig.get().runtime.choices.get("trainer") or "default")
    except Exception:  # noqa: BLE001
        pass
    return "default"


def _check_trainer(cfg: DictConfig) -> None:
    """Keys of the trainer's ``_target_`` (lightning.Trainer, which checks its own values when built) and
    b3dgs's own run settings (the keys of the trainer option files that are no Trainer argument:
    :data:`b3dgs.train.RUN_KEYS`, typed by their values there)."""
    node = cfg.trainer
    if "_target_" in node:
        typed = _typed_by_annotation(_locate(str(node["_target_"])))
        options = dict(_group_options("trainer"))
        files = {k: d for data in [*options.values(), options.get(_trainer_choice(cfg), {})] for k, d in data.items()
                 if not k.startswith("_")}  # the chosen option file's values win
        # an annotated type shows the option files' value as its default where they set one of that type
        shown = {k for k, t in typed.items() if k in files and type(files[k]) is type(t)}
        lightning_args = {k: files[k] if k in shown else t for k, t in typed.items()}
        own = {k: d for k, d in files.items() if k not in lightning_args}
        v = _check_target_node(node, "trainer", extra={**lightning_args, **own}, type_only=set(typed) - shown)
    else:
        v = _check_plain_group(node, "trainer")
    fix = "see conf/trainer/default.yaml for the defaults"
    for key in ("max_steps", "eval_every", "checkpoint_every", "log_every_n_steps"):
        if key in v:
            _int_at_least(f"trainer.{key}", v[key], 1, fix)
    _int_at_least("trainer.curve_max_views", v.get("curve_max_views"), 1, fix, allow_none=True)


def _check_plugins(cfg: DictConfig) -> None:
    """Strategy and posterior blocks: keys and types, then their own check_sanity."""
    from hydra.utils import instantiate

    max_steps = int(cfg.trainer.max_steps)
    nodes = [(g, cfg[g]) for g in ("strategy", "schedule") if isinstance(cfg.get(g), DictConfig)]
    post = cfg.get("posterior") or {}
    blocks = [name for name, _ in _group_options("posterior")]
    for name in post.keys():
        node = post[name]
        if not isinstance(node, DictConfig) or "_target_" not in node:
            raise B3dgsError(f"posterior.{name} is not a posterior block{did_you_mean(str(name), blocks)}",
                             f"pick blocks with posterior=[{','.join(blocks)}]")
        nodes.append((f"posterior.{name}", node))
    for name in (cfg.get("callbacks") or {}).keys():
        node = cfg.callbacks[name]
        if not isinstance(node, DictConfig) or "_target_" not in node:
            raise B3dgsError(f"callbacks.{name} has no _target_", f"pass +callbacks.{name}._target_=CLASS_PATH "
                             "(a lightning Callback), or drop it")
        _check_target_node(node, f"callbacks.{name}")
    for path, node in nodes:
        v = _check_target_node(node, path)
        if path == "strategy" and "percent_dense" in v:
            _need(_is_num(v["percent_dense"]) and 0 < v["percent_dense"] <= 1, "strategy.percent_dense",
                  v["percent_dense"], "a fraction of the scene extent in (0, 1]", "pass strategy.percent_dense=0.01")
        try:
            obj = instantiate(node)
            obj.check_sanity(max_steps=max_steps)
        except B3dgsError:
            raise
        except (ValueError, TypeError) as e:
            msg = " ".join(str(e).split())
            group = path.split(".")[0]
            raise B3dgsError(msg if msg.startswith(path) else f"{path}: {msg}",
                             f"correct that value (the defaults are in conf/{group}/)") from None


def _check_renderer(cfg: DictConfig) -> None:
    """Keys and types; values of enumerated string keys (e.g. ``backend``) must be one an option offers."""
    v = _check_group(cfg, "renderer")
    if "near" in v:
        _need(_is_num(v["near"]) and v["near"] > 0, "renderer.near", v["near"], "a positive number",
              "pass renderer.near=0.01, and data.normalize=true so that the scene's extent is 1")
    if "_target_" in cfg.renderer:
        return
    for key, val in v.items():
        offered = {str(d[key]) for _, d in _group_options("renderer") if isinstance(d.get(key), str)}
        if offered and val not in offered:
            raise B3dgsError(f"renderer.{key}={val} is not offered{did_you_mean(str(val), offered)}",
                             f"pick renderer={'|'.join(n for n, _ in _group_options('renderer'))}")


def _check_posterior_list(cfg: DictConfig) -> None:
    """``posterior=[niw,niw]`` composes to one block: refuse the duplicate (seen in Hydra's overrides)."""
    overrides = []
    if "hydra" in cfg and isinstance(cfg.hydra, DictConfig):
        overrides = list(OmegaConf.select(cfg, "hydra.overrides.task", default=[]) or [])
    else:
        try:
            from hydra.core.hydra_config import HydraConfig

            if HydraConfig.initialized():
                overrides = list(HydraConfig.get().overrides.task)
        except Exception:  # noqa: BLE001
            overrides = []
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides([str(o) for o in overrides])
    except Exception:  # noqa: BLE001 - Hydra parsed them already to compose this config
        return
    for o in parsed:
        items = o.value() if o.key_or_group == "posterior" and o.value_type is not None else None
        if isinstance(items, list):
            items = [str(x) for x in items]
            dup = sorted({x for x in items if items.count(x) > 1})
            if dup:
                raise B3dgsError(f"posterior=[{','.join(items)}] lists {', '.join(dup)} more than once",
                                 f"list each block once, e.g. posterior=[{','.join(dict.fromkeys(items))}]")


def _check_resume(cfg: DictConfig) -> None:
    resume = _get(cfg, "resume", "resume") if "resume" in cfg else None
    fix = "pass resume=null to start afresh, or resume=PATH to an intact .ckpt (e.g. an earlier stepN.ckpt)"
    if resume in (None, False, "", "null"):
        return
    if resume in ("auto", True):
        root = _get(cfg.trainer, "default_root_dir", "trainer.default_root_dir")
        last = None if root is _MISSING else Path(str(root)) / "checkpoints" / "last.ckpt"
        if last is not None and last.exists():
            check_checkpoint(last, fix)
        return
    p = Path(str(resume))
    if not p.exists():
        raise B3dgsError(f"resume={resume}: no such checkpoint", "pass a .ckpt path, resume=auto or resume=null")
    check_checkpoint(p, fix)


def _check_eval(cfg: DictConfig) -> None:
    from hydra.utils import instantiate

    runs = _get(cfg, "run", "run")
    runs = runs if isinstance(runs, list) else [runs]
    if not runs:
        raise B3dgsError("run=[] names no run dir", "pass run=RUN_DIR or run=[A,B,C]")
    _int_at_least("max_views", _get(cfg, "max_views", "max_views") if "max_views" in cfg else None, 1,
                  "pass max_views=N or null for all test views", allow_none=True)
    _int_at_least("panels", _get(cfg, "panels", "panels") if "panels" in cfg else 0, 0, "pass panels=3")
    out = cfg.get("out")
    if out is not None and Path(str(out)).exists() and not Path(str(out)).is_dir():
        raise B3dgsError(f"out={out} is a file", "pass out=PATH to a folder (uq.json and the plots go there)")
    uq = cfg.get("uq")
    regimes = [name for name, _ in _group_options("uq")]
    if not isinstance(uq, DictConfig) or not any(isinstance(uq[k], DictConfig) for k in uq.keys()):
        raise B3dgsError("no uncertainty regime selected", f"pass uq=[native,proxy] (options: {', '.join(regimes)})")
    samples = _get(uq, "samples", "uq.samples") if "samples" in uq else 2
    _need(_is_int(samples) and samples >= 2, "uq.samples", samples,
          "an integer >= 2 (one sample has no spread: zero variance)", "pass uq.samples=50")
    for name in uq.keys():
        node = uq[name]
        if name == "samples":
            continue
        if not isinstance(node, DictConfig) or "_target_" not in node:
            raise B3dgsError(f"uq.{name} is not an uncertainty regime{did_you_mean(str(name), regimes)}",
                             f"pick uq=[{','.join(regimes)}]")
        v = _check_target_node(node, f"uq.{name}")
        if "samples" in v:
            _need(_is_int(v["samples"]) and v["samples"] >= 2, f"uq.{name}.samples", v["samples"],
                  "an integer >= 2", "pass uq.samples=50")
        if len(runs) < int(v.get("min_members") or 0):
            raise B3dgsError(f"uq={name} needs >= {v['min_members']} run dirs, got {len(runs)}",
                             "pass run=[RUN_S0,RUN_S1,RUN_S2] (seeded runs of one scene and model)")
        try:
            obj = instantiate(node)
            if hasattr(obj, "check"):
                obj.check()
        except (ValueError, TypeError) as e:
            raise B3dgsError(f"uq.{name}: {' '.join(str(e).split())}", "correct that value (the defaults are in conf/uq/)") from None
    seen: dict[Path, str] = {}
    for r in runs:
        key = Path(str(r)).resolve()
        if key in seen:  # one model twice is no ensemble: zero spread between "members"
            raise B3dgsError(f"run= names the run {r} twice ({seen[key]} and {r})",
                             "pass each run dir once (an ensemble needs distinct runs, e.g. seeds)")
        seen[key] = str(r)
    for r in runs:
        d = Path(str(r))
        if not (d / "config.yaml").is_file():
            raise B3dgsError(f"{d} is not a b3dgs run dir (no config.yaml)", "pass run=RUN_DIR of a finished b3dgs-train run")
        check_checkpoint(d / "checkpoints" / "last.ckpt",
                         f"finish the run with `b3dgs-train ... hydra.run.dir={d} resume=auto`, or train it again")


# ---------------------------------------------------------------------------------------------- entry


def validate_config(cfg: DictConfig, app: str = "train") -> None:
    """Check every value of a composed ``b3dgs-train`` (``app="train"``) or ``b3dgs-eval`` config.

    Raises :class:`~b3dgs.errors.B3dgsError` naming the first problem and its fix; reads no images.
    """
    _check_top(cfg, app)
    if app == "eval":
        _check_eval(cfg)
        return
    _check_posterior_list(cfg)
    _check_renderer(cfg)  # before data: data.near_plane interpolates renderer.near
    _check_data(cfg)
    _check_model(cfg)
    _check_trainer(cfg)
    _check_plugins(cfg)
    if isinstance(cfg.get("logger"), DictConfig) and "_target_" in cfg.logger:
        _check_target_node(cfg.logger, "logger")
    _check_resume(cfg)
    warn_slow_renderer(cfg)


#: a run the renderer's stated speed puts above this many seconds gets a warning before it starts
SLOW_RUN_S = 600.0


def warn_slow_renderer(cfg: DictConfig) -> Optional[str]:
    """A warning (logged and returned) when the renderer states a CPU cost per step (``cpu_seconds_per_step``, e.g.
    the pure-PyTorch reference's ~1 s) that puts ``trainer.max_steps`` above :data:`SLOW_RUN_S` on the CPU."""
    import logging

    node = cfg.get("renderer")
    if not isinstance(node, DictConfig) or "_target_" not in node:
        return None
    target = _locate(str(node["_target_"]))
    per_step = getattr(target, "cpu_seconds_per_step", None)
    steps = _get(cfg.trainer, "max_steps", "trainer.max_steps")
    device = str(node.get("device_name", "cpu"))
    import torch

    on_cpu = device == "cpu" or (device == "auto" and not torch.cuda.is_available())
    if not (per_step and on_cpu and _is_int(steps) and steps * per_step > SLOW_RUN_S):
        return None
    msg = (f"renderer={getattr(target, 'name', node['_target_'])} trains at about "
           f"{per_step:g} s per step on the CPU: trainer.max_steps={steps} will take about {steps * per_step / 60:.0f} "
           f"min (fix: renderer=cpu, the C++ backend, is ~40x faster; or fewer trainer.max_steps)")
    logging.getLogger(__name__).warning(msg)
    return msg

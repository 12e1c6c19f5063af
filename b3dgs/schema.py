"""Typed config nodes: the keys and value types of every ``_target_`` node are checked by OmegaConf.

A node's schema is a structured config made from its target's fields (a dataclass's, else its keyword parameters
with their annotations); :func:`check_node` sets the user's values into it one key at a time, so an unknown key or a
value of the wrong type becomes one :class:`B3dgsError` line. Ranges: a component checks its own in ``validate``; the
core's own values follow :data:`RULES`; rules across fields are :mod:`b3dgs.validation`'s.
"""
from __future__ import annotations

import dataclasses
import inspect
import math
import types
import typing
from collections.abc import Sequence
from fnmatch import fnmatch
from typing import Any, Callable, Dict, List, Optional

from omegaconf import MISSING, DictConfig, ListConfig, OmegaConf
from omegaconf.errors import ConfigAttributeError, ConfigKeyError, MissingMandatoryValue, ValidationError

from b3dgs.errors import B3dgsError, did_you_mean

__all__ = ["RGB_RULE", "RULES", "UNRESOLVED", "apply_rules", "check_node", "is_int", "is_number", "locate",
           "positive_rule", "show", "value"]

UNRESOLVED = object()  # a value that only a running Hydra app can resolve (${hydra:...})
_WHAT = {bool: "true or false", int: "an integer", float: "a finite number", str: "a string", list: "a list"}


def value(node: DictConfig, key: str, path: str) -> Any:
    """A value of ``node``, resolved (containers as plain lists and dicts); :data:`UNRESOLVED` for ``${hydra:...}``."""
    if OmegaConf.is_missing(node, key):
        raise B3dgsError(f"{path} is not set", f"pass {path}=VALUE on the command line")
    try:
        v = node[key]
    except MissingMandatoryValue as e:
        key = getattr(e, "full_key", None)
        raise B3dgsError(f"{path} needs {key or 'a value'}, which is not set",
                         f"pass {key or 'it'}=VALUE on the command line") from None
    except Exception as e:  # noqa: BLE001 - unresolvable interpolations (${hydra:...} outside an app)
        if "hydra" in str(e).lower():
            return UNRESOLVED
        raise B3dgsError(f"{path} cannot be resolved ({' '.join(str(e).split())[:160]})",
                         f"correct the interpolation in {path}") from None
    return OmegaConf.to_container(v, resolve=True) if isinstance(v, (DictConfig, ListConfig)) else v


def show(v: Any) -> str:
    """A value as it is written on the command line."""
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(show(x) for x in v) + "]"
    return "null" if v is None else str(v)


def locate(target: str) -> Callable:
    from hydra.utils import get_object

    try:
        return get_object(target)
    except Exception as e:  # noqa: BLE001
        raise B3dgsError(f"_target_ {target} cannot be imported ({type(e).__name__})",
                         "install the package that provides it, or correct _target_") from None


def _type(hint: Any, default: Any) -> Any:
    """The OmegaConf type of a field: bool, int, float, str or a list (Optional where None is allowed), else Any;
    an unannotated field is typed by its default."""
    if hint is Any and default is not MISSING and default is not None:
        hint = type(default)
    optional = default is None
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        rest = [a for a in typing.get_args(hint) if a is not type(None)]
        optional, hint = optional or len(rest) < len(typing.get_args(hint)), rest[0] if len(rest) == 1 else Any
    base = typing.get_origin(hint) or hint
    if base in (bool, int, float, str):
        t = base
    elif isinstance(base, type) and issubclass(base, (list, tuple, Sequence)) and base is not str:
        t = List[Any]
    else:
        return Any
    return Optional[t] if optional else t


def _fields(target: Callable) -> tuple[Dict[str, tuple[Any, Any]], bool]:
    """(name -> (annotation, default or MISSING) of what ``target`` accepts, whether it takes ``**kwargs``); the fields
    of a dataclass parameter ``settings`` (``Optional[SceneSettings]``) stand for it, as flat keys."""
    try:
        hints = typing.get_type_hints(target if dataclasses.is_dataclass(target) or not isinstance(target, type)
                                      else target.__init__)
    except Exception:  # noqa: BLE001 - an annotation that does not evaluate here is not checked
        hints = {}
    params = inspect.signature(target).parameters.values()
    fields = {p.name: (hints.get(p.name, Any), MISSING if p.default is p.empty else p.default) for p in params
              if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}
    hint = fields.get("settings", (None,))[0]
    nested = [a for a in (hint, *typing.get_args(hint)) if isinstance(a, type) and dataclasses.is_dataclass(a)]
    if nested:
        fields = {**{k: f for k, f in fields.items() if k != "settings"}, **_fields(nested[0])[0]}
    return fields, any(p.kind == p.VAR_KEYWORD for p in params)


def _unknown(path: str, key: str, known) -> B3dgsError:
    known = sorted(k for k in known if not k.startswith("_"))
    return B3dgsError(f"unknown config key {path}.{key}{did_you_mean(key, known)}",
                      f"remove it or correct its spelling (keys of {path}: {', '.join(known)})")


def check_node(node: DictConfig, path: str, also: Optional[Callable] = None, extra: Optional[dict] = None,
               shown: Optional[dict] = None) -> Dict[str, Any]:
    """Keys and types of the ``_target_`` node ``node`` (at dotted ``path``) against its target's schema; returns
    its resolved values. ``also``: a function whose keywords the target forwards through ``**kwargs`` (the data
    module's format loader); ``extra``: further keys -> example values (b3dgs's own trainer settings); ``shown``:
    the defaults to name in a fix where they are not the target's (the chosen trainer option's values)."""
    fields, var_kw = _fields(locate(str(node["_target_"])))
    if also is not None or extra is not None:  # what the target forwards through **kwargs, and nothing else
        fields.update({k: f for k, f in (_fields(also)[0] if also else {}).items() if k not in fields})
        fields.update({k: (Any, v) for k, v in (extra or {}).items() if k not in fields})
        var_kw = False
    types_ = {k: _type(h, d) for k, (h, d) in fields.items()}
    schema = OmegaConf.structured(dataclasses.make_dataclass(
        "Schema", [(k, t, dataclasses.field(default=MISSING)) for k, t in types_.items()]))
    OmegaConf.set_struct(schema, not var_kw)
    values = {}
    for key in map(str, node.keys()):
        if key.startswith("_"):
            continue
        values[key] = v = value(node, key, f"{path}.{key}")
        try:
            schema[key] = MISSING if v is UNRESOLVED else v
        except (ConfigKeyError, ConfigAttributeError):
            raise _unknown(path, key, fields) from None
        except ValidationError:
            t = types_[key]
            t = typing.get_args(t)[0] if typing.get_origin(t) is typing.Union else t
            base = list if typing.get_origin(t) is list else t
            default = (shown or {}).get(key, fields[key][1])
            example = f", like its default {show(default)}" if default not in (MISSING, None) else ""
            raise B3dgsError(f"{path}.{key}={show(v)} is invalid: it must be {_WHAT[base]}",
                             f"pass {path}.{key}=<{base.__name__}>{example}") from None
    return values


# ---------------------------------------------------------------------------------------------- ranges


def is_int(v: Any, lo: int, hi: float = math.inf) -> bool:
    """``v`` is an integer (not a bool) in ``[lo, hi)``."""
    return isinstance(v, int) and not isinstance(v, bool) and lo <= v < hi


def is_number(v: Any) -> bool:
    """``v`` is a finite int or float (not a bool)."""
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def positive_rule(name: str, fix: str):
    """A rule (test, what, fix) for a positive finite number; ``name`` is appended to "a positive number"."""
    return lambda v: is_number(v) and v > 0, f"a positive number{name}", fix


def default_fix(conf_file: str) -> Callable[[str], str]:
    """A rule's fix that names the key's default in ``conf_file`` (relative to the config folder): ``pass
    trainer.max_steps=30000 (the default of conf/trainer/default.yaml)``."""
    def fix(key: str) -> str:
        from pathlib import Path

        from b3dgs.paths import conf_dir

        conf, missing = OmegaConf.load(Path(conf_dir()) / conf_file), object()
        for k in (key, key.partition(".")[2]):  # a @package _global_ file holds model.*; a group's file its own keys
            try:
                value = OmegaConf.select(conf, k, default=missing)
            except Exception:  # noqa: BLE001 - an interpolation to another group: no default to name
                value = missing
            if value is not missing and not isinstance(value, (DictConfig, ListConfig)):
                return f"pass {key}={show(value)} (the default of conf/{conf_file})"
        return f"see conf/{conf_file} for the defaults"
    return fix


_MODEL = default_fix("model/standard.yaml")
_TRAINER = default_fix("trainer/default.yaml")
RGB_RULE = (lambda v: isinstance(v, list) and len(v) == 3 and all(is_number(x) and 0 <= x <= 1 for x in v), "3 numbers in [0, 1] (RGB)")
#: the ranges of the core's own values (the top-level keys, model, trainer, uq), in the order they are checked: a dotted
#: key (a pattern) -> (test, what the value must be, fix); a key ending in ``?`` also takes null. Keys a config does not
#: hold are skipped. The renderer and the data module check their own values in their ``validate`` (the data module's
#: table is :data:`b3dgs.data.scene.DATA_RULES`), as every plugin does.
RULES = {
    "seed": (lambda v: is_int(v, 0, 2**32), "an integer in [0, 2^32)", "pass seed=0"),
    "threads?": (lambda v: is_int(v, 1), "an integer >= 1 or null", "pass threads=2 or threads=null (torch's default)"),
    "model.sh_degree": (lambda v: is_int(v, 0, 4), "0, 1, 2 or 3", _MODEL),
    "model.sh_increase_every": (lambda v: is_int(v, 1), "an integer >= 1", _MODEL),
    "model.lambda_dssim": (lambda v: is_number(v) and 0 <= v <= 1, "in [0, 1]", "pass model.lambda_dssim=0.2"),
    "model.lr_*": (lambda v: is_number(v) and v >= 0, "a finite number >= 0", _MODEL),
    "model.background": (*RGB_RULE, "pass model.background=[0,0,0] (black) or model.background=[1,1,1] (white)"),
    "model.init_opacity": (lambda v: is_number(v) and 0 < v < 1, "strictly between 0 and 1 (its logit must be finite)",
                           "pass model.init_opacity=0.1"),
    "model.init_scale": positive_rule(" (it multiplies the initial Gaussian sizes; their log must be finite)",
                                      "pass model.init_scale=1.0"),
    "model.init_max_points?": (lambda v: is_int(v, 1), "an integer >= 1 or null", _MODEL),
    "model.init_num_random": (lambda v: is_int(v, 0), "an integer >= 0", _MODEL),
    **{f"trainer.{k}": (lambda v: is_int(v, 1), "an integer >= 1", _TRAINER)
       for k in ("max_steps", "eval_every", "checkpoint_every", "log_every_n_steps")},
    "trainer.curve_max_views?": (lambda v: is_int(v, 1), "an integer >= 1 or null", _TRAINER),
    "max_views?": (lambda v: is_int(v, 1), "an integer >= 1 or null", "pass max_views=N or null for all test views"),
    "panels": (lambda v: is_int(v, 0), "an integer >= 0", "pass panels=3"),
    "uq.*samples": (lambda v: is_int(v, 2), "an integer >= 2 (one sample has no spread: zero variance)", "pass uq.samples=50"),
}

def apply_rules(values: Dict[str, Any], rules: Optional[Dict[str, tuple]] = None) -> None:
    """Refuse the first value of ``values`` (dotted key -> resolved value) that breaks a rule of ``rules`` (default
    :data:`RULES`), as one :class:`B3dgsError` ``"<key>=<value> is invalid: it must be <what>"`` with the rule's fix."""
    for pattern, (ok, what, fix) in (RULES if rules is None else rules).items():
        for key, v in values.items():
            if fnmatch(key, pattern.rstrip("?")) and v is not UNRESOLVED and not (v is None and pattern.endswith("?")) \
                    and not ok(v):
                raise B3dgsError(f"{key}={show(v)} is invalid: it must be {what}", fix(key) if callable(fix) else fix)

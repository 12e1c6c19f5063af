"""A run's method label, from what ran: the model option that ran as much of it as possible, plus what differs.

``method_label(cfg)`` is a *base* followed by what the run adds to it. The base is, among the model options with the
same model settings as the run's ``model.name`` (``standard``, ``niw`` and ``dpmm`` share them; ``mcmc`` has its
own), the one whose posterior blocks are the largest subset of the run's (ties: the same strategy, then the run's
own model): so the label names what ran, not how it was asked for (``model=standard posterior=[niw,sh]`` and
``model=niw posterior=[niw,sh]`` are both ``niw+sh``; ``posterior=[niw,dp]`` is ``niw+dp``). Then

* ``@<value>`` for each setting of a block that changes the method (a block class's ``label_settings``: NIW's
  ``count``) at a value other than the paper's, right after the base for the base's blocks and after the block's
  name for an added block (``posterior.niw.count=fisher``: ``niw@fisher``; ``dpmm@fisher3``; ``niw@weight+sh``);
* ``+block`` / ``-block`` for each posterior block added to / missing from the base's own list;
* ``+<strategy>`` when the strategy is not the base's own (``model=mcmc strategy=default``: ``mcmc+adc``;
  the option ``default`` is named by its class's initials, AdaptiveDensityControl -> ``adc``);
* ``+<schedule>`` for a training schedule other than ``constant`` (``schedule=dash``: ``+dash``; a config without
  a ``schedule`` node, from before schedules existed, ran the constant one).

Other settings inside a block or strategy (``strategy.max_gaussians=...``) do not change the label. The models' own
defaults are read from their option files (``conf/model/<name>.yaml`` and the files they extend); a model without an
option file is labelled by its name alone. Every label is a valid Hydra override value and file name (no ``=``,
brackets or spaces). ``${b3dgs.method:}`` gives the label inside a config (run dir names).
"""
from __future__ import annotations

import json
import re
from functools import lru_cache
from typing import Any, Mapping, Optional

from omegaconf import DictConfig, OmegaConf

from b3dgs.confs import conf_roots, load_option as _option, option_names

__all__ = ["method_label", "register_resolver"]

_DEFAULT_STRATEGY, _DEFAULT_SCHEDULE = "default", "constant"  # conf/train.yaml's defaults list


@lru_cache(maxsize=None)
def _model_defaults(name: str) -> Optional[tuple[tuple[str, ...], str]]:
    """(posterior blocks, strategy option) a model option selects itself; None without an option file."""
    data = _option("model", name)
    if data is None:
        return None
    blocks, strategy = (), _DEFAULT_STRATEGY
    for entry in data.get("defaults") or []:
        if isinstance(entry, str) and entry != "_self_":
            parent = _model_defaults(entry)
            if parent is not None:
                blocks, strategy = parent
        elif isinstance(entry, Mapping):
            for key, val in entry.items():
                group = str(key).replace("override", "").strip().lstrip("/")
                if group == "posterior":
                    blocks = tuple(str(v) for v in (val or []))
                elif group == "strategy":
                    strategy = str(val)
    return blocks, strategy


def _class(target: Any) -> str:
    return str(target or "").rsplit(".", 1)[-1]


@lru_cache(maxsize=None)
def _option_of(group: str, cls: str) -> Optional[str]:
    """The option of ``group`` whose ``_target_`` is class ``cls``."""
    for root in conf_roots():
        for f in sorted((root / group).glob("*.yaml")):
            if _class((_option(group, f.stem) or {}).get("_target_")) == cls:
                return f.stem
    return None


def _initials(cls: str) -> str:
    words = re.findall(r"[A-Z]+(?![a-z])|[A-Z][a-z0-9]*|[a-z0-9]+", re.sub(r"Strategy$", "", cls))
    return ("".join(w[0] for w in words) if len(words) > 1 else "".join(words)).lower() or cls.lower()


@lru_cache(maxsize=None)
def _model_settings(name: str) -> str:
    """The model node a model option composes (its own file over the files it extends), but its name, as JSON."""
    def merged(n: str) -> dict:
        data = _option("model", n) or {}
        out: dict = {}
        for entry in data.get("defaults") or []:
            if isinstance(entry, str) and entry != "_self_" and _option("model", entry) is not None:
                out.update(merged(entry))
        out.update(data.get("model") or {})
        return out

    return json.dumps({k: v for k, v in merged(name).items() if k != "name"}, sort_keys=True, default=str)


def _base(name: str, blocks: list[str], cls: str) -> str:
    """The model option a run of model ``name`` with posterior ``blocks`` and strategy class ``cls`` is labelled
    from: see the module doc."""
    fits = [m for m in option_names("model") if _model_defaults(m) is not None
            and _model_settings(m) == _model_settings(name) and set(_model_defaults(m)[0]) <= set(blocks)]
    if not fits:
        return name

    def rank(m: str):
        own_blocks, own_strategy = _model_defaults(m)
        same_strategy = _class((_option("strategy", own_strategy) or {}).get("_target_")) == cls
        return -len(own_blocks), not same_strategy, m != name, m

    return min(fits, key=rank)


def _settings(block: str, node: Any) -> str:
    """``@<value>`` for each of the block's ``label_settings`` at a value other than the class's default."""
    if not isinstance(node, Mapping) or not node.get("_target_"):
        return ""
    try:
        from hydra.utils import get_class

        declared = dict(getattr(get_class(str(node["_target_"])), "label_settings", None) or {})
    except Exception:  # noqa: BLE001 - a class this code cannot import: labelled by its name
        return ""
    return "".join(f"@{node[k]}" for k, default in declared.items() if k in node and node[k] != default)


def method_label(cfg: Mapping | DictConfig) -> str:
    """The method label of a composed (or saved) run config; see the module doc."""
    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=False)
    model = cfg.get("model") or {}
    name = str(model.get("name") or "custom")
    if _model_defaults(name) is None:
        return name
    posterior = cfg.get("posterior") or {}
    blocks = [str(b) for b in posterior]
    cls = _class((cfg.get("strategy") or {}).get("_target_"))
    base = _base(name, blocks, cls)
    own_blocks, own_strategy = _model_defaults(base)
    parts = [base] + [_settings(b, posterior[b]) for b in blocks if b in own_blocks]
    parts += [f"+{b}{_settings(b, posterior[b])}" for b in blocks if b not in own_blocks]
    parts += [f"-{b}" for b in own_blocks if b not in blocks]
    own_cls = _class((_option("strategy", own_strategy) or {}).get("_target_"))
    if cls and own_cls and cls != own_cls:
        opt = _option_of("strategy", cls)
        parts.append("+" + (opt if opt and opt != _DEFAULT_STRATEGY else _initials(cls)))
    sched = cfg.get("schedule")
    if isinstance(sched, Mapping) and sched.get("_target_"):
        cls = _class(sched["_target_"])
        if cls != _class((_option("schedule", _DEFAULT_SCHEDULE) or {}).get("_target_")):
            parts.append("+" + (_option_of("schedule", cls) or _initials(cls)))
    return "".join(parts)


def register_resolver() -> None:
    """``${b3dgs.method:}``: the label of the config it is resolved in (its root)."""
    if not OmegaConf.has_resolver("b3dgs.method"):
        OmegaConf.register_new_resolver("b3dgs.method", lambda *, _root_: method_label(_root_))

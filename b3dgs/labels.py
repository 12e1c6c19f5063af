"""A run's method label, from what ran: the model's name plus what differs from that model's own defaults.

``method_label(cfg)`` is ``model.name`` followed by

* ``+block`` / ``-block`` for each posterior block added to / missing from the model's own list
  (``b3dgs-train posterior=[niw,dp]`` with the standard model: ``standard+niw+dp``);
* ``+<strategy>`` when the strategy is not the model's own (``model=mcmc strategy=default``: ``mcmc+adc``;
  the option ``default`` is named by its class's initials, AdaptiveDensityControl -> ``adc``);
* ``+<schedule>`` for a training schedule other than ``constant`` (``schedule=dash``: ``+dash``; a config without
  a ``schedule`` node, from before schedules existed, ran the constant one).

Settings inside a block or strategy (``strategy.max_gaussians=...``) do not change the label. The model's own
defaults are read from its option file (``conf/model/<name>.yaml`` and the files it extends); a model without an
option file is labelled by its name alone. ``${b3dgs.method:}`` gives the label inside a config (run dir names).
"""
from __future__ import annotations

import re
from functools import lru_cache
from typing import Any, Mapping, Optional

from omegaconf import DictConfig, OmegaConf

from b3dgs.confs import conf_roots, load_option as _option

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


def method_label(cfg: Mapping | DictConfig) -> str:
    """The method label of a composed (or saved) run config; see the module doc."""
    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=False)
    model = cfg.get("model") or {}
    name = str(model.get("name") or "custom")
    own = _model_defaults(name)
    if own is None:
        return name
    own_blocks, own_strategy = own
    parts = [name]
    blocks = [str(b) for b in (cfg.get("posterior") or {})]
    parts += [f"+{b}" for b in blocks if b not in own_blocks] + [f"-{b}" for b in own_blocks if b not in blocks]
    cls = _class((cfg.get("strategy") or {}).get("_target_"))
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

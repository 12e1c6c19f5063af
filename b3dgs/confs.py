"""b3dgs's config folders, the keys their option files define (for labels and "did you mean" suggestions), and the
class defaults that fill their ``_target_`` nodes (:func:`with_field_defaults`)."""
from __future__ import annotations

import dataclasses
from functools import lru_cache
from pathlib import Path
from typing import Any, Dict, Optional

from omegaconf import DictConfig, OmegaConf

from b3dgs.paths import conf_dir

__all__ = ["added_key_problem", "app_groups", "conf_roots", "field_defaults", "help_groups", "help_text", "known_keys",
           "load_option", "load_primary", "option_clashes", "option_names",
           "with_field_defaults"]


def conf_roots() -> list[Path]:
    """b3dgs's conf dir and those of installed packages (``b3dgs.conf`` entry points)."""
    roots = [Path(conf_dir())]
    try:
        from importlib import resources
        from importlib.metadata import entry_points

        roots += [Path(str(resources.files(ep.value))) for ep in entry_points(group="b3dgs.conf")]
    except Exception:  # noqa: BLE001 - a broken extension package must not hide b3dgs's own options
        pass
    return roots


def _config_value(v: Any) -> bool:
    """``v`` is a value a YAML file can hold (None, bool, number, string, or lists and mappings of them)."""
    if v is None or isinstance(v, (bool, int, float, str)):
        return True
    if isinstance(v, (list, tuple)):
        return all(map(_config_value, v))
    return isinstance(v, dict) and all(isinstance(k, str) and _config_value(x) for k, x in v.items())


def _settings_class(cls: Any) -> Optional[type]:
    """The dataclass that a class's ``settings`` parameter is annotated with (``Optional[SceneSettings]``), else None:
    its fields are the class's flat config keys (:func:`b3dgs.schema._fields` reads them the same way)."""
    import typing

    try:
        hint = typing.get_type_hints(cls.__init__).get("settings")
    except Exception:  # noqa: BLE001 - an annotation that does not evaluate here fills nothing
        return None
    return next((a for a in (hint, *typing.get_args(hint)) if isinstance(a, type) and dataclasses.is_dataclass(a)), None)


#: targets whose modules import Lightning (seconds at start-up), by what :func:`field_defaults` gives for them: the
#: dataclass whose fields they take (``"module:Class"``) or None (no fields). So composing a config (``--help``, a
#: misspelt key or option) does not import Lightning. ``tests/test_config_defaults.py`` checks each against the class.
LIGHTNING_TARGETS: Dict[str, Optional[str]] = {
    "lightning.Trainer": None,
    "lightning.pytorch.loggers.TensorBoardLogger": None,
    "b3dgs.module.SplatModule": None,
    "b3dgs.data.datamodule.SceneDataModule": "b3dgs.data.scene:SceneSettings",
}


def field_defaults(target: str) -> Dict[str, Any]:
    """The defaults of the dataclass ``target`` (a class path), field by field in declaration order: the one home of
    a component's defaults. A class that is no dataclass gives those of the dataclass its ``settings`` parameter takes
    (the data module's :class:`~b3dgs.data.scene.SceneSettings`: ``data.max_side``, ...), as flat keys. Fields without
    a default a config can hold, or marked ``metadata={"config": False}``, are left out; {} when ``target`` has no
    such dataclass or does not import (the schema check reports that)."""
    from hydra.utils import get_object

    try:
        if target in LIGHTNING_TARGETS:
            cls = LIGHTNING_TARGETS[target] and get_object(LIGHTNING_TARGETS[target].replace(":", "."))
        else:
            cls = get_object(target)
    except Exception:  # noqa: BLE001 - reported by check_node when the node is checked
        return {}
    if isinstance(cls, type) and not dataclasses.is_dataclass(cls):
        cls = _settings_class(cls)
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        return {}
    out = {}
    for f in dataclasses.fields(cls):
        d = f.default if f.default_factory is dataclasses.MISSING else f.default_factory()
        if f.init and f.metadata.get("config", True) and d is not dataclasses.MISSING and _config_value(d):
            out[f.name] = list(d) if isinstance(d, tuple) else d
    return out


def _composed_packages(defaults: Any) -> set[str]:
    """The keys a file's defaults list composes into (``- /posterior@posterior: sh`` -> ``posterior``)."""
    out = set()
    for entry in defaults if isinstance(defaults, list) else []:
        for key in entry if isinstance(entry, dict) else [entry]:
            _, at, pkg = str(key).partition("@")
            if at and pkg and pkg != "_global_":
                out.add(pkg.split(".")[0])
    return out


def _fill(node: Any) -> bool:
    """Give every ``_target_`` mapping in ``node`` (a plain container) the :func:`field_defaults` of its target that
    it does not set: ``_target_``, then its keys that are no field (the data module's ``kind``, ``path``), then the
    fields in declaration order. Whether any changed."""
    changed = False
    if isinstance(node, dict):
        for k, v in node.items():
            changed |= k != "defaults" and _fill(v)
        target = node.get("_target_")
        fields = field_defaults(target) if isinstance(target, str) else {}
        for pkg in _composed_packages(node.get("defaults")):  # set by the file's defaults list: never filled over
            fields.pop(pkg, None)
        if any(k not in node for k in fields):
            first = {k: node[k] for k in ("defaults", "_target_") if k in node}
            filled = {**first, **{k: v for k, v in node.items() if k not in fields}}
            filled.update({k: node.get(k, d) for k, d in fields.items()})
            node.clear()
            node.update(filled)
            changed = True
    elif isinstance(node, list):
        for v in node:
            changed |= _fill(v)
    return changed


def with_field_defaults(cfg: DictConfig) -> DictConfig:
    """A config file as b3dgs's apps compose it: a ``_target_`` node holds only its deviations from the target's
    dataclass defaults, and every other field is filled in from the class (:func:`field_defaults`), so that the
    composed config shows every setting and ``group.field=value`` overrides any field. The fill is the node's base
    layer within its file: a file that extends another option of its own package (its defaults list) does not repeat
    ``_target_``. Interpolations and ``???`` stay as written."""
    data = OmegaConf.to_container(cfg, resolve=False)
    return OmegaConf.create(data) if _fill(data) else cfg


def _load(f: Path) -> tuple[dict, bool]:
    """(the file's contents, whether it is a ``@package _global_`` file)."""
    text = f.read_text()
    data = OmegaConf.to_container(OmegaConf.create(text), resolve=False) or {}
    return (data if isinstance(data, dict) else {}), any("@package _global_" in ln for ln in text.splitlines()[:5])


@lru_cache(maxsize=None)
def global_groups() -> frozenset:
    """The config groups all of whose option files (in b3dgs's conf dir and every package's) are ``@package _global_``
    files that set keys all over the config and never a node named after the group (``scene``, ``experiment``)."""
    files: dict[str, list[bool]] = {}
    for root in conf_roots():
        for d in (d for d in root.iterdir() if d.is_dir() and d.name != "hydra"):
            for f in d.glob("*.yaml"):
                data, is_global = _load(f)
                # a global file that fills a node named after its group (model/*.yaml: model: {...}) gives it one
                files.setdefault(d.name, []).append(is_global and d.name not in data)
    return frozenset(g for g, flags in files.items() if flags and all(flags))


def compose_config(config_name: str, overrides: list[str]) -> DictConfig:
    """b3dgs's config ``config_name`` (train, study, ...) composed with ``overrides``, inside a running Hydra app
    or on its own."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    if GlobalHydra.instance().is_initialized():
        return compose(config_name=config_name, overrides=overrides)
    with initialize_config_dir(config_dir=conf_dir(), version_base="1.3"):
        return compose(config_name=config_name, overrides=overrides)


@lru_cache(maxsize=None)
def load_option(group: str, name: str):
    """The contents of option ``name`` of config ``group`` (the first root that has it), None if none has."""
    for root in conf_roots():
        f = root / group / f"{name}.yaml"
        if f.is_file():
            return _load(f)[0]
    return None


@lru_cache(maxsize=None)
def option_names(group: str) -> tuple[str, ...]:
    """The option names of config ``group`` (b3dgs's and installed packages'), e.g. the ``model=`` options."""
    return tuple(sorted({f.stem for root in conf_roots() for f in (root / group).glob("*.yaml")}))


def _defaults_groups(data: dict) -> set[str]:
    """The config groups a primary config's defaults list names (``- data: synthetic``, ``- override /x: y``)."""
    out = set()
    for d in data.get("defaults") or []:
        for k in (d if isinstance(d, dict) else {}):
            out.add(str(k).removeprefix("override ").lstrip("/").split("@")[0].removeprefix("optional "))
    return out


@lru_cache(maxsize=None)
def known_keys(path: str, config: Optional[str] = None) -> tuple[str, ...]:
    """The keys that b3dgs's config files give the node at dotted ``path`` ("" for the top level): the primary configs'
    (only ``config``'s, e.g. ``train``, when given; at the top level with its config groups) and every option file's of
    the group the path starts with (e.g. ``trainer`` -> ``conf/trainer/*.yaml``), a ``_target_`` node's with the
    fields of its dataclass (which the config sources fill in)."""
    parts = [p for p in path.split(".") if p]
    keys: set[str] = set()

    def descend(node, rest):
        for p in rest:
            node = node.get(p) if isinstance(node, dict) else None
        if isinstance(node, dict):
            keys.update(str(k) for k in node if k not in ("defaults", "_target_"))
            if isinstance(node.get("_target_"), str):  # the fields the file leaves to its class's defaults
                keys.update(field_defaults(node["_target_"]))

    for root in conf_roots():
        primaries = [root / f"{config}.yaml"] if config else sorted(root.glob("*.yaml"))
        for f in (f for f in primaries if f.is_file()):  # primary configs (train, eval, view, ...)
            data = _load(f)[0]
            descend(data, parts)
            if config and not parts:
                keys.update(_defaults_groups(data) - {"hydra", "_self_"})
        if not parts and not config:
            keys.update(d.name for d in root.iterdir() if d.is_dir() and d.name != "hydra")
        elif parts and (root / parts[0]).is_dir():
            for f in sorted((root / parts[0]).glob("*.yaml")):
                data, is_global = _load(f)
                descend(data, parts if is_global else parts[1:])
    return tuple(sorted(keys))


def _nodes_at(path: str, config: str) -> list:
    """The nodes b3dgs's config files give dotted ``path`` under app ``config`` (its primary config, and every option
    file of the group the path starts with when the app's defaults list composes that group), as loaded."""
    parts = [p for p in path.split(".") if p]
    found = []

    def descend(node, rest):
        for p in rest:
            if not isinstance(node, dict) or p not in node:
                return
            node = node[p]
        found.append(node)

    groups = set()
    for root in conf_roots():
        f = root / f"{config}.yaml"
        if f.is_file():
            data = _load(f)[0]
            descend(data, parts)
            groups |= _defaults_groups(data)
    for root in conf_roots():  # option files of the groups the app composes (a node of the same name is not one)
        if parts and parts[0] in groups and (root / parts[0]).is_dir():
            for g in sorted((root / parts[0]).glob("*.yaml")):
                data, is_global = _load(g)
                descend(data, parts if is_global else parts[1:])
    return found


def added_key_problem(key: str, config: str, prog: Optional[str] = None) -> Optional[tuple[str, str]]:
    """(problem, fix) when ``+key=...`` adds a key that nothing of app ``config`` reads, else None. A key is read when a
    config file of the app gives it, or when it lies under a node that takes any key: an empty mapping there
    (``policy_settings: {}``, ``callbacks: {}``) or a ``_target_`` node (whose class's fields decide, when it is
    built). ``hydra.*`` is Hydra's own."""
    import difflib

    parts = [p for p in str(key).split(".") if p]
    if not parts or parts[0] == "hydra":
        return None
    for i in range(len(parts)):  # the first prefix no file gives; stop early under a node that takes any key
        nodes = _nodes_at(".".join(parts[:i + 1]), config)
        if not nodes:
            break
        if i + 1 < len(parts) and any(isinstance(n, dict) and (not n or "_target_" in n) for n in nodes):
            return None
    else:
        return None  # the key exists
    parent, leaf = ".".join(parts[:i]), parts[i]
    known = [k for k in known_keys(parent, config) if not k.startswith("hydra") and "/" not in k]
    close = difflib.get_close_matches(leaf, known, n=1, cutoff=0.6)
    hint = f"; did you mean {(parent + '.' if parent else '') + close[0]}?" if close else ""
    where = f"{parent}.{leaf}" if parent else leaf
    return (f"+{key}: {where} reaches nothing {prog or 'b3dgs-' + config} reads{hint}",
            f"remove it, or set one of {parent + '.' if parent else ''}{{{', '.join(known)}}}")


def option_clashes() -> list[tuple[str, list[Path]]]:
    """Config options that two conf roots both give (``model/niw.yaml`` in b3dgs and in an installed package): one
    name that means two files, of which Hydra would silently take one. [(``group/name``, [the files])]."""
    seen: dict[str, list[Path]] = {}
    for root in dict.fromkeys(r.resolve() for r in conf_roots()):  # one folder named twice is one root
        if not root.is_dir():
            continue
        for f in sorted(root.rglob("*.yaml")):
            rel = f.relative_to(root).with_suffix("").as_posix()
            if "/" in rel and not rel.startswith("hydra/"):  # group options, not primary configs
                seen.setdefault(rel, []).append(f)
    return [(k, v) for k, v in sorted(seen.items()) if len(v) > 1]


def _format_groups(keep) -> str:
    """Hydra's ``--help`` list of the config groups ``keep(group)`` accepts ("" outside a Hydra app)."""
    from hydra.core.global_hydra import GlobalHydra

    hydra = GlobalHydra.instance().hydra if GlobalHydra.instance().is_initialized() else None
    return "" if hydra is None else hydra.format_config_groups(keep)


def load_primary(config: str) -> dict:
    """The contents of app ``config``'s primary config (``conf/<config>.yaml``, the first root that has it; {} if none)."""
    f = next((f for f in (root / f"{config}.yaml" for root in conf_roots()) if f.is_file()), None)
    return {} if f is None else _load(f)[0]


def app_groups(config: str) -> set[str]:
    """The config groups app ``config`` reads: those its primary config's defaults list names (Hydra's aside)."""
    return {g for g in _defaults_groups(load_primary(config)) if g != "_self_" and g.split("/")[0] != "hydra"}


def help_groups(config: str, *hidden: str) -> str:
    """Hydra's ``--help`` list of the config groups (``group: option, ...`` lines) app ``config`` reads
    (:func:`app_groups`), less the ``hidden`` ones: ``NAME`` hides a group, ``NAME=OPTION`` one option of a group
    (``b3dgs-train`` hides experiment/strategy, which its experiment picks, and the study-only preset)."""
    options = {tuple(h.split("=", 1)) for h in hidden if "=" in h}
    shown = app_groups(config) - {h for h in hidden if "=" not in h}
    lines = []
    for line in _format_groups(lambda g: g in shown).splitlines(keepends=True):
        group, sep, rest = line.partition(": ")
        if sep and any(g == group for g, _ in options):
            line = f"{group}: {', '.join(o for o in rest.strip().split(', ') if (group, o) not in options)}\n"
        lines.append(line)
    return "".join(lines)


#: the end of every b3dgs command's ``--help``
HELP_FOOTER = ("Overrides are key=value, group=option or +key=value; -m (--multirun) before them sweeps a,b,c values;\n"
               "--cfg job prints the composed config; --hydra-help lists Hydra's own flags.")


def help_text(config: str, *hidden: str, _parent_=None) -> str:
    """The ``--help`` template of a b3dgs command (``hydra.help.template: ${b3dgs.help:CONFIG,HIDDEN...}`` in its
    primary config): its ``hydra.help.header`` (the purpose line and three examples), the config groups it reads
    (:func:`help_groups`; none listed for a command that reads none), its config (Hydra's ``$CONFIG``) and
    :data:`HELP_FOOTER`."""
    header = str(_parent_.get("header", "")).rstrip() if _parent_ is not None else ""
    groups = help_groups(config, *hidden)
    parts = [header.replace("$", "$$"), ""]
    if groups:
        parts += ["== Configuration groups ==", "Compose your configuration from those groups (group=option)", "",
                  groups.rstrip().replace("$", "$$"), ""]
    parts += ["== Config ==", "Override anything in the config (foo.bar=value)", "", "$CONFIG", HELP_FOOTER]
    return "\n".join(parts)

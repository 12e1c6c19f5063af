"""Config rules that no single target can check, run before any scene is loaded.

:func:`validate_config` checks a composed config and raises :class:`~b3dgs.errors.B3dgsError` ``(problem, fix)`` for
the first bad value. Node keys and types come from :mod:`b3dgs.schema`; each plugin is built and checks its own values
in ``validate``. Here: the top-level keys, the core's ranges (:data:`RULES`), values that must agree across nodes, an
unset ``data.path``, a posterior block listed twice, and files that must exist (``resume``, run dirs, lpips weights).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from b3dgs.checkpoint import check_checkpoint
from b3dgs.confs import conf_roots, global_groups, known_keys, load_option, option_names
from b3dgs.errors import B3dgsError, did_you_mean
from b3dgs.rundir import not_a_run_dir
from b3dgs.schema import RULES, UNRESOLVED, apply_rules, check_node, is_int, is_number, locate, show, value
from b3dgs.upgrade import schedule_node

__all__ = ["check_checkpoint", "hydra_value", "validate_config"]


def hydra_value(cfg: DictConfig, key: str, default: Any) -> Any:
    """``hydra.<key>`` of the composed config, else of the running Hydra app."""
    if "hydra" in cfg and OmegaConf.select(cfg, f"hydra.{key}", default=None) is not None:
        return OmegaConf.select(cfg, f"hydra.{key}")
    try:
        from hydra.core.hydra_config import HydraConfig

        return OmegaConf.select(HydraConfig.get(), key, default=default) if HydraConfig.initialized() else default
    except Exception:  # noqa: BLE001
        return default


def _blocks(cfg: DictConfig, group: str, what: str, values: dict) -> list:
    """The keyed ``_target_`` nodes of ``group`` (posterior blocks, UQ regimes, callbacks), keys and types checked."""
    out = []
    for name in (k for k in (cfg.get(group) or {}).keys() if not (group == "uq" and k == "samples")):
        node = cfg[group][name]
        if not isinstance(node, DictConfig) or "_target_" not in node:
            if group == "callbacks":
                raise B3dgsError(f"callbacks.{name} has no _target_", f"pass +callbacks.{name}._target_=CLASS_PATH "
                                 "(a lightning Callback), or drop it")
            raise B3dgsError(f"{group}.{name} is not {what}{did_you_mean(str(name), option_names(group))}",
                             f"pick {group}=[{','.join(option_names(group))}]")
        values.update({f"{group}.{name}.{k}": v for k, v in check_node(node, f"{group}.{name}").items()})
        out.append((f"{group}.{name}", node))
    return out


#: third-party targets whose ``**kwargs`` go to another callable, whose keywords are then the keys the node may have
KWARGS_FORWARDED_TO = {"lightning.pytorch.loggers.TensorBoardLogger": "torch.utils.tensorboard.writer.SummaryWriter"}


def _nested_targets(node: DictConfig, path: str):
    """(path, node) of every ``_target_`` node inside ``node`` (e.g. a UQ regime's added posterior blocks)."""
    for k in map(str, node.keys()):
        child = node._get_node(k)
        if isinstance(child, DictConfig):
            if "_target_" in child:
                yield f"{path}.{k}", child
            yield from _nested_targets(child, f"{path}.{k}")


def _validate_plugins(nodes: list, **run) -> dict:
    """Check the keys of the ``_target_`` nodes nested in each plugin's node, then build each plugin and run its
    own ``validate`` (``run``: ``max_steps``, ``sh_degree``), the one time it runs; returns the plugins by path, marked
    validated (:func:`b3dgs.plugin.validate_once`) for the run that builds its model from them."""
    from hydra.utils import instantiate

    from b3dgs.plugin import validate_once

    built = {}
    for path, node in nodes:
        for sub_path, sub in _nested_targets(node, path):
            check_node(sub, sub_path)
        try:
            built[path] = validate_once(instantiate(node), **run)
        except B3dgsError as e:
            if e.fix is not None or "(fix:" in e.problem:
                raise
            raise B3dgsError(e.problem if e.problem.startswith(path) else f"{path}: {e.problem}",
                             "correct that value (the defaults are the class's fields; `--cfg job` prints the composed values)") from None
    return built


def _refuse_other_apps_option(cfg: DictConfig, key: str, app: str) -> None:
    """A top-level ``key`` that the chosen option of a global group (``experiment=archived_posterior``) sets but only
    another b3dgs command reads: refuse the option by name (else the user sees "unknown config key <key>")."""
    for group in sorted(global_groups()):
        choice = hydra_value(cfg, f"runtime.choices.{group}", None)
        option = load_option(group, str(choice)) if choice else None
        if not isinstance(option, dict) or key not in option:
            continue
        apps = sorted({f.stem for root in conf_roots() if root.is_dir() for f in root.glob("*.yaml")})  # train, eval, ...
        readers = [f"b3dgs-{a}" for a in apps if a != app and key in known_keys("", a)]
        where = f"it is an option for {' / '.join(readers)}" if readers else "nothing reads it"
        raise B3dgsError(f"{group}={choice} sets {key}, which b3dgs-{app} does not read ({where})",
                         f"drop {group}={choice} from this command"
                         + (f", or run {readers[0]} with it" if readers else ""))


def _check_top(cfg: DictConfig, app: str, values: dict) -> None:
    known = set(known_keys("", app)) | {"hydra", "b3dgs"}
    for key in map(str, cfg.keys()):
        node = cfg.get(key)
        if key in global_groups() and isinstance(node, DictConfig) and len(node):
            # an option file of a global group without the header: its keys went under <key>.*, where nothing reads
            choice = hydra_value(cfg, f"runtime.choices.{key}", None)
            keys = ", ".join(map(str, node.keys()))
            if choice:
                raise B3dgsError(f"{key}/{choice}.yaml is not a global config file: its keys landed under {key}.{{{keys}}}, "
                                 "where nothing reads them",
                                 f"start that file with the line '# @package _global_' (as every b3dgs {key} file does)")
            first = next(iter(node.keys()))
            raise B3dgsError(f"{key}.{{{keys}}} reaches nothing: {key} options set top-level keys",
                             f"pass {first}... without the '{key}.' prefix")
        if key not in known:
            _refuse_other_apps_option(cfg, key, app)
            shown = sorted(k for k in known if "/" not in k)  # not a defaults-list subgroup (experiment/strategy)
            raise B3dgsError(f"unknown config key {key}{did_you_mean(key, shown)}",
                             f"remove it or correct its spelling (top-level keys: {', '.join(shown)})")
        if key != "hydra" and not isinstance(cfg._get_node(key), DictConfig):  # a missing run= is "run is not set"
            values[key] = value(cfg, key, key)
    extra_b3dgs = sorted(map(str, set(cfg.get("b3dgs") or {}) - {"debug"}))
    if extra_b3dgs or not isinstance(OmegaConf.select(cfg, "b3dgs.debug", default=False), bool):
        what = f"b3dgs.{extra_b3dgs[0]} is not a setting: " if extra_b3dgs else ""
        raise B3dgsError(f"{what}the b3dgs node holds only b3dgs.debug (true or false)",
                         "pass b3dgs.debug=true for full tracebacks")
    lw = values.get("lpips_weights")
    if lw not in (None, "") and not Path(str(lw)).expanduser().is_file():
        raise B3dgsError(f"lpips_weights={lw}: no such file",
                         f"run `b3dgs-lpips --out {lw}` to build it, or pass lpips_weights=null (then "
                         "$B3DGS_LPIPS_WEIGHTS or the cache ~/.cache/b3dgs/lpips_alex.pth is used)")


def _option(group: str, name: str) -> dict:
    """The values option ``name`` of ``group`` gives, with those of the options it extends (its defaults list)."""
    data, out = dict(load_option(group, name) or {}), {}
    for parent in data.pop("defaults", None) or []:
        out.update(_option(group, parent) if isinstance(parent, str) and parent != "_self_" else {})
    return {**out, **data}


#: the model's arguments that b3dgs-train fills from elsewhere (b3dgs.lifecycle.build_module), with where to set them:
#: a ``model.<name>`` key would be accepted by the model's signature and then silently replaced
MODEL_SET_BY_RUN = {"strategy": "strategy=<option> or strategy.<setting>=...",
                    "posterior": "posterior=[...] and posterior.<block>.<setting>=... (e.g. posterior.niw.kappa0=1)",
                    "renderer": "renderer=<option>", "max_steps": "trainer.max_steps=N", "seed": "seed=N",
                    "schedule": "schedule=<option> or schedule.<setting>=..."}


def _check_train(cfg: DictConfig, values: dict) -> dict:
    from b3dgs.data.scene import get_loader, loader_reads_files

    loader = get_loader(str(value(cfg.data, "kind", "data.kind")))  # one line if no format has that name
    if loader_reads_files(loader) and OmegaConf.is_missing(cfg.data, "path"):
        raise B3dgsError(f"data={cfg.data.kind} needs a scene folder: data.path is not set", "pass data.path=PATH")
    trainer = {}
    for name in option_names("trainer"):
        trainer.update({k: v for k, v in _option("trainer", name).items() if not k.startswith("_")})
    chosen = _option("trainer", hydra_value(cfg, "runtime.choices.trainer", "default"))
    extra = {"data": {"also": loader}, "trainer": {"extra": trainer, "shown": chosen}}
    logger_target = OmegaConf.select(cfg, "logger._target_", default=None)
    if logger_target in KWARGS_FORWARDED_TO:  # the logger's **kwargs go to its writer: check them against the writer's
        extra["logger"] = {"also": locate(KWARGS_FORWARDED_TO[logger_target])}
    for group in ("renderer", "data", "model", "trainer", "logger", "strategy", "schedule"):
        node = cfg.get(group)
        if isinstance(node, DictConfig) and ("_target_" in node or group != "logger"):
            if "_target_" not in node:
                raise B3dgsError(f"{group} has no _target_", f"pick a {group}= option ({'|'.join(option_names(group))})")
            values.update({f"{group}.{k}": v for k, v in check_node(node, group, **extra.get(group, {})).items()})
    for key, where in MODEL_SET_BY_RUN.items():
        if isinstance(cfg.get("model"), DictConfig) and key in cfg.model:
            raise B3dgsError(f"model.{key} is not read: b3dgs-train builds the model's {key} from its own setting",
                             f"pass {where} instead of model.{key}")
    schedule = cfg.get("schedule") if cfg.get("schedule") is not None else OmegaConf.create(schedule_node(None))
    plugins = [(g, node) for g, node in (("strategy", cfg.get("strategy")), ("schedule", schedule))  # null schedule:
               if isinstance(node, DictConfig)]  # the constant one
    plugins += _blocks(cfg, "posterior", "a posterior block", values)
    _blocks(cfg, "callbacks", "a callback", values)
    if isinstance(cfg.get("model"), DictConfig) and OmegaConf.is_interpolation(cfg.model, "background"):
        values.pop("model.background", None)  # ${data.background}: the data module checks that value, by its name
    apply_rules(values)
    bg, data_bg = values.get("model.background"), values.get("data.background")
    if None not in (bg, data_bg) and [float(x) for x in bg] != [float(x) for x in data_bg]:
        raise B3dgsError(f"model.background={show(bg)} differs from data.background={show(data_bg)}: the model renders "
                         "over the first, the images are composited on the second",
                         "drop the model.background override (it follows data.background)")
    return _validate_plugins(plugins, max_steps=int(values["trainer.max_steps"]), sh_degree=values.get("model.sh_degree"))


_BOOL, _POSITIVE = (lambda v: isinstance(v, bool), "true or false"), (lambda v: is_number(v) and v > 0, "a positive number")
_SIDE = (lambda v: is_int(v, 8), "an integer >= 8 (or null: no cap)", "pass max_side=512, or max_side=null")
#: the ranges of the values the other apps read (as :data:`b3dgs.schema.RULES`, which they get too: seed, threads),
#: checked at each app's entry by :func:`validate_config`; the values that need the run or the files stay with their use
APP_RULES = {
    "render": {"fps": (lambda v: is_int(v, 1), "a frame rate, an integer >= 1", "pass fps=24"), "max_side?": _SIDE,
               "panel_max?": (*_POSITIVE, "pass panel_max=0.05, or null (auto)"),
               "video": (*_BOOL, "pass video=false for the frames alone")},
    "export": {"overwrite": (*_BOOL, "pass overwrite=true to replace an existing out= file, or leave it out")},
    "view": {"min_side": (lambda v: is_int(v, 8), "an integer >= 8", "pass min_side=32"), "max_side?": _SIDE,
             "samples": (lambda v: is_int(v, 2), "an integer >= 2 (a spread needs two draws)", "pass samples=16"),
             **{k: (*_BOOL, f"pass {k}=true or {k}=false") for k in ("frusta", "photos")},
             **{k: (*_POSITIVE, f"pass {k}= a number > 0") for k in ("target_ms", "still_ms", "jitter", "duration_s?")},
             "sigma_max?": (*_POSITIVE, "pass sigma_max=0.03, or null (auto)"),
             "count_scale?": (*_POSITIVE, "pass count_scale=0.1 (as uq=native), or null for the model's own counts")},
    "process": {**{k: (lambda v: is_int(v, 16), "a size in pixels, an integer >= 16", f"pass {k}=1600")
                   for k in ("max_side", "sift_max_side")},
                "min_registered": (lambda v: is_number(v) and 0 <= v <= 1, "a share of the photos, in [0, 1]",
                                   "pass min_registered=0.5"),
                "fps": (lambda v: is_number(v) and 0 < v <= 120, "a frame rate in (0, 120]", "pass fps=2"),
                **{k: (*_BOOL, f"pass {k.rstrip('?')}=true or false")
                   for k in ("single_camera?", "overwrite", "verbose", "scene_file")}},
    "report": {"on_duplicate": (lambda v: v in ("error", "newest"), "error or newest", "pass on_duplicate=newest"),
               "time_fractions": (lambda v: all(is_number(f) and 0 < f <= 1 for f in v), "fractions in (0, 1]",
                                  "pass time_fractions=[0.95,0.99]"),
               "bootstrap.confidence": (lambda v: is_number(v) and 0 < v < 1, "in (0, 1)", "pass bootstrap.confidence=0.95"),
               **{f"bootstrap.{k}": (lambda v: is_int(v, 1), "an integer >= 1", f"pass bootstrap.{k}={d}")
                  for k, d in (("n_resamples", 9999), ("bca_min_n", 6))}},
}


def _check_posterior_list(cfg: DictConfig) -> None:
    """``posterior=[niw,niw]`` composes to one block: refuse the duplicate (seen in Hydra's overrides)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides([str(o) for o in hydra_value(cfg, "overrides.task", []) or []])
    except Exception:  # noqa: BLE001 - Hydra parsed them already to compose this config
        return
    for o in parsed:
        items = o.value() if o.key_or_group == "posterior" and o.value_type is not None else None
        dup = sorted({str(x) for x in items if items.count(x) > 1}) if isinstance(items, list) else []
        if dup:
            raise B3dgsError(f"posterior=[{','.join(map(str, items))}] lists {', '.join(dup)} more than once",
                             f"list each block once, e.g. posterior=[{','.join(dict.fromkeys(map(str, items)))}]")


def _check_resume(cfg: DictConfig, resume: Any) -> None:
    from b3dgs.rundir import resolve_resume

    root = value(cfg.trainer, "default_root_dir", "trainer.default_root_dir") if resume in ("auto", True) else ""
    ckpt = None if root is UNRESOLVED else resolve_resume(resume, Path(str(root)))
    if ckpt is not None:
        check_checkpoint(ckpt, "pass resume=null to start afresh, or resume=PATH to an intact .ckpt (e.g. an earlier "
                               "stepN.ckpt)")


def _check_eval(cfg: DictConfig, values: dict) -> dict:
    runs = value(cfg, "run", "run")
    runs = runs if isinstance(runs, list) else [runs]
    if not runs:
        raise B3dgsError("run=[] names no run dir", "pass run=RUN_DIR or run=[A,B,C]")
    out = cfg.get("out")
    if out is not None and Path(str(out)).exists() and not Path(str(out)).is_dir():
        raise B3dgsError(f"out={out} is a file", "pass out=PATH to a folder (uq.json and the plots go there)")
    data_keys = known_keys("data", "eval")  # data.path: the runs' scene folder on this machine
    for key in map(str, cfg.get("data") or {}):
        if key not in data_keys:
            raise B3dgsError(f"unknown config key data.{key}{did_you_mean(key, data_keys)}",
                             f"remove it (b3dgs-eval reads the run's own data settings; it takes only "
                             f"{', '.join('data.' + k for k in data_keys)})")
    uq = cfg.get("uq")
    if not isinstance(uq, DictConfig) or not any(isinstance(uq[k], DictConfig) for k in uq.keys()):
        raise B3dgsError("no uncertainty regime selected", f"pass uq=[native,proxy] (options: {', '.join(option_names('uq'))})")
    values["uq.samples"] = value(uq, "samples", "uq.samples") if "samples" in uq else 2
    regimes = _blocks(cfg, "uq", "an uncertainty regime", values)
    apply_rules(values)
    for path, node in regimes:
        members = int(node.get("min_members") or 0)
        if len(runs) < members:
            raise B3dgsError(f"uq={path[3:]} needs >= {members} run dirs, got {len(runs)}",
                             "pass run=[RUN_S0,RUN_S1,RUN_S2] (seeded runs of one scene and model)")
    built = _validate_plugins(regimes, max_steps=0)
    seen: dict[Path, str] = {}
    for r in runs:
        if Path(str(r)).resolve() in seen:  # one model twice is no ensemble: zero spread between "members"
            raise B3dgsError(f"run= names the run {r} twice ({seen[Path(str(r)).resolve()]} and {r})",
                             "pass each run dir once (an ensemble needs distinct runs, e.g. seeds)")
        seen[Path(str(r)).resolve()] = str(r)
    for d in map(Path, map(str, runs)):
        if not (d / "config.yaml").is_file():
            raise not_a_run_dir(d)
        check_checkpoint(d / "checkpoints" / "last.ckpt",
                         f"finish the run with `b3dgs-train ... hydra.run.dir={d} resume=auto`, or train it again")
    return {path[len("uq."):]: regime for path, regime in built.items()}


def validate_config(cfg: DictConfig, app: str = "train") -> dict:
    """Check every value of a composed ``b3dgs-train`` (``app="train"``), ``b3dgs-eval`` or other app's (render,
    export, view, process, report: :data:`APP_RULES`) config, once, at the app's entry: each plugin
    (strategy, schedule, posterior block, UQ regime) is built and validated here and nowhere else (a train config's
    plugins are returned by path, ``strategy``, ``schedule``, ``posterior.<name>``: :class:`b3dgs.lifecycle.Run` builds
    its model from them; an eval config's regimes by name, which ``b3dgs-eval`` fits).

    Raises :class:`~b3dgs.errors.B3dgsError` naming the first problem and its fix; reads no images.
    """
    values: dict[str, Any] = {}
    _check_top(cfg, app, values)
    if app in APP_RULES:
        for key in (k for k in map(str, cfg.keys()) if k not in ("hydra", "b3dgs") and isinstance(cfg.get(k), DictConfig)):
            values.update({f"{key}.{k}": v for k, v in value(cfg, key, key).items()})  # e.g. bootstrap.confidence
        apply_rules(values, {**RULES, **APP_RULES[app]})
        return {}
    if app == "eval":
        return _check_eval(cfg, values)
    _check_posterior_list(cfg)
    plugins = _check_train(cfg, values)
    _check_resume(cfg, values.get("resume"))
    return plugins

"""Every older on-disk format b3dgs still reads, converted into the current one: one function per format, listed in
:data:`UPGRADES` (format -> function); no other module carries a conversion of its own (``tests/test_upgrade.py``
has one test per format). It imports nothing of b3dgs but ``conf_dir``, so every reader can call it; its functions
take what was read and return the current form.

Tolerated where read rather than converted (a missing record skips a check): a checkpoint without a renderer identity
or content digest, a ``uq.json`` entry without ``run_checkpoints``, a b3dgs-eval staging folder without host and pid,
a config without a ``schedule`` node in a method label. Refused in one line: a relative ``data.path`` in
``config.yaml`` (``b3dgs.runs``), the acquisition settings' flat form (``b3dgs.study.active.load_policy``).
"""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Callable, Iterable, Mapping, Optional

from omegaconf import OmegaConf

from b3dgs import conf_dir

__all__ = ["CONSTANT_SCHEDULE", "FAMILY_POSTERIOR_UNRECORDED", "RENAMED_TARGETS", "RENDER_PATHS", "RUN_DEFAULTS",
           "UPGRADES", "V1_PATTERNS", "manifest_run_id", "manifest_v1_files", "old_temp_target", "omit_run_defaults",
           "omit_study_defaults", "posterior_pass_s", "premanifest_files", "protocol_from_meta", "renderer_option",
           "schedule_node", "trainer_arg", "uq_panels", "upgrade_targets"]


# ------------------------------------------------------------------ config.yaml and checkpoint identities
#: Class-path prefixes renamed since a run was written: (old, new). Plugins were the top-level package
#: ``plugins`` until they were installed as ``b3dgs_plugins`` (a name that cannot clash with another project's).
RENAMED_TARGETS = (("plugins.", "b3dgs_plugins."),)


def upgrade_targets(node: Any) -> Any:
    """``_target_`` class paths before the install rename (c2b61e1: ``plugins.*`` became ``b3dgs_plugins.*``), in a
    plain config or checkpoint identity (dicts, lists): renamed by :data:`RENAMED_TARGETS`."""
    if isinstance(node, list):
        return [upgrade_targets(v) for v in node]
    if not isinstance(node, Mapping):
        return node
    out = {k: upgrade_targets(v) for k, v in node.items()}
    target = out.get("_target_")
    for old, new in RENAMED_TARGETS:
        if isinstance(target, str) and target.startswith(old):
            out["_target_"] = new + target[len(old):]
    return out


def renderer_option(node: Any) -> Optional[str]:
    """``config.yaml``'s ``renderer`` node before renderers were plugins (00f6cdc): none (``auto``), a bare option
    name, or ``{backend: cpu|torch}``: the ``renderer=`` option it names; ``None`` for a current node (a ``_target_``)."""
    if node is None or isinstance(node, str):
        return node or "auto"
    if "_target_" in node:
        return None
    return str(node.get("backend", "auto"))


#: trainer keys of run dirs written before the trainer node was a ``lightning.Trainer`` target (ab57b0a)
_OLD_TRAINER_KEYS = {"progress_bar": "enable_progress_bar", "log_every": "log_every_n_steps"}


def trainer_arg(key: str) -> str:
    """``config.yaml``'s ``trainer`` keys before the node was a ``lightning.Trainer`` target (ab57b0a):
    ``progress_bar`` and ``log_every``, renamed to Lightning's argument; other keys unchanged."""
    return _OLD_TRAINER_KEYS.get(key, key)


#: the schedule of configs and checkpoint identities written before training schedules existed (16ebca2): they all
#: trained at a constant resolution
CONSTANT_SCHEDULE = {"_target_": "b3dgs.schedule.ConstantSchedule"}


def schedule_node(node: Any) -> Any:
    """``config.yaml`` or a checkpoint identity without a ``schedule`` (before 16ebca2): the constant schedule's node
    (:data:`CONSTANT_SCHEDULE`, a copy); a node that is there, unchanged."""
    return dict(CONSTANT_SCHEDULE) if node is None else node


# ------------------------------------------------------------------ protocols: settings older writers did not record
#: settings runs written before they were configurable did not record: left out of a protocol at these values
RUN_DEFAULTS = {"trainer.precision": "32-true", "trainer.deterministic": False, "data.test_split": "interleaved",
                "data.test_fraction": 0.125, "data.sector_axis": 0, "data.images_dir": None,
                "data.undistort": None,
                # a field the config files did not list before they were filled from the dataclass (issue 53 §3)
                "posterior.niw.mse_ema": 0.99,
                # the pair sums' cadence (issue 51 §2), every step in every run before it was a setting
                "posterior.dp.pair_sums_every": 1, "posterior.color.pair_sums_every": 1}


def omit_run_defaults(settings: Mapping[str, Any]) -> dict[str, Any]:
    """A run protocol (flattened ``config.yaml`` settings) comparable with runs written before ``trainer.precision``,
    ``trainer.deterministic`` and ``data.test_split``/``test_fraction``/``sector_axis`` (ab57b0a) or
    ``data.images_dir`` (bfb7523) or ``data.undistort`` were settings, or before a plugin's config node held every field
    of its class (``posterior.niw.mse_ema``) or the pair sums had a cadence: those keys left out at the values such runs used (:data:`RUN_DEFAULTS`)."""
    return {k: v for k, v in settings.items() if not (k in RUN_DEFAULTS and v == RUN_DEFAULTS[k])}


#: the posterior blocks each family's model had in every study folder written before ``family_posterior`` (which
#: did not record them): left out of protocol.json at these values, so those folders stay valid, and a folder of
#: one posterior refuses rows of another (e.g. after a change of conf/model/niw.yaml's default blocks)
#: (conf/experiment/archived_posterior.yaml, the pins of the committed campaigns)
FAMILY_POSTERIOR_UNRECORDED: dict = {
    k: list(v) for k, v in OmegaConf.load(Path(conf_dir()) / "experiment" / "archived_posterior.yaml")
    .family_posterior.items()}


def omit_study_defaults(settings: dict[str, Any], family_posteriors: Optional[Mapping] = None) -> dict[str, Any]:
    """An active study's ``protocol.json`` settings comparable with folders written before batch options (5daa7cb)
    and ``family_posterior`` (b529740): ``acquisition.batch_settings`` left out when empty, and
    ``family_posterior.<family>`` (the blocks of each family's model as composed) added only where they differ from
    :data:`FAMILY_POSTERIOR_UNRECORDED`. Changes and returns ``settings``."""
    if settings.get("acquisition.batch_settings") == {}:
        del settings["acquisition.batch_settings"]
    for fam, blocks in sorted((family_posteriors or {}).items()):
        if list(blocks) != FAMILY_POSTERIOR_UNRECORDED.get(fam):
            settings[f"family_posterior.{fam}"] = list(blocks)
    return settings


def protocol_from_meta(meta: Mapping) -> dict:
    """An active study's scene folder before ``protocol.json`` (9ef1d55): the settings its ``meta.json`` records
    (``acquire``, ``total_steps``, ``variant``, ``score_max_side``, a standard variant's initial view count) under
    their protocol keys, compared on the keys it has (``None``: not recorded)."""
    legacy = {"acquire": meta.get("acquire"), "trainer.max_steps": meta.get("total_steps"),
              "variant": meta.get("variant"), "acquisition.score_max_side": meta.get("score_max_side")}
    if meta.get("variant") == "standard" and isinstance(meta.get("initial_views"), list):
        legacy["initial_views"] = len(meta["initial_views"])
    return legacy


# ------------------------------------------------------------------ metrics.json and uq.json
def posterior_pass_s(metrics: Mapping) -> float:
    """``metrics.json`` before the blocks' pass over the training views was timed (bb449df): ``posterior_pass_s``
    0 (no pass was timed); a recorded value as it is (non-positive or not a number: 0)."""
    ps = metrics.get("posterior_pass_s")
    return float(ps) if isinstance(ps, (int, float)) and ps > 0 else 0.0


def uq_panels(name: str, entry: Mapping, meta: Mapping) -> list[str]:
    """A ``uq.json`` regime's panel files: its entry's ``panels``, or (files written before entries listed them,
    7a1e6d8) ``uq/<regime>_<view>.png`` for each view of the file's ``_meta``."""
    if isinstance(entry.get("panels"), list):
        return [str(p) for p in entry["panels"]]
    return [f"uq/{name}_{Path(str(v)).stem}.png" for v in meta.get("views") or []]


# ------------------------------------------------------------------ run manifests (.b3dgs-run.json)
#: what a format-1 manifest of b3dgs-train listed by a fixed name (the current ``b3dgs.rundir.TRAIN_FILES`` then)
_V1_TRAIN_FILES = ("config.yaml", ".hydra/config.yaml", ".hydra/hydra.yaml", ".hydra/overrides.yaml", "metrics.json",
                   "curve.json", "curve.png", "point_cloud.ply", "checkpoints/last.ckpt")
#: the patterns a format-1 manifest listed for b3dgs-train and b3dgs-eval (and what a run dir written before
#: manifests is read with), besides its job log, the renders of metrics.json's views and the panels of uq.json
V1_PATTERNS = (*_V1_TRAIN_FILES, "checkpoints/step[0-9]*.ckpt", "tb/events.out.tfevents.*", "tb/hparams.yaml",
               "train.log", "uq.json", ".uq.json.lock", "uq/sparsification.png", "uq/reliability.png",
               "tb_uq/events.out.tfevents.*")
#: b3dgs-render's camera paths while manifests were of format 1 (its video was ``<path>.mp4``): the names a format-1
#: ``*.mp4`` pattern stands for (later paths, ``orbit`` or a path file, are listed by name in format 2)
RENDER_PATHS = ("test", "train", "interpolate")
#: a format-1 pattern's wildcard component -> the names its writer gives files (a pattern matches nothing else: a
#: user's ``render/test/my_cut.mp4`` or ``frame_final_edit.png`` is never one of ours); other wildcards match nothing
_V1_NAMES = {"step[0-9]*.ckpt": r"step\d+\.ckpt", "frame_[0-9]*.png": r"frame_\d{5,}\.png",
             "events.out.tfevents.*": r"events\.out\.tfevents\.\d{10,}\..+\.\d+\.\d+",
             "*.mp4": rf"(?:{'|'.join(RENDER_PATHS)})\.mp4"}
_GLOB = re.compile(r"[*?\[]")


def _v1_matches(rel: str, pattern: str) -> bool:
    """Whether a format-1 ``pattern`` names the file ``rel``: component by component, a literal one equal, a
    wildcard one only as :data:`_V1_NAMES` says its writer names files."""
    def part(x: str, y: str) -> bool:
        return x == y if not _GLOB.search(y) else y in _V1_NAMES and re.fullmatch(_V1_NAMES[y], x) is not None

    a, b = rel.split("/"), pattern.split("/")
    return len(a) == len(b) and all(map(part, a, b))


def _uq_outputs(uq: Mapping) -> list[str]:
    """The panels of the regimes of a ``uq.json`` (:func:`uq_panels`)."""
    meta = uq.get("_meta") or {}
    return [p for name, entry in uq.items() if not name.startswith("_") and isinstance(entry, dict)
            for p in uq_panels(name, entry, meta)]


def manifest_v1_files(files: Iterable[str], patterns: Iterable[str], metrics: Optional[Mapping] = None,
                      uq: Optional[Mapping] = None) -> list[str]:
    """A run manifest of format 1 (before aff6d34, issue 46) listed ``writes`` patterns; format 2 lists ``files`` by
    name. Of the run dir's ``files`` (posix paths relative to it, in the order given), those the ``patterns`` name
    (:func:`_v1_matches`), with the renders of the views in ``metrics`` (its metrics.json) and the panels of ``uq``
    (its uq.json), which such a manifest did not list."""
    patterns = [str(p) for p in patterns]
    per_view = (metrics or {}).get("per_view") or []
    exact = {f"renders/{Path(str(v.get('name'))).stem}.png" for v in per_view if isinstance(v, dict) and v.get("name")}
    exact |= set(_uq_outputs(uq or {}))
    return [f for f in files if f in exact or any(_v1_matches(f, p) for p in patterns)]


def premanifest_files(files: Iterable[str], metrics: Optional[Mapping] = None,
                      uq: Optional[Mapping] = None) -> list[str]:
    """A run dir written before run manifests (a b3dgs ``config.yaml`` with its outputs; ``b3dgs.rundir.is_legacy_run``
    tells one): the files a format-1 manifest of b3dgs-train and b3dgs-eval would list (:data:`V1_PATTERNS`)."""
    return manifest_v1_files(files, V1_PATTERNS, metrics, uq)


def manifest_run_id(m: Mapping) -> str:
    """A run manifest's run identity: its ``run_id``, or (format 1 had none) ``created <its creation time>``."""
    return m.get("run_id") or f"created {m.get('created')}"


# ------------------------------------------------------------------ temp files of atomic writes
_TEMP_BEFORE = re.compile(r"^\.(?P<name>.+)\.[a-z0-9_]{8}\.tmp$")


def old_temp_target(name: str) -> Optional[str]:
    """A temp file of ``b3dgs.io.atomic_path`` before its names carried ``b3dgs.io.TEMP_MARK`` (0467be2):
    ``.<name>.<8 random characters of mkstemp>.tmp`` -> the ``<name>`` it was written for; ``None`` for any other
    name (a user's ``.notes.tmp``)."""
    m = _TEMP_BEFORE.match(name)
    return None if m is None else m.group("name")


#: every older format b3dgs reads -> the function that gives its current form (tests/test_upgrade.py: one test each)
UPGRADES: dict[str, Callable] = {
    "config/checkpoint _target_ plugins.* (before c2b61e1)": upgrade_targets,
    "config renderer {backend: ...} (before 00f6cdc)": renderer_option,
    "config trainer progress_bar/log_every (before ab57b0a)": trainer_arg,
    "config/checkpoint without schedule (before 16ebca2)": schedule_node,
    "config without precision/deterministic/test split keys (before ab57b0a)": omit_run_defaults,
    "study protocol.json without batch_settings/family_posterior (before 5daa7cb/b529740)": omit_study_defaults,
    "study folder with meta.json only (before 9ef1d55)": protocol_from_meta,
    "metrics.json without posterior_pass_s (before bb449df)": posterior_pass_s,
    "uq.json entry without panels (before 7a1e6d8)": uq_panels,
    ".b3dgs-run.json format 1: writes patterns (before aff6d34)": manifest_v1_files,
    ".b3dgs-run.json format 1: no run_id (before aff6d34)": manifest_run_id,
    "run dir without a manifest": premanifest_files,
    "atomic temp file .<name>.<random>.tmp (before 0467be2)": old_temp_target,
}

"""A run dir that one process owns: its lock, its deferred job log and ``.hydra/``, stale temp files.

* :func:`run_dir_lock`: an exclusive lock on ``<run dir>/.b3dgs.lock`` (:mod:`b3dgs.locks`), taken before anything
  else is written; the kernel drops it when its holder dies, so a lock file left behind is stale by construction.
* :class:`DeferredFileHandler`: Hydra's job log, held in memory until :func:`arm_run_log` (a refused run writes none).
* The run manifest ``.b3dgs-run.json`` (:func:`write_manifest`): what marks a folder as a b3dgs run dir, its run's
  identity and every file b3dgs wrote there, by name (listed before it is written, :func:`record_written`), so that
  ``overwrite=true`` removes exactly those (:func:`remove_run_files`); a non-empty folder without one is someone
  else's (:func:`run_dir_kind`).
* :func:`prepare_run_dir` decides whether a training may use a run dir (continue, replace or start) before anything
  is written; :func:`claim_run_dir` then takes it, the manifest first.
"""
from __future__ import annotations

import fnmatch
import logging
import os
import re
import time
import uuid
from contextlib import ExitStack, contextmanager, suppress
from itertools import islice
from pathlib import Path
from typing import Callable, Iterable, Iterator, Optional

from b3dgs.errors import B3dgsError
from b3dgs.io import atomic_path, read_json_dict, write_json
from b3dgs.locks import LockHeld, lock_holder, pid_alive, process_lock
from b3dgs.upgrade import manifest_run_id, manifest_v1_files, old_temp_target, premanifest_files

log = logging.getLogger(__name__)

LOCK_NAME = ".b3dgs.lock"


def not_a_run_dir(path: Path, key: str = "run") -> B3dgsError:
    """The refusal of a folder without ``config.yaml`` given as ``key=``: a folder of run dirs (a sweep, outputs/train)
    names them and the one to pass; any other says what a run dir is."""
    path = Path(path)
    runs: list[Path] = []
    if path.is_dir():
        for depth in ("*", "*/*"):  # a sweep's or outputs/train's runs; outputs/ holds train/<run>
            runs = sorted(d.parent for d in path.glob(f"{depth}/config.yaml") if (d.parent / "metrics.json").is_file())
            if runs:
                break
    if runs:
        listed = ", ".join(str(r.relative_to(path)) for r in runs[:4]) + (", ..." if len(runs) > 4 else "")
        return B3dgsError(f"{key}={path} holds {len(runs)} finished run dir{'s' * (len(runs) > 1)} ({listed}), not a run",
                          f"pass one of them, e.g. {key}={runs[-1]}")
    return B3dgsError(f"no run dir at {path}" if not path.exists() else f"{path} is not a b3dgs run dir (no config.yaml)",
                      f"pass {key}=DIR of a finished b3dgs-train run (outputs/train/...)")


@contextmanager
def run_dir_lock(run_dir: Path, prog: str = "b3dgs-train") -> Iterator[None]:
    """Hold ``run_dir``'s lock for the block; refuse (one line) if another live process holds it.

    An empty run dir left by a refused run is removed on the way out."""
    with _folder_lock(Path(run_dir), LOCK_NAME, f"the run dir {run_dir}", prog, "hydra.run.dir"):
        yield


@contextmanager
def out_dir_lock(out: Path, prog: str) -> Iterator[None]:
    """Hold ``prog``'s lock on an ``out=`` folder outside a run dir (``.<prog>.lock``) while it writes there, so
    that two of its jobs into one folder cannot mix their files; the second is refused in one line."""
    with _folder_lock(Path(out), f".{prog}.lock", f"out={out}", prog, "out"):
        yield


@contextmanager
def _folder_lock(folder: Path, lock_name: str, what: str, prog: str, key: str) -> Iterator[None]:
    """:func:`run_dir_lock` and :func:`out_dir_lock`: create ``folder``, hold the lock file ``lock_name`` in it, and
    remove the folder on the way out if it is left empty (a refused first run)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise B3dgsError(f"{what} is a file (or lies below one)", f"pass {key}=PATH to a folder") from None
    except PermissionError:
        raise B3dgsError(f"cannot create {what}: permission denied", f"pass {key}=PATH to a writable folder") from None
    held = ExitStack()
    try:
        held.enter_context(process_lock(folder / lock_name, wait=False, remove=True))
    except PermissionError:
        raise B3dgsError(f"{what} is not writable", f"pass {key}=PATH to a writable folder") from None
    except LockHeld as e:
        raise B3dgsError(f"{what} is in use by another {prog} (pid {e.pid})",
                         f"wait for it to finish, or pass another {key}") from None
    try:
        with held:
            yield
    finally:
        with suppress(OSError):
            folder.rmdir()  # only if nothing was left (a refused run in a new folder)


#: a temp file of :func:`b3dgs.io.atomic_path`: ``.<name>.b3dgs-<random>.tmp`` (an older writer's:
#: :func:`b3dgs.upgrade.old_temp_target`, removed only where ``<name>`` is a file the manifest lists)
_TEMP_NOW = re.compile(r"^\.(?P<name>.+)\.b3dgs-[A-Za-z0-9_]{8}\.tmp$")


def remove_stale_tmp(run_dir: Path) -> list[Path]:
    """Remove the temp files that a killed b3dgs writer left in ``run_dir`` and its sub-folders, and nothing else:
    a user's own ``.notes.tmp`` stays (only :func:`b3dgs.io.atomic_path`'s names, or an older writer's temp of a
    file the manifest lists)."""
    run_dir = Path(run_dir)
    listed = None
    gone = []
    for p in sorted(run_dir.rglob(".*.tmp")):
        if not p.is_file() or p.is_symlink():
            continue
        if _TEMP_NOW.match(p.name) is None:
            target = old_temp_target(p.name)
            if target is None:
                continue
            if listed is None:
                try:
                    listed = set(_listed(run_dir, read_manifest(run_dir)))
                except B3dgsError:  # a damaged manifest: leave older-named temps alone
                    listed = set()
            if (p.parent / target).relative_to(run_dir).as_posix() not in listed:
                continue
        p.unlink()
        gone.append(p)
    return gone


#: b3dgs-eval stages its panels in ``<folder>/.uq-staging.<host>.<pid>.<random>`` until it publishes them
STAGING_PREFIX = ".uq-staging."


def staging_prefix() -> str:
    """The staging-folder prefix of this process (host and pid, so a later process can tell a killed eval's folder)."""
    import socket

    return f"{STAGING_PREFIX}{socket.gethostname()}.{os.getpid()}."


def remove_stale_staging(folder: Path, owned: bool = False) -> list[Path]:
    """Remove the staging folders a killed b3dgs-eval left in ``folder``: those of this host whose process is gone.
    ``owned`` (the caller holds the run dir, e.g. ``overwrite=true``): also those with no host and pid in their name
    (written before the name carried them). Folders of live evals and of other hosts stay."""
    import shutil
    import socket

    gone = []
    host = socket.gethostname()
    for p in Path(folder).glob(f"{STAGING_PREFIX}*"):
        if not p.is_dir() or p.is_symlink():
            continue
        parts = p.name[len(STAGING_PREFIX):].rsplit(".", 2)
        named = len(parts) == 3 and parts[1].isdigit()  # host and pid in the name
        if (parts[0] == host and not pid_alive(int(parts[1]))) if named else owned:
            shutil.rmtree(p, ignore_errors=True)
            gone.append(p)
    return gone


def run_dir_busy(run_dir: Path) -> Optional[str]:
    """The pid of the live process that holds ``run_dir``'s lock (a training in progress), else ``None``."""
    return lock_holder(Path(run_dir) / LOCK_NAME)


# ------------------------------------------------------------------------------------------ run manifest
MANIFEST_NAME = ".b3dgs-run.json"
#: the manifest's format: 2 lists the files by name (``files``); 1 (before issue 46) listed patterns (``writes``)
MANIFEST_FORMAT = 2
#: what b3dgs-train writes into its run dir by a fixed name, listed when the run starts (before any is written); the
#: others join as they are written: its job log, ``renders/<test view>.png``, ``checkpoints/step<N>.ckpt`` and its
#: logger's files (:class:`b3dgs.callbacks.RunFiles`)
TRAIN_FILES = ("config.yaml", ".hydra/config.yaml", ".hydra/hydra.yaml", ".hydra/overrides.yaml", "metrics.json",
               "curve.json", "curve.png", "point_cloud.ply", "checkpoints/last.ckpt")
#: the frames b3dgs-render writes: ``frame_<5 digits>.png``
FRAME_NAME = re.compile(r"frame_\d{5,}\.png")


def _iter_files(root: Path) -> Iterator[str]:
    """Every file below ``root`` (symlinks included, not followed) as a posix path relative to it."""
    for d, dirs, files in os.walk(root):
        dirs.sort()
        base = Path(d).relative_to(root)
        yield from ((base / f).as_posix() for f in sorted(files))
        yield from ((base / x).as_posix() for x in dirs if (Path(d) / x).is_symlink())


def _matches(rel: str, pattern: str) -> bool:
    a, b = rel.split("/"), pattern.split("/")
    return len(a) == len(b) and all(fnmatch.fnmatchcase(x, y) for x, y in zip(a, b))


def read_manifest(run_dir: Path, fix: Optional[str] = None) -> Optional[dict]:
    """The run manifest of ``run_dir`` (format 2: ``files``; format 1: ``writes``), ``None`` without one; a damaged
    one is refused in one line (``fix``: what the calling command's user can do instead; default: a training's)."""
    path = Path(run_dir) / MANIFEST_NAME
    if not path.exists() and not path.is_symlink():
        return None
    m = read_json_dict(path)
    key = "files" if m is not None and m.get("b3dgs_run") == MANIFEST_FORMAT else "writes"
    if m is None or not isinstance(m.get(key), list) or not all(isinstance(f, str) for f in m[key]):
        raise B3dgsError(f"the run manifest {path} is damaged",
                         fix or "pass another hydra.run.dir, or remove the run dir yourself (b3dgs removes only the "
                                "files its manifest lists)")
    return m


def is_legacy_run(run_dir: Path) -> bool:
    """Whether ``run_dir`` holds a run written before run manifests: a b3dgs config.yaml (data, model and seed)
    with ``metrics.json`` or ``checkpoints/last.ckpt`` beside it."""
    from omegaconf import DictConfig, OmegaConf

    run_dir = Path(run_dir)
    try:
        cfg = OmegaConf.load(run_dir / "config.yaml")
    except Exception:  # noqa: BLE001 - missing, unreadable or not YAML: not a b3dgs config
        return False
    if not isinstance(cfg, DictConfig) or not all(k in cfg for k in ("data", "model", "seed")):
        return False
    return finished_metrics(run_dir) is not None or (run_dir / "checkpoints" / "last.ckpt").is_file()


def run_dir_kind(run_dir: Path) -> str:
    """``empty`` (nothing but the lock), ``run`` (a manifest), ``legacy`` (:func:`is_legacy_run`) or ``foreign``
    (files b3dgs did not write, and no run of its own)."""
    run_dir = Path(run_dir)
    if read_manifest(run_dir) is not None:
        return "run"
    if not foreign_files(run_dir, limit=1):
        return "empty"
    return "legacy" if is_legacy_run(run_dir) else "foreign"


def foreign_files(run_dir: Path, limit: Optional[int] = None) -> list[str]:
    """The files of a folder without a manifest (its lock file aside): the first ``limit`` found, sorted (a
    folder such as a home directory is not walked to its end)."""
    if not Path(run_dir).is_dir():
        return []
    return sorted(islice((f for f in _iter_files(Path(run_dir)) if f != LOCK_NAME), limit))


def _listed(run_dir: Path, m: Optional[dict]) -> list[str]:
    """The files a manifest ``m`` lists (a format-1 one: the files its patterns name,
    :func:`b3dgs.upgrade.manifest_v1_files`); for a run dir written before manifests (``m`` None), those of
    :func:`b3dgs.upgrade.premanifest_files`."""
    if m is not None and m.get("b3dgs_run") == MANIFEST_FORMAT:
        return list(dict.fromkeys(m["files"]))
    if m is None and not is_legacy_run(run_dir):
        return []
    files, metrics = _iter_files(run_dir), read_json_dict(run_dir / "metrics.json")
    uq = read_json_dict(run_dir / "uq.json")
    return premanifest_files(files, metrics, uq) if m is None else manifest_v1_files(files, m["writes"], metrics, uq)


def manifest_token(m: Optional[dict]) -> Optional[str]:
    """The identity of the run a manifest belongs to: its ``run_id``, new for every run that starts afresh (a new
    run dir, ``overwrite=true``) and kept by a resume; for a format-1 manifest, its creation time."""
    return None if m is None else manifest_run_id(m)


def _job_logs(run_dir: Path) -> list[str]:
    """The job log of this process if it lies in ``run_dir`` (Hydra's ``<job name>.log``)."""
    out = []
    for h in logging.getLogger().handlers:
        if isinstance(h, logging.FileHandler):
            try:
                out.append(Path(h.baseFilename).resolve().relative_to(Path(run_dir).resolve()).as_posix())
            except ValueError:
                pass
    return out


def _write_manifest(run_dir: Path, files: Iterable[str], token: Optional[str], created: Optional[str],
                    writer: Optional[str] = None, amended: Optional[list] = None) -> None:
    """The manifest of ``run_dir``; ``writer`` marks a folder that one command wrote whole (b3dgs-export's model
    folder), not a run; ``amended``: what was added to the finished run's metrics.json later (:func:`record_amended`)."""
    write_json(Path(run_dir) / MANIFEST_NAME, {
        "b3dgs_run": MANIFEST_FORMAT, "run_id": token or uuid.uuid4().hex,
        "created": created or time.strftime("%Y-%m-%dT%H:%M:%S%z"), "files": list(dict.fromkeys(map(str, files))),
        **({"writer": writer} if writer else {}), **({"amended": amended} if amended else {})})


def record_amended(run_dir: Path, keys: Iterable[str]) -> None:
    """List in ``run_dir``'s manifest, if it has one, that the finished run's metrics.json ``keys`` were changed now
    (:meth:`b3dgs.lifecycle.Run.amend_metrics`, which holds the run dir's lock)."""
    m = read_manifest(run_dir)
    if m is not None:
        done = [*(m.get("amended") or []), {"keys": sorted(map(str, keys)), "at": time.strftime("%Y-%m-%dT%H:%M:%S%z")}]
        _write_manifest(run_dir, _listed(run_dir, m), manifest_token(m), m.get("created"), m.get("writer"), done)


def write_manifest(run_dir: Path) -> None:
    """Mark ``run_dir`` as a b3dgs run and list what its training writes by a fixed name (:data:`TRAIN_FILES`, its
    job log). Kept: the files of an earlier manifest (a format-1 one is rewritten with the files its patterns name)
    and its run's identity (:func:`manifest_token`); for a run written before manifests, the outputs
    :func:`run_files` recognises as its own."""
    run_dir = Path(run_dir)
    old = read_manifest(run_dir)
    _write_manifest(run_dir, [*_listed(run_dir, old), *TRAIN_FILES, *_job_logs(run_dir)], manifest_token(old),
                    (old or {}).get("created"), amended=(old or {}).get("amended"))


def start_manifest(folder: Path) -> None:
    """Give ``folder`` an empty run manifest if it has none (a study row's run dir, :meth:`b3dgs.lifecycle.Run.record`);
    the caller holds its lock."""
    if read_manifest(folder) is None:
        _write_manifest(folder, [], None, None)


def _bad_name(rel: str) -> bool:
    """``rel`` is no file of a run dir: absolute, with an empty, ``.`` or ``..`` part, or the manifest or the lock."""
    return rel.startswith("/") or any(p in ("", ".", "..") for p in rel.split("/")) or rel in (MANIFEST_NAME, LOCK_NAME)


def record_written(folder: Path, names: Iterable[str], forget: Iterable[str] = ()) -> None:
    """List the files ``names`` (exact paths relative to ``folder``, recorded before they are written) in its
    manifest, if it has one, and drop ``forget`` from it (callers hold :func:`manifest_lock`, or the run dir's)."""
    folder = Path(folder)
    m = read_manifest(folder)
    if m is None:
        return
    names, have, gone = list(map(str, names)), _listed(folder, m), set(map(str, forget))
    bad = [n for n in names if _bad_name(n)]
    if bad:
        raise B3dgsError(f"not a file name relative to a run dir: {bad[0]!r}", "pass its path inside the run dir")
    files = [f for f in dict.fromkeys([*have, *names]) if f not in gone]
    if files != have or m.get("b3dgs_run") != MANIFEST_FORMAT:
        _write_manifest(folder, files, manifest_token(m), m.get("created"), m.get("writer"), m.get("amended"))


@contextmanager
def manifest_lock(folder: Path, prog: str, wait_s: float = 120.0) -> Iterator[None]:
    """Hold ``folder``'s run dir lock (:func:`run_dir_lock`) for a short change of its manifest and files; another
    command holding it briefly is waited for (up to ``wait_s``), a training that holds it is refused in one line."""
    deadline = time.monotonic() + wait_s
    while True:
        try:
            with process_lock(Path(folder) / LOCK_NAME, wait=False, remove=True):
                yield
            return
        except LockHeld as e:
            if time.monotonic() >= deadline:
                raise B3dgsError(f"the run dir {folder} is in use by another process (pid {e.pid}), so {prog} cannot "
                                 "record its files in the run's manifest",
                                 "wait for it to finish (a training holds its run dir until it ends), or pass out=DIR "
                                 "outside the run dir") from None
            time.sleep(0.05)


@contextmanager
def claim_in_run(owner: Path, folder: Path, names: Iterable[str], prog: str, own: "re.Pattern",
                 check: Optional[Callable[[list[str]], None]] = None) -> Iterator[None]:
    """Make room for ``names`` in ``folder`` inside the run dir ``owner``, under its lock: the files of ``folder`` its
    manifest lists whose names ``own`` matches go and ``names`` join the manifest before they are written (``check``
    first gets those of ``names`` it does not list, to refuse files b3dgs did not write)."""
    rel = Path(folder).resolve().relative_to(Path(owner).resolve()).as_posix()
    pre, names = ("" if rel == "." else f"{rel}/"), list(names)
    with manifest_lock(owner, prog):
        listed = run_files(owner)
        if check is not None:
            check([n for n in names if pre + n not in listed])
        remove_recorded(owner, [f for f in listed if f.startswith(pre) and "/" not in f[len(pre):]
                                and own.fullmatch(f[len(pre):])])
        record_written(owner, [pre + n for n in names])
        Path(folder).mkdir(parents=True, exist_ok=True)
        yield


def run_files(run_dir: Path) -> list[str]:
    """The files of ``run_dir`` that b3dgs wrote and that are there: those its manifest lists (a format-1 manifest,
    or a run written before manifests: the files its patterns name, :mod:`b3dgs.upgrade`), sorted."""
    run_dir = Path(run_dir)
    return sorted(f for f in _listed(run_dir, read_manifest(run_dir)) if _safe_target(run_dir, f) is not None)


def _safe_target(root: Path, rel: str) -> Optional[Path]:
    """``root/rel`` if it is a file (or a link) reached through real folders of ``root``: never a path with ``..``,
    an absolute one, one through a symlinked folder, the manifest or the lock."""
    if _bad_name(str(rel)):
        return None
    parts, cur = str(rel).split("/"), Path(root)
    for p in parts[:-1]:
        cur = cur / p
        if cur.is_symlink() or not cur.is_dir():
            return None
    target = cur / parts[-1]
    return target if target.is_symlink() or target.is_file() else None


def remove_listed(folder: Path, names: Iterable[str]) -> list[str]:
    """Remove the files ``names`` (paths relative to ``folder``, through its own folders only, :func:`_safe_target`)
    and the folders below ``folder`` that this leaves empty; returns what went."""
    folder = Path(folder)
    gone = []
    for f in dict.fromkeys(map(str, names)):
        p = _safe_target(folder, f)
        if p is not None:
            p.unlink(missing_ok=True)
            gone.append(f)
    for d in sorted({p for f in gone for p in Path(f).parents if p != Path(".")}, key=lambda p: -len(p.parts)):
        q = folder / d
        if not q.is_symlink():
            with suppress(OSError):  # not empty: someone else's files are in it
                q.rmdir()
    return gone


def remove_recorded(folder: Path, names: Iterable[str]) -> list[str]:
    """Remove those of ``names`` that ``folder``'s manifest lists (:func:`remove_listed`) and drop them from it;
    returns what went (callers hold :func:`manifest_lock`)."""
    listed = set(_listed(Path(folder), read_manifest(Path(folder))))
    names = [n for n in map(str, names) if n in listed]
    gone = remove_listed(folder, names)
    record_written(folder, [], forget=names)
    return gone


def remove_run_files(run_dir: Path, keep: Iterable[str] = ()) -> list[str]:
    """Replace the run of ``run_dir`` (``overwrite=true``): remove the files its manifest lists (for a format-1
    manifest or a run written before manifests, :func:`run_files`), but ``keep`` (patterns), and the folders they
    leave empty; then start the new run's manifest (a new :func:`manifest_token`, the kept files and
    :data:`TRAIN_FILES`). Nothing else is touched. Returns what went."""
    run_dir = Path(run_dir)
    m = read_manifest(run_dir)
    if m is None and not is_legacy_run(run_dir):
        return []
    keep = list(keep)
    listed = _listed(run_dir, m)
    kept = [f for f in listed if any(_matches(f, k) for k in keep)]
    gone = remove_listed(run_dir, [f for f in listed if f not in kept])
    _write_manifest(run_dir, [*kept, *TRAIN_FILES, *_job_logs(run_dir)], None, None)
    return gone


def holds_run(folder: Path) -> bool:
    """Whether ``folder`` is a b3dgs run dir (a manifest, or a run written before manifests)."""
    folder = Path(folder)
    return (folder / MANIFEST_NAME).exists() or is_legacy_run(folder)


def owning_run_dir(path: Path) -> Optional[Path]:
    """The nearest folder above ``path`` (resolved) that holds a b3dgs run (:func:`holds_run`), else ``None``."""
    for d in Path(path).resolve().parents:
        if holds_run(d):
            return d
    return None


def refuse_in_checkpoints(path: Path, prog: str) -> None:
    """Refuse ``path`` if it is, or lies inside, a run's ``checkpoints/`` folder: b3dgs writes nothing there but
    the training's own checkpoints (an export there would replace the run's only ``last.ckpt``)."""
    p = Path(path).resolve()
    for d in (p, *p.parents):
        if d.name == "checkpoints" and holds_run(d.parent):
            raise B3dgsError(f"out={path} lies in the checkpoints/ folder of the run {d.parent}, where only its "
                             f"training writes", f"pass out= a path outside {d}")


def check_replace(path: Path, prog: str, overwrite: bool = False, fix: Optional[str] = None) -> Optional[Path]:
    """Whether ``prog`` may write the file ``path``; returns the run dir whose manifest is to list it (or ``None``).

    Refused, in one line: a path in a run's ``checkpoints/`` (:func:`refuse_in_checkpoints`) or one of a training's
    own files (:data:`TRAIN_FILES`), whatever ``overwrite``; an existing file that no run's manifest lists (a user's),
    unless ``overwrite`` (``fix`` says how to pass it)."""
    path = Path(path)
    refuse_in_checkpoints(path, prog)
    owner = owning_run_dir(path)
    rel = None
    if owner is not None:
        read_manifest(owner, fix="pass out=PATH outside the run dir")
        rel = path.resolve().relative_to(owner).as_posix()
        if rel in TRAIN_FILES or rel in (MANIFEST_NAME, LOCK_NAME):
            raise B3dgsError(f"out={path} is the run's own {rel}, which its training wrote",
                             "pass out= another path")
    if (path.exists() or path.is_symlink()) and not overwrite:
        if owner is None or rel not in run_files(owner):
            raise B3dgsError(f"out={path} exists and b3dgs did not write it ({prog} replaces only files a run's "
                             "manifest lists)", fix or "pass another out=")
    return owner


def run_dir_stamp(folder: Path) -> dict:
    """Which run ``folder`` holds now (for b3dgs-eval to tell whether it changed while it ran): its manifest's
    :func:`manifest_token` and the parameter digest of metrics.json's final checkpoint (``None`` where absent)."""
    folder = Path(folder)
    try:
        token = manifest_token(read_manifest(folder))
    except B3dgsError:
        token = "damaged"
    metrics = read_json_dict(folder / "metrics.json") or {}
    return {"run_id": token, "params_sha256": (metrics.get("checkpoint") or {}).get("params_sha256")}


# ------------------------------------------------------------------------------ job log and .hydra/
class DeferredFileHandler(logging.FileHandler):
    """Hydra's job-log file handler, holding records in memory until :func:`arm_run_log` (a refused run
    leaves no log file)."""

    def __init__(self, filename, mode: str = "a", encoding: Optional[str] = None, **kw) -> None:
        super().__init__(filename, mode=mode, encoding=encoding, delay=True)
        self._held: Optional[list[logging.LogRecord]] = []

    def emit(self, record: logging.LogRecord) -> None:
        if self._held is not None:
            if len(self._held) < 10000:
                self._held.append(record)
            return
        super().emit(record)

    def arm(self, fresh: bool = False) -> None:
        held, self._held = self._held or [], None
        if fresh:
            self.mode = "w"  # overwrite=true: the replaced run's log goes too
        for r in held:
            super().emit(r)


def arm_run_log(fresh: bool = False) -> None:
    """Start writing the job log (with what was logged so far); ``fresh``: replace an old log, not append."""
    for h in logging.getLogger().handlers:
        if isinstance(h, DeferredFileHandler):
            h.arm(fresh)


def write_hydra_files(run_dir: Path, cfg) -> None:
    """Hydra's ``.hydra/{config,hydra,overrides}.yaml`` for this job, written once the run is accepted
    (:func:`claim_run_dir`)."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf, open_dict

    if not HydraConfig.initialized():
        return
    hc = HydraConfig.instance().cfg
    out = Path(run_dir) / ".hydra"
    out.mkdir(parents=True, exist_ok=True)
    task = cfg.copy()
    with open_dict(task):
        task.pop("hydra", None)
    for name, node in (("config.yaml", task), ("hydra.yaml", hc), ("overrides.yaml", hc.hydra.overrides.task)):
        with atomic_path(out / name) as tmp:
            tmp.write_text(OmegaConf.to_yaml(node))


# -------------------------------------------------------------------------- resume, overwrite, the claim
#: what marks a b3dgs run dir (one with a run manifest) as holding a run
RUN_MARKERS = ("config.yaml", "checkpoints/last.ckpt", "metrics.json")
#: what ``overwrite=true`` leaves of the replaced run: the new run rewrites Hydra's ``.hydra/`` and its job log
RUN_OUTPUTS_KEPT = (".hydra/*", "*.log")


def _resuming(resume) -> bool:
    return resume not in (None, False, "null", "")


def resolve_resume(resume, run_dir: Path) -> Optional[str]:
    """The checkpoint ``resume`` names: the run dir's ``last.ckpt`` for ``auto`` (``None`` without one), else the
    path given."""
    if not _resuming(resume):
        return None
    if resume in ("auto", True):
        last = Path(run_dir) / "checkpoints" / "last.ckpt"
        return str(last) if last.exists() else None
    p = Path(str(resume))
    if not p.exists():
        raise B3dgsError(f"resume={resume}: no such checkpoint", "pass a .ckpt path, resume=auto or resume=null")
    return str(p)


def finished_metrics(run_dir: Path) -> Optional[dict]:
    """The complete ``metrics.json`` of a finished run in ``run_dir``, else ``None``."""
    m = read_json_dict(Path(run_dir) / "metrics.json")
    return m if m is not None and "checkpoint" in m else None


def prepare_run_dir(run_dir: Path, resume=None, overwrite=False,
                    check_checkpoint: Optional[Callable[[str], None]] = None) -> tuple[Optional[str], bool]:
    """``(checkpoint to resume from or None, whether to remove the old run's outputs first)`` for a training into
    ``run_dir`` with the config's ``resume`` and ``overwrite``; writes nothing (:func:`claim_run_dir` does).

    A run dir that holds a run (or one written before manifests, :func:`is_legacy_run`) is refused unless
    ``resume=auto`` (or one of its own checkpoints) continues it or ``overwrite=true`` replaces it; a non-empty folder
    without a manifest is someone else's, refused whatever the flags. ``check_checkpoint(path)`` vets the checkpoint to
    resume from."""
    if not isinstance(overwrite, bool):
        raise B3dgsError(f"overwrite={overwrite} is invalid: it must be true or false",
                         "pass overwrite=true to replace the run in the run dir, or leave it out")
    if overwrite and _resuming(resume):
        raise B3dgsError(f"resume={resume} and overwrite=true contradict each other",
                         "pass resume=auto to continue the run in the run dir, or overwrite=true to replace it, not both")
    run_dir = Path(run_dir)
    kind = run_dir_kind(run_dir)
    if kind == "foreign":
        files = foreign_files(run_dir, limit=5)
        raise B3dgsError(f"{run_dir} is not empty and holds no b3dgs run ({', '.join(files[:4])}"
                         f"{' and more' if len(files) > 4 else ''})", "pass hydra.run.dir=PATH to a new or empty "
                         "folder; b3dgs writes only there or into its own run dirs, and overwrite=true removes only "
                         "files a b3dgs run wrote")
    held = [n for n in RUN_MARKERS if (run_dir / n).exists()]
    if overwrite:
        return None, kind != "empty"
    ckpt = resolve_resume(resume, run_dir)
    if ckpt is not None and check_checkpoint is not None:
        check_checkpoint(ckpt)
    if not held:
        return ckpt, False
    if resume in ("auto", True):
        if finished_metrics(run_dir) is not None:
            return ckpt, False  # finished: the caller checks its identity, says so and rewrites nothing
        if ckpt is None and (run_dir / "metrics.json").exists():
            raise B3dgsError(f"{run_dir} holds a finished run but no checkpoints/last.ckpt to resume from",
                             "pass overwrite=true to train it again, or another hydra.run.dir")
        return ckpt, False
    own = (run_dir / "checkpoints").resolve()
    if ckpt is not None and Path(ckpt).resolve().parent == own:
        return ckpt, False
    raise B3dgsError(f"{run_dir} already holds a run ({', '.join(held)})",
                     "pass resume=auto to continue it, overwrite=true to replace it, or another hydra.run.dir")


def save_config(cfg, path: Path) -> None:
    """The composed config (without Hydra's own node), resolved, ``data.path`` made absolute (``b3dgs-eval``
    works from any folder), written atomically."""
    from omegaconf import OmegaConf, open_dict

    c = cfg.copy()
    with open_dict(c):
        c.pop("hydra", None)
    plain = OmegaConf.to_container(c, resolve=True)
    data = plain.get("data")
    if isinstance(data, dict) and data.get("path"):
        data["path"] = str(Path(str(data["path"])).expanduser().resolve())
    with atomic_path(path) as tmp:
        tmp.write_text(OmegaConf.to_yaml(OmegaConf.create(plain)))


def claim_run_dir(run_dir: Path, cfg, clear: bool) -> None:
    """Take ``run_dir`` for an accepted training (its lock held, every check passed): the run manifest first (with
    ``clear``, ``overwrite=true``, after removing what the old one lists), so that a kill at any later moment leaves a
    run dir that ``resume=auto`` and ``overwrite=true`` take over; then the job log, the leftovers of a kill,
    ``.hydra/`` and ``config.yaml``."""
    run_dir = Path(run_dir)
    if clear:  # the replaced run's files, exactly as its manifest lists them; then a new manifest, atomically
        log.warning("overwrite=true: removing the previous run's outputs from %s", run_dir)
        remove_run_files(run_dir, keep=RUN_OUTPUTS_KEPT)
    else:
        write_manifest(run_dir)
    arm_run_log(fresh=clear)
    if not clear and ((run_dir / "metrics.json").is_file() or (run_dir / "metrics.json").is_symlink()):
        (run_dir / "metrics.json").unlink()  # a damaged done marker comes back when this run finishes
    for p in remove_stale_tmp(run_dir):
        log.info("removed %s, a temp file left by an interrupted run", p.relative_to(run_dir))
    for p in remove_stale_staging(run_dir, owned=clear):
        log.info("removed %s, the staging folder of an interrupted b3dgs-eval", p.name)
    write_hydra_files(run_dir, cfg)
    save_config(cfg, run_dir / "config.yaml")

"""One-line errors and a quiet log for b3dgs's commands.

A known problem raises :class:`B3dgsError` ``(problem, fix)``; the console entry points print it as
``<prog>: error: <problem> (fix: <fix>)`` and exit with code 2 (the traceback only with ``HYDRA_FULL_ERROR=1`` or
``b3dgs.debug=true``). Hydra's composition errors, OmegaConf's missing values, missing files, full disks and running
out of memory are known too; anything else is a bug and keeps its traceback. :func:`quiet_known_noise` silences
known-harmless library warnings and Lightning INFO lines by name.
"""
from __future__ import annotations

import difflib
import errno
import os
import sys
import traceback
from contextlib import contextmanager
from typing import Any, Callable, Iterable, Optional

EXIT_CODE = 2
DEBUG_KEY = "b3dgs.debug"
_APP_CONFIG: Optional[str] = None  # the running CLI's primary config (run_cli), for "did you mean"
_PROG: Optional[str] = None  # the running CLI's name (run_cli), for fixes that repeat its command

__all__ = ["B3dgsError", "B3dgsTypeError", "EXIT_CODE", "did_you_mean", "format_error", "known_errors", "quiet_known_noise", "run_cli"]


class B3dgsError(ValueError):
    """A known problem with its fix; ``str()`` is ``"<problem> (fix: <fix>)"``, or the message as given when no
    ``fix`` is passed (the one-line report then adds a general one unless the message holds ``(fix: ...)``).

    The one error type of b3dgs and its plugins (``Plugin.validate`` raises it too); subclasses ``ValueError`` so
    callers that catch bad-value errors keep working.
    """

    def __init__(self, problem: str, fix: Optional[str] = None):
        self.problem = str(problem).strip()
        self.fix = None if fix is None else str(fix).strip()
        super().__init__(self.problem if fix is None else f"{self.problem} (fix: {self.fix})")


class B3dgsTypeError(B3dgsError, TypeError):
    """A :class:`B3dgsError` for an argument of the wrong type; a ``TypeError`` too, as Python's own."""


def field_default(owner: Any, name: str) -> Any:
    """The declared default of the dataclass field ``name`` of ``owner`` (a dataclass or an instance of one): what a
    fix text quotes, so that the text reads the default's one home (``e.g. the default {field_default(self, "x")}``)."""
    import dataclasses

    f = next(f for f in dataclasses.fields(owner) if f.name == name)
    return f.default if f.default_factory is dataclasses.MISSING else f.default_factory()


def check_field(owner: Any, key: str, ok: bool, rule: str, how: Optional[str] = None, note: str = "",
                got: bool = False) -> None:
    """Refuse the field ``key`` (``group.name``) of the dataclass ``owner`` unless ``ok``, in one line: ``<key> must be
    <rule>[, got <value>]`` (fix: ``pass <key> <how or rule>, e.g. the default <its default><note>``)."""
    name = key.rsplit(".", 1)[-1]
    if not ok:
        raise B3dgsError(f"{key} must be {rule}" + (f", got {getattr(owner, name)}" if got else ""),
                         fix=f"pass {key} {how or rule}, e.g. the default {field_default(owner, name)}{note}")


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """``"; did you mean X?"`` for the closest of ``choices``, else ``""``."""
    close = difflib.get_close_matches(str(word), sorted(set(map(str, choices))), n=1, cutoff=0.6)
    return f"; did you mean {close[0]}?" if close else ""


def _rerun_with_m() -> str:
    """The running command again with ``-m`` first (its name as :func:`run_cli` was given it)."""
    import shlex

    return shlex.join([_PROG or "b3dgs-train", "-m", *(a for a in sys.argv[1:] if a not in _MULTIRUN_FLAGS)])


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _key_suggestion(key: str) -> str:
    """``"; did you mean X?"`` for a misspelt dotted config key, from the keys b3dgs's config files give each node on
    its path (those of the running app's primary config, :data:`_APP_CONFIG`, at the top): the leaf when only the leaf
    is misspelt (``max_steps``), else the whole corrected key (``trainer.max_steps`` for ``traner.max_steps``)."""
    try:
        from b3dgs.confs import known_keys

        parts, fixed = str(key).split("."), []
        for part in parts:
            known = known_keys(".".join(fixed), _APP_CONFIG)
            if part not in known and known:
                close = difflib.get_close_matches(part, sorted(known), n=1, cutoff=0.6)
                if not close:
                    return ""
                part = close[0]
            fixed.append(part)
        if fixed == parts:
            return ""
        return f"; did you mean {fixed[-1] if fixed[:-1] == parts[:-1] else '.'.join(fixed)}?"
    except Exception:  # noqa: BLE001 - a suggestion must never hide the error itself
        return ""


def _parse_fix(override: Optional[str]) -> str:
    """The fix for an override Hydra cannot parse: quoting, when its value holds characters Hydra's grammar reads
    as syntax or does not read at all (spaces, non-ASCII letters, brackets, quotes); else the override forms."""
    text = str(override or "")
    key, eq, value = text.partition("=")
    def plain(text: str) -> bool:  # characters Hydra's grammar reads in an unquoted value
        return all(c.isascii() and (c.isalnum() or c in "_./:-+@*%? ") for c in text)

    if eq and key and value.startswith("~") and plain(value[1:]):  # zsh leaves ~ after = unexpanded
        return f"write the home folder out: {key}={os.path.expanduser(value)} (Hydra cannot read ~)"
    if eq and key and value and not plain(value):
        inner = value.replace("'", "\\'")
        return f"quote the value: \"{key}='{inner}'\" (the outer quotes for the shell, the inner ones for Hydra)"
    return "write overrides as key=value, group=option or +key=value"


def _hydra_error(exc: BaseException) -> Optional[B3dgsError]:
    """A one-line form of Hydra's composition errors (bad override, unknown option or key)."""
    try:
        from hydra.errors import HydraException, OverrideParseException
    except ImportError:  # pragma: no cover
        return None
    if isinstance(exc, OverrideParseException):
        return B3dgsError(f"cannot parse the override {_one_line(exc)}", _parse_fix(getattr(exc, "override", None)))
    if not isinstance(exc, HydraException):
        return None
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    cause = exc.__cause__
    if cause is not None:
        lines += [ln.strip() for ln in str(cause).splitlines() if ln.strip()]
    head = lines[0] if lines else type(exc).__name__
    text = " ".join(lines)
    if head.startswith("Ambiguous value for argument"):  # a,b,c without -m: Hydra's three readings, kept
        arg = head.split("'", 1)[1].rsplit("'", 1)[0] if "'" in head else "key=a,b"
        key, _, value = arg.partition("=")
        return B3dgsError(f"{arg} is a sweep, a list or a string", f"to sweep over it, put -m first: "
                          f"{_rerun_with_m()}; a list: '{key}=[{value}]'; a string: \"{key}='{value}'\"")
    if "Could not append" in head and "already" in text:
        key = head.split("'")[1] if "'" in head else head
        given = [a for a in sys.argv[1:] if a.lstrip("+~").partition("=")[0] == key]
        if len(given) > 1:
            return B3dgsError(f"{key} is given {len(given)} times ({' '.join(given)})", "pass it once")
        return B3dgsError(f"+{key} adds a key the config already has", f"pass {key}=VALUE without the +")
    import re

    local = re.match(r"In '([\w.-]+)/([^']+)': Could not override '([^'@]+)@\1\.", head)
    if local is not None:  # a group file's defaults list ran in the group's package: the file is not global
        group, name, target = local.groups()
        return B3dgsError(f"{group}/{name}.yaml is not a global config file: its defaults list overrides /{target} "
                          f"inside {group}.{target}, which no config has",
                          "start that file with the line '# @package _global_' (as every b3dgs scene file does)")
    if "Could not override" in head or "Could not append" in head or "not in struct" in text:
        key = head.split("'")[1] if "'" in head else head
        return B3dgsError(f"unknown config key {key}{_key_suggestion(key)}",
                          "check its spelling; `--cfg job` prints every key of the composed config")
    unloaded = re.search(r"Could not load '([\w./-]+)/([^'/]+)'", head)
    if unloaded is not None:  # a list option (uq=[nativ]): Hydra names no options; the group's files do
        from b3dgs.confs import option_names

        group, wanted = unloaded.groups()
        names = option_names(group)
        return B3dgsError(f"{group}={wanted} is not an option of {group}{did_you_mean(wanted, names)}",
                          f"pick an existing option: {' '.join(names)}" if names else "pick an existing option")
    if "Could not find" in head or "In '" in head:
        avail = [ln for ln in lines[1:] if not ln.startswith(("Config search path", "provider=", "In "))]
        opts = " ".join(avail)[:200]
        wanted, options = head.split("Could not find '")[-1].split("'")[0], " ".join(avail).partition("':")[2]
        hint = did_you_mean(wanted.rpartition("/")[2], options.split()) if "Could not find '" in head else ""
        return B3dgsError(_one_line(head) + hint, f"pick an existing option{': ' + opts if opts else ''}")
    return B3dgsError(_one_line(head), "correct the config override named above")


_IO_FIX = {
    errno.ENOSPC: ("no space left on the device", "free disk space, or pass hydra.run.dir / out= on another disk"),
    errno.EDQUOT: ("disk quota exceeded", "free disk space, or pass hydra.run.dir / out= on another disk"),
    errno.EFBIG: ("the file exceeds the file-size limit (ulimit -f) or the file system's",
                  "raise the limit, or pass hydra.run.dir / out= on another disk"),
    errno.EROFS: ("the file system is read-only", "pass hydra.run.dir / out= to a writable folder"),
    errno.EACCES: ("permission denied", "pass hydra.run.dir / out= to a folder you can write"),
    errno.EPERM: ("operation not permitted", "pass hydra.run.dir / out= to a folder you can write"),
    errno.ENOTDIR: ("a path component is a file, not a folder", "pass hydra.run.dir / out= to a folder"),
    errno.EISDIR: ("it is a folder, not a file", "pass the path of a file"),
    errno.EEXIST: ("a file is in the way of a folder", "pass hydra.run.dir / out= to a folder"),
}
_OUTPUT_KEYS = {"train": "hydra.run.dir=DIR", **{c: "out=DIR" for c in ("eval", "export", "process", "render", "report",
                                                                           "suggest")}}  # where each app writes
_TORCH_WRITE = ("file write failed", "iostream error", "unexpected pos")  # torch.save's C++ writer
_OOM = ("can't allocate memory", "out of memory", "cannot allocate memory")


def _io_error(exc: BaseException) -> Optional[str]:
    """One line for disk full, read-only or unwritable outputs, and running out of memory."""
    if isinstance(exc, MemoryError) or (isinstance(exc, RuntimeError) and any(k in str(exc).lower() for k in _OOM)):
        return ("ran out of memory (fix: lower data.max_side or data.resolution (image size) or data.max_images, "
                "or use a machine with more memory)")
    if isinstance(exc, RuntimeError) and any(k in str(exc) for k in _TORCH_WRITE):  # torch.save on a full disk
        return ("cannot write a checkpoint: the disk is full, not writable or over a file-size limit (fix: free disk "
                "space, or pass hydra.run.dir on another disk)")
    if isinstance(exc, OSError) and exc.errno in _IO_FIX:
        what, fix = _IO_FIX[exc.errno]
        fix = fix.replace("hydra.run.dir / out=", _OUTPUT_KEYS.get(_APP_CONFIG, "hydra.run.dir / out="))
        name = exc.filename if exc.filename is not None else ""
        return f"cannot write {name}: {what} (fix: {fix})" if name else f"{what} (fix: {fix})"
    return None


def format_error(exc: BaseException) -> Optional[str]:
    """``"<problem> (fix: <fix>)"`` for a known error, ``None`` for anything else (a bug)."""
    if isinstance(exc, B3dgsError):
        msg = _one_line(exc)
        return msg if "(fix:" in msg else f"{msg} (fix: correct the input named above)"
    try:
        from hydra.errors import InstantiationException
        from omegaconf.errors import MissingMandatoryValue
    except ImportError:  # pragma: no cover
        InstantiationException = MissingMandatoryValue = ()  # type: ignore
    if isinstance(exc, InstantiationException):  # a component refused its values when Hydra built it (its validate)
        return None if exc.__cause__ is None else format_error(exc.__cause__)  # anything else is a bug
    h = _hydra_error(exc)
    if h is not None:
        return _one_line(h)
    if isinstance(exc, MissingMandatoryValue):
        key = getattr(exc, "full_key", None) or "a value"
        return f"{key} is not set (fix: pass {key}=VALUE on the command line)"
    if isinstance(exc, FileNotFoundError):
        return f"{_one_line(exc)} (fix: check the path)"
    if isinstance(exc, ValueError) and str(exc).startswith("Only one of --run, --multirun"):  # Hydra's flags
        return f"{_one_line(exc)} (fix: drop all of those flags but one)"
    io = _io_error(exc)
    if io is not None:
        return io
    return None


_USER_ENV = "B3DGS_USER_HYDRA_FULL_ERROR"  # the user's HYDRA_FULL_ERROR while run_cli overrides it


def _debug_requested(argv: list[str]) -> bool:
    if os.environ.get(_USER_ENV, os.environ.get("HYDRA_FULL_ERROR", "")) not in ("", "0"):
        return True
    flags = (a.lstrip("+~").partition("=") for a in argv)
    return any(k == DEBUG_KEY and v.strip().lower() in ("true", "1", "yes", "on") for k, _, v in flags)


class ReportedError(Exception):
    """A multirun job's known error, already printed as its one line: the sweep runs the other jobs on,
    then exits with code 2."""


def _in_multirun() -> bool:
    try:
        from hydra.core.hydra_config import HydraConfig
        from hydra.types import RunMode

        return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN
    except Exception:  # noqa: BLE001
        return False


def _report(prog: str, e: BaseException) -> None:
    if isinstance(e, ReportedError):
        sys.exit(EXIT_CODE)
    msg = format_error(e)
    if msg is None:
        traceback.print_exception(e)
        sys.stderr.write(f"{prog}: unexpected error (a bug); rerun with {DEBUG_KEY}=true for the full traceback\n")
        sys.exit(1)
    sys.stderr.write(f"{prog}: error: {msg}\n")
    sys.stderr.flush()
    sys.exit(EXIT_CODE)


@contextmanager
def known_errors(prog: str, cfg=None, quiet: bool = False):
    """Inside a Hydra task: a known error becomes one line on stderr and ``SystemExit(2)`` (which Hydra
    passes on untouched); unknown errors and debug mode (``b3dgs.debug=true``) re-raise. ``quiet``: first
    :func:`quiet_known_noise`."""
    debug = _debug_requested(sys.argv[1:])
    if cfg is not None and not debug:
        try:
            debug = bool(cfg.get("b3dgs", {}).get("debug", False))
        except Exception:  # noqa: BLE001
            debug = False
    try:
        if quiet:
            quiet_known_noise()
        yield
    except Exception as e:  # noqa: BLE001
        if debug or format_error(e) is None:
            raise
        if _in_multirun():  # one job's bad value must not stop the jobs after it
            from hydra.core.hydra_config import HydraConfig

            sys.stderr.write(f"{prog}: error: job {HydraConfig.get().job.num}: {format_error(e)}\n")
            sys.stderr.flush()
            raise ReportedError(format_error(e)) from None
        _report(prog, e)


#: apps whose task checks every key of its composed config itself (b3dgs.validation.validate_config)
_VALIDATED_APPS = ("train", "eval")


def _refuse_option_clashes(prog: str) -> None:
    """One line and exit 2 when two conf roots (b3dgs's, an installed package's) give the same option: a name that
    could mean either file (:func:`b3dgs.confs.option_clashes`)."""
    from b3dgs.confs import option_clashes

    clashes = option_clashes()
    if clashes:
        name, files = clashes[0]
        _report(prog, B3dgsError(f"the config option {name} is given by {len(files)} files ({', '.join(map(str, files))}),"
                                 " so the name could mean either", f"rename one of them (e.g. {name}_mine.yaml) "
                                 "in the package that adds it"))


def _refuse_unread_additions(prog: str, argv: list[str], config: str) -> None:
    """One line and exit 2 for a ``+key=value`` override that nothing of the app reads (:func:`b3dgs.confs.
    added_key_problem`); b3dgs-train and b3dgs-eval check their composed configs instead."""
    from b3dgs.confs import added_key_problem

    for arg in argv:
        if arg.startswith("+") and "=" in arg:
            problem = added_key_problem(arg.lstrip("+").split("=", 1)[0], config, prog)
            if problem is not None:
                _report(prog, B3dgsError(*problem))


_MULTIRUN_FLAGS = ("-m", "--multirun")


def multirun_first(argv: list[str]) -> list[str]:
    """``argv`` with ``-m`` / ``--multirun`` moved before the overrides when it comes after one (``seed=0,1 -m``),
    which Hydra's argument parser refuses with its usage text; ``argv`` itself when nothing moves."""
    at = [i for i, a in enumerate(argv) if a in _MULTIRUN_FLAGS]
    if not at or not any("=" in a and not a.startswith("-") for a in argv[:at[0]]):
        return argv
    return [argv[at[0]], *(a for i, a in enumerate(argv) if i not in at)]


def run_cli(prog: str, hydra_main: Callable[[], object], argv: Optional[list[str]] = None,
            config: Optional[str] = None,
            prepare_argv: Optional[Callable[[str, list[str]], list[str]]] = None,
            again: str = "run the same command again") -> None:
    """Call a ``@hydra.main`` function (with ``HYDRA_FULL_ERROR=1``, so Hydra passes exceptions on); print known
    composition errors as one line and exit with code 2 (errors inside the task: :func:`known_errors`). ``config``: the
    app's primary config, whose keys "did you mean" suggests first; ``prepare_argv(prog, argv)``: the overrides as the
    app reads them (e.g. :func:`b3dgs.data.scene.infer_data_override`); ``again``: what to do after a SIGINT / SIGTERM,
    said in the one line it ends with."""
    global _APP_CONFIG, _PROG
    _APP_CONFIG, _PROG = config, prog
    argv = sys.argv[1:] if argv is None else argv
    moved = multirun_first(argv)
    if moved is not argv and argv == sys.argv[1:]:
        sys.argv[1:] = argv = moved
    debug = _debug_requested(argv)
    old = os.environ.get("HYDRA_FULL_ERROR")
    os.environ[_USER_ENV] = old or ""
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        _refuse_option_clashes(prog)
        if prepare_argv is not None:
            try:
                prepared = prepare_argv(prog, argv)
            except B3dgsError as e:
                _report(prog, e)
            if prepared is not argv and argv == sys.argv[1:]:
                sys.argv[1:] = argv = prepared
        if config not in (None, *_VALIDATED_APPS):
            _refuse_unread_additions(prog, argv, config)
        from b3dgs.signals import Interrupted, interrupt_handlers

        try:
            with interrupt_handlers():  # a signal unwinds finally blocks and locks (training nests its own, to save)
                hydra_main()
        except Interrupted as e:
            sys.exit(e.report(prog, again))
        except Exception as e:  # noqa: BLE001 - composition errors; task errors end in known_errors
            if debug:  # HYDRA_FULL_ERROR=1 or b3dgs.debug=true: Hydra passes the full traceback on
                raise
            _report(prog, e)
    finally:
        os.environ.pop(_USER_ENV, None)
        if old is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = old



def cli_main(prog: str, hydra_main: Callable[[], object], config: str, **kw) -> Callable[[], None]:
    """The console entry point of ``prog`` (pyproject's ``[project.scripts]``): :func:`run_cli` on ``hydra_main``."""
    def main() -> None:
        run_cli(prog, hydra_main, config=config, **kw)

    main.__doc__ = f"``{prog}``: one-line errors with exit code 2 (see :mod:`b3dgs.errors`)."
    return main

# ---------------------------------------------------------------------------------------------- quiet log

# Known-harmless library warnings (message regexes), silenced by name; any other warning still shows.
HARMLESS_WARNINGS = (
    r"You passed in a `val_dataloader` but have no `validation_step`",  # we train only; eval is ours
    r"`isinstance\(treespec, LeafSpec\)` is deprecated",  # Lightning internals vs newer torch
    r"The number of training batches \(\d+\) is smaller than the logging interval",
    r"You have overridden `transfer_batch_to_device` in `LightningModule`",  # the module's is the one meant
    r"Using ModelCheckpoint with manual optimization and every_n_train_steps",  # post-step state is intended
)
# Known-harmless Lightning INFO lines (message prefixes).
HARMLESS_INFO = ("GPU available:", "TPU available:", "HPU available:", "💡 Tip:", "`Trainer.fit` stopped: `max_steps=")


class _HarmlessInfoFilter:
    """Drops Lightning's hardware summary, its product tips and the 'max_steps reached' line."""

    def filter(self, record) -> bool:
        return not str(record.getMessage()).lstrip().startswith(HARMLESS_INFO)


def quiet_known_noise() -> None:
    """Silence known-harmless warnings and Lightning INFO lines, and stop Lightning's own console handler from printing
    every line a second time (call after Hydra has configured logging): now, or right after Lightning is imported
    (:class:`_AfterImport`, so a command that never needs Lightning does not pay seconds to import it)."""
    import logging
    import warnings

    for pattern in HARMLESS_WARNINGS:
        warnings.filterwarnings("ignore", message=pattern)
    for name in ("lightning.pytorch.utilities.rank_zero", "lightning.fabric.utilities.rank_zero"):
        lg = logging.getLogger(name)
        if not any(isinstance(f, _HarmlessInfoFilter) for f in lg.filters):
            lg.addFilter(_HarmlessInfoFilter())
    if "lightning" in sys.modules:
        _one_lightning_log()
    elif not any(isinstance(f, _AfterImport) for f in sys.meta_path):
        sys.meta_path.insert(0, _AfterImport("lightning", _one_lightning_log))


def _one_lightning_log() -> None:
    """Lightning's records go to Hydra's handlers only (once), not also to the console handler of its package."""
    import logging

    if logging.getLogger().handlers:  # Hydra's handlers print (and file) every record once
        for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
            lg = logging.getLogger(name)
            for h in list(lg.handlers):
                if type(h) is logging.StreamHandler:
                    lg.removeHandler(h)
            lg.propagate = True


class _AfterImport:
    """A finder on ``sys.meta_path`` that runs ``then()`` once, right after the module ``name`` is first imported
    (Python has no post-import hook of its own); it takes itself off the path at that import."""

    def __init__(self, name: str, then: Callable[[], None]):
        self.name, self.then = name, then

    def find_spec(self, fullname: str, path=None, target=None):
        if fullname != self.name:
            return None
        import importlib.util

        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(fullname)
        if spec is not None and spec.loader is not None:
            run, then = spec.loader.exec_module, self.then

            def exec_module(module) -> None:
                run(module)
                then()

            spec.loader.exec_module = exec_module
        return spec

"""One error convention (docs/extending.md, CONTRIBUTING.md): every error a user can cause is a
``b3dgs.errors.B3dgsError(problem, fix)``, its fix passed as ``fix=`` and not written into the message.

The test reads every ``.py`` of ``b3dgs/`` and ``plugins/`` with ``ast`` and finds

* every ``raise`` of a built-in exception class (``ValueError``, ``FileNotFoundError``, ``RuntimeError``, ...) but
  those marked ``# protocol: <which>`` where they stand (Python's protocols: an abstract method, a module's
  ``__getattr__``, json's ``default=``, an exit),
* every ``raise`` of an exception class of the package that is no ``B3dgsError``,
* every ``B3dgsError`` (or subclass) built with ``"(fix:"`` in its message text,
* every ``B3dgsError`` (or subclass) built without a fix (neither a second positional argument nor ``fix=``),

and fails unless each one is in :data:`ALLOWED` (error types of ours that are signals, not errors, with the reason)
or in :data:`PENDING` (raises in files another change is rewriting; that change converts them and deletes their lines).
A key is ``(file, exception class, a fragment of the message text)``, independent of line numbers; an entry that
matches nothing any more fails too, so the lists only shrink.
"""
from __future__ import annotations

import ast
import builtins
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROOTS = ("b3dgs", "plugins")
BUILTIN = {n for n, o in vars(builtins).items() if isinstance(o, type) and issubclass(o, BaseException)}
ROOT_ERROR = "B3dgsError"

#: error types of ours that are signals a user cannot cause: (file, exception class, message fragment) -> why
ALLOWED = {
    ("b3dgs/errors.py", "ReportedError", ""):
        "a multirun job's error, already printed as its one line; the sweep goes on and exits 2",
    ("b3dgs/locks.py", "LockHeld", ""): "internal signal; run_dir_lock turns it into a B3dgsError naming the holder",
    ("b3dgs/signals.py", "Interrupted", ""): "a signal (SIGINT/SIGTERM) stopping a run, handled by the CLI, not an input error",
    ("b3dgs/callbacks.py", "Interrupted", ""): "a signal (SIGINT/SIGTERM) stopping a run, handled by the CLI, not an input error",
    ("b3dgs/process.py", "Interrupted", ""): "a signal (SIGINT/SIGTERM) stopping b3dgs-process at a stage boundary, handled by the CLI",
    ("b3dgs/uq/store.py", "B3dgsError", "not a JSON object"):
        "internal signal, caught in the same function and re-raised as B3dgsError naming the damaged file, with its fix",
}

# ------------------------------------------------------------------------------------------------------------------
#: pending, owned by another change: raises in files being rewritten elsewhere (key: file, exception, message
#: fragment); that change converts them to B3dgsError(problem, fix=...) and deletes its lines. Empty: none pending.
PENDING: dict = {}


def _name(node: ast.AST):
    return node.id if isinstance(node, ast.Name) else node.attr if isinstance(node, ast.Attribute) else None


def _text(node) -> str:
    """The literal text of a message expression; ``{}`` for each interpolated value, "" for a non-literal."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        return "".join(v.value if isinstance(v, ast.Constant) else "{}" for v in node.values)
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
        return _text(node.left) + _text(node.right)
    return ""


def _message(call: ast.Call) -> str:
    arg = call.args[0] if call.args else next((k.value for k in call.keywords if k.arg in ("problem", "message")), None)
    return _text(arg) if arg is not None else ""


def _modules(roots=ROOTS, repo: Path = REPO):
    for root in roots:
        for path in sorted((repo / root).rglob("*.py")):
            text = path.read_text(encoding="utf-8")
            tree = ast.parse(text, str(path))
            tree.lines = text.splitlines()  # for the ``# protocol:`` marks
            yield path.relative_to(repo).as_posix(), tree


def scan(modules) -> list[tuple[str, int, str, str, str]]:
    """``(file, line, exception class, message text, problem)`` for each raise or error that breaks the convention."""
    modules = list(modules)
    bases: dict[str, set[str]] = {}
    for _, tree in modules:
        for node in ast.walk(tree):
            if isinstance(node, ast.ClassDef):
                bases.setdefault(node.name, set()).update(filter(None, map(_name, node.bases)))

    def reaches(name: str, goal, seen=()) -> bool:
        return goal(name) or (name not in seen and any(reaches(b, goal, (*seen, name)) for b in bases.get(name, ())))

    ours = {n for n in bases if reaches(n, lambda b: b == ROOT_ERROR)} | {ROOT_ERROR}
    foreign = {n for n in bases if n not in ours and reaches(n, lambda b: b in BUILTIN)}
    found = []
    for rel, tree in modules:
        for node in ast.walk(tree):
            if isinstance(node, ast.Raise) and node.exc is not None:
                call = node.exc if isinstance(node.exc, ast.Call) else None
                name = _name(call.func if call else node.exc)
                if name in BUILTIN and "# protocol:" not in tree.lines[node.end_lineno - 1]:
                    found.append((rel, node.lineno, name, _message(call) if call else "", "a built-in exception"))
                elif name in foreign:
                    found.append((rel, node.lineno, name, _message(call) if call else "", "not a B3dgsError"))
            if isinstance(node, ast.Call) and _name(node.func) in ours:
                if "(fix:" in _message(node):
                    found.append((rel, node.lineno, _name(node.func), _message(node), '"(fix:" written into the text'))
                if not _has_fix(node):
                    found.append((rel, node.lineno, _name(node.func), _message(node), "no fix"))
    return found


def _has_fix(call: ast.Call) -> bool:
    """Whether a ``B3dgsError(...)`` call passes a fix: a second positional argument, ``fix=``, or ``*args`` /
    ``**kwargs`` (which may carry one)."""
    return (len(call.args) >= 2 or any(isinstance(a, ast.Starred) for a in call.args)
            or any(k.arg in ("fix", None) for k in call.keywords))


def _key(entry, finding) -> bool:
    path, exc, fragment = entry
    return finding[0] == path and finding[2] == exc and fragment in finding[3]


def test_the_scan_finds_each_form(tmp_path):
    (tmp_path / "b3dgs").mkdir()
    (tmp_path / "b3dgs" / "m.py").write_text(
        "from b3dgs.errors import B3dgsError\n"
        "class Mine(B3dgsError): pass\n"
        "class Other(RuntimeError): pass\n"
        "def f(x, e):\n"
        "    if x == 1: raise ValueError(f'bad {x}')\n"
        "    if x == 2: raise builtins.KeyError('k')\n"
        "    if x == 3: raise Other('o')\n"
        "    if x == 4: raise B3dgsError(f'bad {x} (fix: pass x=0)')\n"
        "    if x == 5: raise Mine('bad ' + '(fix: y)')\n"
        "    if x == 6: raise B3dgsError('bad', 'pass x=0')\n"
        "    if x == 7: raise Mine(problem='fine', fix='f')\n"
        "    if x == 8: raise e\n"
        "    if x == 9: raise\n"
        "    err = B3dgsError('made here (fix: z)')\n"
        "    raise NotImplementedError\n"
        "    if x == 10: raise B3dgsError(f'bad {x}')\n"
        "    if x == 11: raise Mine(problem='bad')\n"
        "    if x == 12: raise B3dgsError(*pair)\n"
        "    if x == 13: raise B3dgsError(**parts)\n"
        "    if x == 14: raise TypeError(f'{x} is no JSON')  # protocol: json's default=\n")
    got = [(line, name, what) for _, line, name, _, what in scan(_modules(("b3dgs",), tmp_path))]
    assert sorted(got) == [(5, "ValueError", "a built-in exception"), (6, "KeyError", "a built-in exception"),
                           (7, "Other", "not a B3dgsError"), (8, "B3dgsError", '"(fix:" written into the text'),
                           (8, "B3dgsError", "no fix"), (9, "Mine", '"(fix:" written into the text'),
                           (9, "Mine", "no fix"), (14, "B3dgsError", '"(fix:" written into the text'),
                           (14, "B3dgsError", "no fix"), (15, "NotImplementedError", "a built-in exception"),
                           (16, "B3dgsError", "no fix"), (17, "Mine", "no fix")]


def test_every_deliberate_error_is_a_b3dgs_error_with_its_fix():
    bad = [f for f in scan(_modules()) if not any(_key(e, f) for e in (*ALLOWED, *PENDING))]
    assert not bad, ("raise B3dgsError(problem, fix=...) for an error a user can cause, its fix naming what the "
                     "caller should do (or add a programming error to ALLOWED with its reason):\n" + "\n".join(f"  {p}:{n}: {e}({t!r}): {w}" for p, n, e, t, w in bad))


def test_every_allow_list_entry_is_current_and_has_a_reason():
    found = scan(_modules())
    for table in (ALLOWED, PENDING):
        for entry, reason in table.items():
            assert reason.strip(), entry
            assert any(_key(entry, f) for f in found), (
                f"{entry} matches no raise any more: delete it from {'ALLOWED' if table is ALLOWED else 'PENDING'}")


def test_pending_entries_name_only_files_another_change_owns():
    owned = {"b3dgs/train.py", "b3dgs/runs.py", "b3dgs/module.py", "plugins/posterior/niw.py", "plugins/posterior/sh.py",
             "b3dgs/study/rounds.py", "b3dgs/study/compression.py", "b3dgs/rundir.py", "b3dgs/eval.py",
             "b3dgs/render_cli.py", "b3dgs/plugin.py", "b3dgs/fisher.py"}
    assert {p for p, _, _ in PENDING} <= owned

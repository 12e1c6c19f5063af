"""``bench/`` imports one way (issue 45 §5): as the package ``bench``, run as ``python -m bench.<name>`` from the
repository root. Read from the source with ``ast`` (nothing is imported), every ``bench/*.py``:

- imports a sibling only as ``bench.<module>`` (``from bench.common import ...``), never bare (``from common
  import ...``) or relative;
- leaves ``sys.path`` alone (no ``insert``/``append``/``extend``/..., no assignment): ``bench.common.load_file``
  loads a file by path when one is needed;
- has no second import path: no ``try``/``except ImportError`` (or ``ModuleNotFoundError``) around an import of
  ``bench`` or a sibling.
"""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT / "bench"
SIBLINGS = {p.stem for p in BENCH.glob("*.py")} - {"__init__"}
IMPORT_ERRORS = {"ImportError", "ModuleNotFoundError"}
PATH_MUTATORS = {"insert", "append", "extend", "remove", "pop", "clear", "__setitem__", "__delitem__", "__iadd__"}


def _is_sys_path(node) -> bool:
    return isinstance(node, ast.Attribute) and node.attr == "path" and isinstance(node.value, ast.Name) \
        and node.value.id == "sys"


def _bench_imports(node) -> list[str]:
    """The names of ``bench``/sibling modules that import statement ``node`` imports, as written."""
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    elif isinstance(node, ast.ImportFrom):
        if node.level:
            return [f"{'.' * node.level}{node.module or ''}"]
        names = [node.module or ""]
    else:
        return []
    return [n for n in names if n.split(".")[0] in SIBLINGS | {"bench"}]


def _catches_import_error(handler: ast.ExceptHandler) -> bool:
    if handler.type is None:
        return True
    types = handler.type.elts if isinstance(handler.type, ast.Tuple) else [handler.type]
    return any(isinstance(t, ast.Name) and t.id in IMPORT_ERRORS | {"Exception", "BaseException"} for t in types)


def problems(path: Path, root: Path = ROOT) -> list[str]:
    out = []
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        where = f"{path.relative_to(root)}:{getattr(node, 'lineno', '?')}"
        for name in _bench_imports(node):
            head = name.split(".")[0]
            if name.startswith(".") or head != "bench":
                out.append(f"{where}: sibling imported as {name!r}, not as bench.<module>")
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and _is_sys_path(node.func.value) \
                and node.func.attr in PATH_MUTATORS:
            out.append(f"{where}: sys.path.{node.func.attr}(...)")
        if isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign, ast.Delete)):
            targets = node.targets if isinstance(node, (ast.Assign, ast.Delete)) else [node.target]
            for t in targets:
                for sub in ast.walk(t):
                    if _is_sys_path(sub):
                        out.append(f"{where}: sys.path assigned")
        if isinstance(node, ast.Try) and any(_catches_import_error(h) for h in node.handlers):
            guarded = [n for stmt in node.body + [s for h in node.handlers for s in h.body]
                       for sub in ast.walk(stmt) for n in _bench_imports(sub)]
            if guarded:
                out.append(f"{where}: try/except ImportError around {sorted(set(guarded))}")
    return out


def test_bench_imports_one_way():
    assert SIBLINGS, "no bench/*.py found"
    found = [p for path in sorted(BENCH.glob("*.py")) for p in problems(path)]
    assert not found, "bench/ imports one way, as bench.<module> (issue 45 §5):\n" + "\n".join(found)


def test_checker_catches_each_kind(tmp_path):
    """The three patterns the checker exists for are found (so a pass above means something)."""
    bad = tmp_path / "bad.py"
    bad.write_text("import sys\nfrom pathlib import Path\n"
                   "sys.path.insert(0, str(Path(__file__).parent))\n"
                   "sys.path = ['x'] + sys.path\n"
                   "from common import RESULTS\n"
                   "from .render import camera\n"
                   "try:\n    from bench.common import machine\nexcept ModuleNotFoundError:\n    pass\n")
    text = "\n".join(problems(bad, tmp_path))
    assert "sys.path.insert" in text and "sys.path assigned" in text
    assert "'common'" in text and "'.render'" in text
    assert "try/except ImportError" in text

"""The import graph of ``b3dgs/`` and ``plugins/`` has no cycle, at two levels, counting every import, also those
inside functions (a lazy import hides a cycle from Python, not from this test):

- between modules: no module imports, directly or through others, a module that imports it back (``render._ext``
  -> ``render.renderers`` -> ``render._ext`` was one);
- between the top-level modules and subpackages of ``b3dgs`` (``b3dgs.render``, ``b3dgs.metrics``, ``b3dgs.train``,
  ...): the floors form a DAG (render <-> metrics was one). ``import b3dgs`` itself (resolvers, ``conf_dir``) is a
  leaf.

An import names a module (``from b3dgs.render import renderers``) or the package whose ``__init__`` defines the
name (``from b3dgs.render import X``); the implicit import of a module's parent packages is not an edge.
"""
import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("b3dgs", "plugins")
ALIASES = {"b3dgs_plugins": "plugins"}  # the installed name of plugins/


def _modules() -> dict[str, tuple[Path, bool]]:
    out = {}
    for pkg in PACKAGES:
        for path in (ROOT / pkg).rglob("*.py"):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            is_pkg = parts[-1] == "__init__"
            out[".".join(parts[:-1] if is_pkg else parts)] = (path, is_pkg)
    return out


def _canonical(name: str) -> str:
    head, _, rest = name.partition(".")
    head = ALIASES.get(head, head)
    return f"{head}.{rest}" if rest else head


def _targets(node, package: str, modules) -> list[str]:
    if isinstance(node, ast.Import):
        return [_canonical(a.name) for a in node.names]
    base = node.module or ""
    if node.level:
        parts = package.split(".")
        base = ".".join(parts[: len(parts) - node.level + 1] + ([base] if base else []))
    base = _canonical(base)
    return [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]


def module_graph() -> dict[str, set[str]]:
    modules = _modules()
    graph: dict[str, set[str]] = {}
    for module, (path, is_pkg) in modules.items():
        package = module if is_pkg else module.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for t in _targets(node, package, modules):
                    if t in modules and t != module:
                        graph.setdefault(module, set()).add(t)
    return graph


def _unit(module: str) -> str:
    return ".".join(module.split(".")[:2])


def unit_graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for module, targets in module_graph().items():
        if module.startswith("b3dgs"):
            for t in targets:
                if t.startswith("b3dgs.") and _unit(t) != _unit(module):
                    graph.setdefault(_unit(module), set()).add(_unit(t))
    return graph


def find_cycle(graph: dict[str, set[str]]):
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(v):
        state[v] = 1
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if state.get(w) == 1:
                return stack[stack.index(w):] + [w]
            if w not in state:
                found = visit(w)
                if found:
                    return found
        state[v] = 2
        stack.pop()
        return None

    for v in sorted(graph):
        if v not in state:
            found = visit(v)
            if found:
                return found
    return None


def test_no_module_import_cycle():
    graph = module_graph()
    # the walk saw the code and plugins
    assert "b3dgs.render._ext" in graph["b3dgs.render.renderers"]
    assert any(m.startswith("plugins.") for m in graph)
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_b3dgs_names_no_plugin_module():
    """docs/design.md: the core builds what the config names (the viewer's σ modes are conf/uq regimes), so no
    module of b3dgs/ imports one of plugins/ (installed as b3dgs_plugins), lazily or not."""
    graph = module_graph()
    assert "b3dgs.confs" in graph["b3dgs.viewer.modes"]  # the walk saw the viewer's lazy imports
    assert sorted((m, t) for m, ts in graph.items() if m.startswith("b3dgs") for t in ts if t.startswith("plugins")) == []


def test_b3dgs_floors_are_a_dag():
    graph = unit_graph()
    assert "b3dgs.render" in graph and "b3dgs.metrics" in graph  # the walk saw the code
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)
    assert "b3dgs.metrics" not in graph["b3dgs.render"]


def test_the_check_finds_a_lazy_cycle(tmp_path, monkeypatch):
    """A cycle closed only by an import inside a function is reported."""
    pkg = tmp_path / "b3dgs"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from b3dgs.b import g\n")
    (pkg / "b.py").write_text("def g():\n    from b3dgs import a\n    return a\n")
    (tmp_path / "plugins").mkdir()
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert find_cycle(module_graph()) in (["b3dgs.a", "b3dgs.b", "b3dgs.a"], ["b3dgs.b", "b3dgs.a", "b3dgs.b"])


#: plugin modules that import another plugin's module, each with why; empty since issue 53 moved the shared code
#: (check_radius, the appearance math, the DP CAVI and scores, the native regime) into b3dgs/, and it only shrinks
CROSS_PLUGIN_ALLOWED: dict[tuple[str, str], str] = {}


def plugin_cross_imports() -> list[tuple[str, str]]:
    """(importer, imported) pairs where a plugin module (``plugins.<kind>.<x>``, not a package's ``__init__``) imports
    another plugin's module; shared code lives in ``b3dgs/`` (base classes, numerics), which every plugin may import
    (issue 53)."""
    return sorted((m, t) for m, targets in module_graph().items()
                  if m.startswith("plugins.") and m.count(".") >= 2
                  for t in targets if t.startswith("plugins.") and t.count(".") >= 2 and t != m)


def test_no_plugin_imports_another_plugins_module(tmp_path, monkeypatch):
    found = plugin_cross_imports()
    assert [p for p in found if p not in CROSS_PLUGIN_ALLOWED] == []
    assert set(CROSS_PLUGIN_ALLOWED) <= set(found), "an allowed import is gone: delete its entry"
    assert "b3dgs.fisher" in module_graph()["plugins.posterior.niw"]  # the walk saw the plugins' imports
    pkg = tmp_path / "plugins" / "acquisition"  # and it finds one, lazy or not, through the installed name
    pkg.mkdir(parents=True)
    (tmp_path / "plugins" / "posterior").mkdir()
    (tmp_path / "plugins" / "posterior" / "sh.py").write_text("X = 1\n")
    (pkg / "pol.py").write_text("def f():\n    from b3dgs_plugins.posterior.sh import X\n    return X\n")
    (tmp_path / "b3dgs").mkdir()
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert plugin_cross_imports() == [("plugins.acquisition.pol", "plugins.posterior.sh")]

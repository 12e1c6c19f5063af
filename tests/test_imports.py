"""The import graph of ``b3dgs/`` is a DAG at the level of its top-level modules and subpackages (``b3dgs.render``,
``b3dgs.metrics``, ``b3dgs.train``, ...), counting every import, also those inside functions: no cycle is hidden by
a lazy import (render <-> metrics was one). ``import b3dgs`` itself (resolvers, ``conf_dir``) is a leaf."""
import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "b3dgs"


def _unit(module: str) -> str:
    return ".".join(module.split(".")[:2])


def _graph() -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for path in PKG.rglob("*.py"):
        parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
        is_pkg = parts[-1] == "__init__"
        module = ".".join(parts[:-1] if is_pkg else parts)
        package = module if is_pkg else module.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                targets = [base]
            else:
                continue
            for t in targets:
                if t.startswith("b3dgs.") and _unit(t) != _unit(module):
                    graph.setdefault(_unit(module), set()).add(_unit(t))
    return graph


def _cycle(graph: dict[str, set[str]]):
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


def test_b3dgs_import_graph_is_a_dag():
    graph = _graph()
    assert "b3dgs.render" in graph and "b3dgs.metrics" in graph  # the walk saw the code
    cycle = _cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)
    assert "b3dgs.metrics" not in graph["b3dgs.render"]

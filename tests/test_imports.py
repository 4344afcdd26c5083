"""The project's module import graph, read statically (ast): no import circle, and lacuna/ on the
ground floor.  Every import counts, at the top of a file or inside a function (a lazy import
still ties the two modules together); only ``if TYPE_CHECKING:`` blocks are left out."""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("lacuna", "mocap", "hlm", "crbm", "daemon", "clients", "blend", "view", "archive")


def _modules() -> dict[str, Path]:
    out = {}
    for pkg in PACKAGES:
        for p in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(p.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = p
    return out


def _imported(tree: ast.Module, here: str, is_pkg: bool) -> set[str]:
    """Dotted names this module imports (with `from X import name`, X.name where that is a module too)."""
    names: set[str] = set()

    def visit(node: ast.AST) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.If) and "TYPE_CHECKING" in ast.unparse(child.test):
                for n in child.orelse:
                    visit(n)
                continue
            if isinstance(child, ast.Import):
                names.update(a.name for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    pkg = here.split(".") if is_pkg else here.split(".")[:-1]
                    pkg = pkg[:len(pkg) - (child.level - 1)]
                    base = ".".join(pkg + ([base] if base else []))
                names.add(base)
                names.update(f"{base}.{a.name}" for a in child.names)
            visit(child)

    visit(tree)
    return names


def import_graph() -> dict[str, set[str]]:
    mods = _modules()
    graph: dict[str, set[str]] = {}
    for name, path in mods.items():
        wanted = _imported(ast.parse(path.read_text(), str(path)), name, path.name == "__init__.py")
        graph[name] = {m for m in wanted if m in mods and m != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_the_graph_is_read():
    g = import_graph()
    # a few edges known to exist: the reader must find both top-level and function-level imports
    assert "lacuna.filler" in g["mocap.feature_model"]
    assert "daemon.wire" in g["clients.control"]
    assert "daemon.security" in g["daemon.config"]
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


def test_no_import_circle():
    found = cycles(import_graph())
    assert not found, "import circles (each a set of modules that import each other):\n" + "\n".join(
        " <-> ".join(c) for c in found)


def test_lacuna_is_the_ground_floor():
    g = import_graph()
    up = {m: sorted(d for d in deps if not d.startswith("lacuna")) for m, deps in g.items() if m.startswith("lacuna")}
    up = {m: d for m, d in up.items() if d}
    assert not up, f"lacuna/ imports modules above it: {up}"


def test_no_file_in_daemon_over_400_lines():
    # issue 19: each file of daemon/ holds one idea; stop 38 let decode.py reach 405 unnoticed
    long = {p.name: n for p in sorted((ROOT / "daemon").glob("*.py"))
            if (n := len(p.read_text().splitlines())) > 400}
    assert not long, f"daemon/ files over 400 lines: {long}"

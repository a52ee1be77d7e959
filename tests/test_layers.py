"""The package layout: imports flow one way, from the core up to the command line, with no circle.

Every import counts: module-level, inside functions (lazy) and under TYPE_CHECKING; only an
`if __name__ == "__main__":` block is left out (it runs when the module is the program, never when it is
imported: `python -m skyview.experiments.NAME` hands over to the command line). A module's layer is
its package under `skyview/`; a module may import its own layer and those below it, never one above.
Inside a layer, the imports between modules form no cycle either. docs/architecture.md draws the same
picture.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "skyview"

# lowest first; a module may import its own layer and any layer before it
LAYERS = ("core", "io", "detect", "identify", "simulate", "solver", "present", "record", "experiments", "bench",
          "viewer", "cli")
FACADES = {"skyview", "skyview.__main__"}  # the package's own door: `skyview.solve`, `python -m skyview`
SINKS = ("viser", "rerun")  # the identification stages never import a sink


def _modules() -> dict[str, Path]:
    mods = {}
    for p in ROOT.rglob("*.py"):
        parts = p.relative_to(ROOT.parent).with_suffix("").parts
        mods[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return mods


MODULES = _modules()


def _imports(name: str, path: Path) -> list[tuple[str, int]]:
    """Every skyview module `name` imports (resolved to a module, not an attribute), with its line."""
    out = []
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    tree = ast.parse(path.read_text(), str(path))
    tree.body = [n for n in tree.body if not _is_main_block(n)]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join(up + ([node.module] if node.module else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in MODULES else base for a in node.names]
        else:
            continue
        for t in targets:
            while t not in MODULES and "." in t:
                t = t.rpartition(".")[0]
            if t in MODULES and t != name:
                out.append((t, node.lineno))
    return out


def _is_main_block(node: ast.stmt) -> bool:
    return (isinstance(node, ast.If) and isinstance(node.test, ast.Compare)
            and isinstance(node.test.left, ast.Name) and node.test.left.id == "__name__"
            and any(isinstance(c, ast.Constant) and c.value == "__main__" for c in node.test.comparators))


def _external(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and not node.level and node.module:
            names.add(node.module.split(".")[0])
    return names


def layer(name: str) -> int | None:
    if name in FACADES:
        return None
    return LAYERS.index(name.split(".")[1])


def test_every_module_has_a_layer():
    for name in MODULES:
        if name not in FACADES:
            assert name.split(".")[1] in LAYERS, f"{name} is in no layer of {LAYERS}"


def test_imports_flow_one_way():
    wrong = []
    for name, path in MODULES.items():
        mine = layer(name)
        if mine is None:
            continue
        for target, line in _imports(name, path):
            theirs = layer(target)
            if theirs is None or theirs > mine:
                wrong.append(f"{path.relative_to(ROOT.parent)}:{line} imports {target}")
    assert not wrong, "imports against the layers:\n" + "\n".join(wrong)


def test_no_import_cycle():
    graph = {name: {t for t, _ in _imports(name, path)} for name, path in MODULES.items()}
    # Tarjan's strongly connected components, iteratively
    index, low, on, stack, cycles, counter = {}, {}, set(), [], [], [0]

    def visit(root):
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]; counter[0] += 1
        stack.append(root); on.add(root)
        while work:
            v, it = work[-1]
            for w in it:
                if w not in index:
                    index[w] = low[w] = counter[0]; counter[0] += 1
                    stack.append(w); on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                    break
                if w in on:
                    low[v] = min(low[v], index[w])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[v])
                if low[v] == index[v]:
                    comp = []
                    while True:
                        w = stack.pop(); on.discard(w); comp.append(w)
                        if w == v:
                            break
                    if len(comp) > 1:
                        cycles.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


@pytest.mark.parametrize("stage", ["core", "io", "detect", "identify", "simulate", "solver"])
def test_the_stages_import_no_sink(stage):
    users = [str(p.relative_to(ROOT.parent)) for n, p in MODULES.items()
             if n.split(".")[1:2] == [stage] and _external(p) & set(SINKS)]
    assert not users, f"{users} import a sink ({SINKS})"


def test_the_checker_sees_lazy_and_type_checking_imports(tmp_path):
    probe = tmp_path / "probe.py"
    probe.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from skyview.core import camera\n"
                     "def f():\n    from skyview.solver.pipeline import MethodSolver\n    import skyview.io.wcs\n"
                     "if __name__ == '__main__':\n    from skyview.cli import main\n")
    assert {t for t, _ in _imports("skyview.core.probe", probe)} == {
        "skyview.core.camera", "skyview.solver.pipeline", "skyview.io.wcs"}

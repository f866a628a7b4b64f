"""The package's import structure, read from its source: every ``import`` of a jointsim module,
at module level or inside a function, is an edge. Layers only point down, siblings do not
import each other, no module imports another's private names, and there is no import cycle
(a cycle hidden by an import inside a function is still a cycle)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "jointsim"

# Top-level parts of the package, bottom to top. A part may import parts of lower rank only;
# parts of equal rank are siblings that do not import each other.
LAYERS: list[set[str]] = [
    {"_cudss", "_surface"},  # the GPU's sparse direct solver, below linalg (optional: nvmath-python); a user's surface file, below scene
    {"_cores", "_warp", "scene", "linalg", "timing"},  # settings, shared numerics, the stage timer
    {"geometry"},  # the sensor's shapes and electrode layout
    {"mesh"},  # tetrahedral meshes of the chamber
    {"eit", "mechanics", "reconstruction"},  # the physics and the inverse
    {"metrics", "io"},
    {"instrument"},  # the sensor's measurement chain and the one frame step
    {"palpation", "studies", "dataset", "design"},  # the jobs: each measures through the instrument, none through another
    {"calibration"},
    {"cli"},
    {"__main__"},
]
RANK = {part: i for i, parts in enumerate(LAYERS) for part in parts}


def _module(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _resolves(name: str) -> bool:
    p = PACKAGE.parent / name.replace(".", "/")
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def _imports() -> list[tuple[str, str, str]]:
    """(importing module, imported module, imported name or '') for every jointsim import."""
    out = []
    for path in sorted(PACKAGE.rglob("*.py")):
        mod = _module(path)
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                out += [(mod, a.name, "") for a in node.names if a.name.split(".")[0] == "jointsim"]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                if target.split(".")[0] != "jointsim":
                    continue
                for a in node.names:
                    sub = f"{target}.{a.name}"
                    out.append((mod, sub, "") if _resolves(sub) else (mod, target, a.name))
    return out


IMPORTS = _imports()


def _part(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def test_every_part_of_the_package_has_a_layer():
    parts = {_part(m) for m, _, _ in IMPORTS} | {_part(t) for _, t, _ in IMPORTS}
    assert parts - {""} <= set(RANK), f"give these a layer: {sorted(parts - {''} - set(RANK))}"


def test_layers_only_point_down():
    edges = sorted({(m, t) for m, t, _ in IMPORTS if _part(m) != _part(t) and _part(t)})
    up = [f"{m} imports {t}" for m, t in edges if RANK[_part(m)] <= RANK[_part(t)]]
    assert len(edges) > 50 and not up, "imports that do not point down a layer: " + "; ".join(up)


def test_no_module_imports_another_modules_private_names():
    private = [(m, t, n) for m, t, n in IMPORTS if n.startswith("_") and not n.startswith("__") and m != t]
    assert not private, "private names used across modules: " + "; ".join(f"{m} imports {t}.{n}" for m, t, n in private)


def test_there_is_no_import_cycle():
    graph: dict[str, set[str]] = {}
    for m, t, _ in IMPORTS:
        if m != t and not m.startswith(t + "."):  # a module importing its own package's __init__
            graph.setdefault(m, set()).add(t)
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for nxt in sorted(graph.get(node, ())):
            if state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            if nxt not in state and (cycle := visit(nxt)):
                return cycle
        state[node] = 2
        path.pop()
        return None

    for node in sorted(graph):
        if node not in state and (cycle := visit(node)):
            pytest.fail("import cycle: " + " -> ".join(cycle))


def part_graph() -> str:
    """The imports between parts, top layer first, as a Markdown table (ARCHITECTURE.md shows it)."""
    uses: dict[str, set[str]] = {}
    for m, t, _ in IMPORTS:
        if _part(m) and _part(t) and _part(m) != _part(t):
            uses.setdefault(_part(m), set()).add(_part(t))
    rows = ["| layer | part | imports |", "|---|---|---|"]
    for i in reversed(range(len(LAYERS))):
        for p in sorted(LAYERS[i]):
            below = sorted(uses.get(p, ()), key=lambda q: (-RANK[q], q))
            rows.append(f"| {i + 1} | `{p}` | {', '.join(f'`{q}`' for q in below) or '–'} |")
    return "\n".join(rows)


def test_architecture_md_shows_the_import_graph_as_it_is():
    text = (PACKAGE.parent / "ARCHITECTURE.md").read_text()
    assert part_graph() in text, "ARCHITECTURE.md's import table is out of date: paste `python tests/test_architecture.py`"


if __name__ == "__main__":  # python tests/test_architecture.py: the table in ARCHITECTURE.md
    print(part_graph())

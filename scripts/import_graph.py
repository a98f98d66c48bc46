"""The import graph of ``src/mira``: cycles between modules and between packages, upward arrows between
the architecture's layers, and modules or classes too long to read.

Every ``import`` of a ``mira`` module counts, wherever it is written (module level, inside a function,
under ``TYPE_CHECKING``): a lazy import hides an arrow from the reader, not from the design. Modules are
grouped into the layers of ``docs/architecture.md``; an arrow may point to the same or a lower layer
only. Read between packages (``mira.<pkg>``, the first level under ``mira``; a top-level module such as
``mira.config`` is a node of its own), the same imports form no cycle either: two packages that import
each other, even through different modules, are one package in all but name. A module holds at most
``MAX_MODULE_LINES`` lines and a class ``MAX_CLASS_LINES``, except the program checker's AST visitor
(one ``visit_*`` per node kind, read one method at a time). Exit status 1, with every offending arrow,
cycle, module and class, when the tree breaks a rule.

    python scripts/import_graph.py              # check (CI runs this through the test suite)
    python scripts/import_graph.py --dot        # the package-level graph in Graphviz syntax
    python scripts/import_graph.py --mermaid    # the same as a Mermaid block (docs/architecture.md)
"""

from __future__ import annotations

import argparse
import ast
import itertools
import sys
from collections import defaultdict
from pathlib import Path

SRC = Path(__file__).resolve().parents[1] / "src"

# Lowest first. A module belongs to the layer of the longest prefix listed here ("mira" is the package
# itself only).
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("foundation", ("mira", "mira.errors", "mira.runio", "mira.cli_types", "mira.version")),
    ("core", ("mira.replay", "mira.tasks", "mira.agents", "mira.rewards", "mira.loop")),
    ("components", ("mira.factors", "mira.llm", "mira.engineer", "mira.shaping", "mira.mcm", "mira.srr",
                    "mira.baselines", "mira.examples")),
    ("methods", ("mira.outer", "mira.config", "mira.config_history", "mira.methods", "mira.explain", "mira.train_cli")),
    ("experiments", ("mira.experiments",)),
    ("cli", ("mira.cli", "mira.__main__", "mira.api")),
]


MAX_MODULE_LINES = 600
MAX_CLASS_LINES = 300
SIZE_EXCEPTIONS = {"mira.factors.checker", "mira.factors.checker._FunctionChecker"}


def layer_of(module: str) -> int:
    best, best_len = -1, -1
    for rank, (_, prefixes) in enumerate(LAYERS):
        for prefix in prefixes:
            covers = module == prefix or (prefix != "mira" and module.startswith(prefix + "."))
            if covers and len(prefix) > best_len:
                best, best_len = rank, len(prefix)
    if best < 0:
        raise SystemExit(f"import_graph: module {module} is in no layer; add it to LAYERS")
    return best


def module_name(path: Path, src: Path = SRC) -> str:
    parts = list(path.relative_to(src).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_of(path: Path, name: str, src: Path = SRC) -> set[str]:
    """``mira`` modules imported anywhere in the file (``from pkg import mod`` counts ``pkg.mod`` if it is
    a module, else ``pkg``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    is_package = path.name == "__init__.py"
    out: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.split(".")[0] == "mira")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target.split(".")[0] != "mira":
                continue
            for alias in node.names:
                sub = f"{target}.{alias.name}"
                out.add(sub if _exists(sub, src) else target)
    out.discard(name)
    return out


def _exists(module: str, src: Path = SRC) -> bool:
    rel = Path(*module.split("."))
    return (src / rel).with_suffix(".py").is_file() or (src / rel / "__init__.py").is_file()


def graph(src: Path = SRC) -> dict[str, set[str]]:
    """Module → the ``mira`` modules it imports, for the tree under ``src`` (the directory holding
    ``mira/``)."""
    edges: dict[str, set[str]] = {}
    for path in sorted((src / "mira").rglob("*.py")):
        name = module_name(path, src)
        edges[name] = imports_of(path, name, src)
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for root in edges:
        if root in index:
            continue
        work = [(root, iter(sorted(edges.get(root, ()))))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            child = next(children, None)
            if child is not None:
                if child not in edges:
                    continue
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(sorted(edges[child]))))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    top = stack.pop()
                    on_stack.discard(top)
                    component.append(top)
                    if top == node:
                        break
                if len(component) > 1:
                    out.append(sorted(component))
    return out


def upward(edges: dict[str, set[str]]) -> list[tuple[str, str]]:
    """Arrows from a module to one in a higher layer; a package's ``__init__`` re-exporting its own
    modules is not an arrow of its own."""
    bad = []
    for src, targets in edges.items():
        for dst in targets:
            if dst.startswith(src + "."):
                continue
            if layer_of(dst) > layer_of(src):
                bad.append((src, dst))
    return sorted(bad)


def oversized(sources: dict[str, str]) -> list[str]:
    """Modules over ``MAX_MODULE_LINES`` lines and classes over ``MAX_CLASS_LINES`` (``sources``: module
    name → its text), as readable lines; the exceptions are ``SIZE_EXCEPTIONS``."""
    found = []
    for name, text in sorted(sources.items()):
        lines = len(text.splitlines())
        if lines > MAX_MODULE_LINES and name not in SIZE_EXCEPTIONS:
            found.append(f"module {name}: {lines} lines (at most {MAX_MODULE_LINES})")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef) and f"{name}.{node.name}" not in SIZE_EXCEPTIONS:
                size = (node.end_lineno or node.lineno) - node.lineno + 1
                if size > MAX_CLASS_LINES:
                    found.append(f"class {name}.{node.name}: {size} lines (at most {MAX_CLASS_LINES})")
    return found


def sources(src: Path = SRC) -> dict[str, str]:
    return {module_name(p, src): p.read_text(encoding="utf-8") for p in sorted((src / "mira").rglob("*.py"))}


def package(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2])


def package_edges(edges: dict[str, set[str]]) -> dict[str, set[str]]:
    pkg_edges: dict[str, set[str]] = defaultdict(set)
    for src, targets in edges.items():
        for dst in targets:
            a, b = package(src), package(dst)
            if a != b and b != "mira" and a != "mira":
                pkg_edges[a].add(b)
    return pkg_edges


def package_cycles(edges: dict[str, set[str]]) -> list[str]:
    """Cycles of the package graph, one per strongly connected component of more than one package, as
    readable lines: the shortest cycle through the component's first package, then the module arrows
    that make each of its steps."""
    pkg_edges = package_edges(edges)
    found = []
    for component in cycles(dict(pkg_edges)):
        members = set(component)
        start = component[0]
        came_from: dict[str, str] = {}
        frontier = [start]
        while start not in came_from:
            step = []
            for node in frontier:
                for nxt in sorted(pkg_edges[node] & members):
                    if nxt not in came_from:
                        came_from[nxt] = node
                        step.append(nxt)
            frontier = step
        path = [start]
        while len(path) == 1 or path[-1] != start:
            path.append(came_from[path[-1]])
        path.reverse()
        steps = []
        for a, b in itertools.pairwise(path):
            arrows = sorted(f"{src} -> {dst}" for src, targets in edges.items() for dst in targets
                            if package(src) == a and package(dst) == b)
            steps.append(", ".join(arrows))
        found.append(" -> ".join(path) + " (" + "; ".join(steps) + ")")
    return found


def mermaid(edges: dict[str, set[str]]) -> str:
    """The package graph as a Mermaid flowchart, layers as subgraphs (highest first); arrows into the
    foundation layer (errors, run-directory I/O), which every package uses, are left out."""
    pkg_edges = package_edges(edges)
    foundation = {package(p) for p in LAYERS[0][1]}
    lines = ["```mermaid", "flowchart TB"]
    for rank in range(len(LAYERS) - 1, -1, -1):
        layer, prefixes = LAYERS[rank]
        members = sorted({package(p) for p in prefixes if p != "mira"})
        lines.append(f"  subgraph {layer}")
        lines += [f"    {m.replace('.', '_')}[{m.removeprefix('mira.')}]" for m in members]
        lines.append("  end")
    for a in sorted(pkg_edges):
        for b in sorted(pkg_edges[a] - foundation):
            lines.append(f"  {a.replace('.', '_')} --> {b.replace('.', '_')}")
    lines.append("```")
    return "\n".join(lines)


def dot(edges: dict[str, set[str]]) -> str:
    pkg_edges = package_edges(edges)
    lines = ["digraph mira {", "  rankdir=BT;"]
    for rank, (layer, prefixes) in enumerate(LAYERS):
        members = sorted({package(p) for p in prefixes if p != "mira"})
        lines.append(f"  subgraph cluster_{rank} {{ label=\"{layer}\"; " + " ".join(f'"{m}";' for m in members) + " }")
    for a in sorted(pkg_edges):
        for b in sorted(pkg_edges[a]):
            lines.append(f'  "{a}" -> "{b}";')
    lines.append("}")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dot", action="store_true", help="print the package graph in Graphviz syntax")
    parser.add_argument("--mermaid", action="store_true", help="print the package graph as a Mermaid block")
    parser.add_argument("--src", type=Path, default=SRC,
                        help="the directory holding the mira/ tree to check (default: this repository's src)")
    args = parser.parse_args()
    edges = graph(args.src)
    if args.dot or args.mermaid:
        print(dot(edges) if args.dot else mermaid(edges))
        return 0
    found_cycles, found_upward = cycles(edges), upward(edges)
    for component in found_cycles:
        print("cycle: " + " <-> ".join(component))
    found_package_cycles = package_cycles(edges)
    for line in found_package_cycles:
        print(f"package cycle: {line}")
    for src, dst in found_upward:
        print(f"upward: {src} ({LAYERS[layer_of(src)][0]}) -> {dst} ({LAYERS[layer_of(dst)][0]})")
    found_large = oversized(sources(args.src))
    for line in found_large:
        print(f"too long: {line}")
    if found_cycles or found_package_cycles or found_upward or found_large:
        return 1
    packages = {package(m) for m in edges} - {"mira"}
    print(f"import graph: {len(edges)} modules in {len(packages)} packages, no cycles between modules or "
          "packages, no upward arrows, none too long")
    return 0


if __name__ == "__main__":
    sys.exit(main())

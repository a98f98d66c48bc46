"""The architecture's rules: no import cycles between modules or between packages, no arrow from a lower
layer to a higher one, no module or class too long to read."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "import_graph.py"


def test_import_graph_has_no_cycles_and_no_upward_arrows() -> None:
    done = subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr


def test_the_checker_finds_a_cycle_and_an_upward_arrow(tmp_path: Path) -> None:
    """The check can fail: a toy tree with a cycle and a core module importing the CLI is refused."""
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        import import_graph as ig
    finally:
        sys.path.pop(0)
    edges = {"mira.replay": {"mira.cli"}, "mira.cli": {"mira.replay"}, "mira.errors": set()}
    assert ig.cycles(edges) == [["mira.cli", "mira.replay"]]
    assert ig.upward(edges) == [("mira.replay", "mira.cli")]


def test_the_checker_finds_a_cycle_between_packages_that_no_module_cycle_shows(tmp_path: Path) -> None:
    """Packages that import each other through different modules (one of the imports lazy) are refused,
    the cycle named with the module arrows that close it; a top-level module is a package of its own."""
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        import import_graph as ig
    finally:
        sys.path.pop(0)
    tree = {
        "mira/__init__.py": "",
        "mira/engineer/__init__.py": "",
        "mira/engineer/prompt.py": "from mira.srr.rules import Rule\n",
        "mira/srr/__init__.py": "",
        "mira/srr/rules.py": "class Rule:\n    pass\n",
        "mira/srr/reframe.py": "def reframe():\n    from mira.engineer import prompt\n    return prompt\n",
        "mira/config.py": "from mira.outer.settings import OuterSettings\n",
        "mira/outer/__init__.py": "",
        "mira/outer/settings.py": "class OuterSettings:\n    pass\n",
        "mira/outer/loop.py": "import mira.config\n",
    }
    for rel, text in tree.items():
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(text, encoding="utf-8")
    edges = ig.graph(tmp_path)
    assert ig.cycles(edges) == []
    assert sorted(ig.package_cycles(edges)) == [
        "mira.config -> mira.outer -> mira.config (mira.config -> mira.outer.settings; mira.outer.loop -> mira.config)",
        "mira.engineer -> mira.srr -> mira.engineer"
        " (mira.engineer.prompt -> mira.srr.rules; mira.srr.reframe -> mira.engineer.prompt)",
    ]
    done = subprocess.run([sys.executable, str(SCRIPT), "--src", str(tmp_path)], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 1, done.stdout + done.stderr
    assert "package cycle: mira.engineer -> mira.srr -> mira.engineer" in done.stdout
    assert "package cycle: mira.config -> mira.outer -> mira.config" in done.stdout


def test_the_checker_finds_a_module_and_a_class_too_long() -> None:
    """The size rule can fail: a module and a class past their limits are named, an exception is not."""
    sys.path.insert(0, str(SCRIPT.parent))
    try:
        import import_graph as ig
    finally:
        sys.path.pop(0)
    big_class = "class Big:\n" + "    x = 1\n" * ig.MAX_CLASS_LINES
    long_module = "y = 0\n" * (ig.MAX_MODULE_LINES + 1)
    found = ig.oversized({"mira.a": big_class, "mira.b": long_module, "mira.factors.checker": long_module,
                          "mira.c": "class Small:\n    x = 1\n"})
    assert found == [f"class mira.a.Big: {ig.MAX_CLASS_LINES + 1} lines (at most {ig.MAX_CLASS_LINES})",
                     f"module mira.b: {ig.MAX_MODULE_LINES + 1} lines (at most {ig.MAX_MODULE_LINES})"]


def test_docs_show_the_current_graph() -> None:
    """``docs/architecture.md`` carries the graph the script draws now."""
    done = subprocess.run([sys.executable, str(SCRIPT), "--mermaid"], capture_output=True, text=True, timeout=120)
    doc = (SCRIPT.parents[1] / "docs" / "architecture.md").read_text(encoding="utf-8")
    assert done.stdout.strip() in doc, "regenerate the graph: python scripts/import_graph.py --mermaid"

"""The architecture's import rule: no cycles, no arrow from a lower layer to a higher one."""

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


def test_docs_show_the_current_graph() -> None:
    """``docs/architecture.md`` carries the graph the script draws now."""
    done = subprocess.run([sys.executable, str(SCRIPT), "--mermaid"], capture_output=True, text=True, timeout=120)
    doc = (SCRIPT.parents[1] / "docs" / "architecture.md").read_text(encoding="utf-8")
    assert done.stdout.strip() in doc, "regenerate the graph: python scripts/import_graph.py --mermaid"

"""The documentation's relative links and images point to files that are in the repository."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")


def _tracked_markdown() -> list[Path]:
    done = subprocess.run(["git", "ls-files", "*.md"], cwd=ROOT, capture_output=True, text=True, check=False)
    if done.returncode == 0 and done.stdout.strip():
        return [ROOT / line for line in done.stdout.split()]
    return [*ROOT.glob("*.md"), *ROOT.glob("docs/**/*.md"), *ROOT.glob("bench/*.md")]  # not a git checkout


def _missing_targets(doc: Path) -> list[str]:
    """Relative link targets of ``doc`` (URLs and same-page anchors aside) with no file behind them."""
    out = []
    for target in LINK.findall(doc.read_text(encoding="utf-8")):
        if re.match(r"^[a-z]+:", target) or target.startswith("#"):
            continue
        if not (doc.parent / target.split("#")[0]).exists():
            out.append(target)
    return out


def test_every_relative_link_in_the_docs_resolves() -> None:
    broken = [f"{doc.relative_to(ROOT)}: {t}" for doc in _tracked_markdown() for t in _missing_targets(doc)]
    assert not broken, "links to files that are not in the repository:\n" + "\n".join(broken)


def test_a_missing_target_is_reported(tmp_path: Path) -> None:
    (tmp_path / "here.png").write_bytes(b"")
    doc = tmp_path / "x.md"
    doc.write_text("![a](here.png) ![b](runs/nowhere.png) [site](https://example.org) [up](#top)\n")
    assert _missing_targets(doc) == ["runs/nowhere.png"]

"""``bench/archive.py`` keeps what a table and an audit need, and nothing heavy, in the layout the table
readers expect."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from types import ModuleType


def _fake_run(run: Path, final: float) -> None:
    (run / "programs").mkdir(parents=True)
    (run / "interventions" / "001").mkdir(parents=True)
    (run / "checkpoints" / "step_5000").mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"method": "mira", "seed": 0}))
    (run / "eval.csv").write_text(f"step,return_mean,return_std,wall_s\n5000,1.0,0.1,10\n10000,{final},0.1,20\n")
    (run / "programs" / "v000.json").write_text("{}")
    (run / "interventions" / "001" / "decision.json").write_text(json.dumps({"step": 7000}))
    (run / "checkpoints" / "step_5000" / "buffer.pt").write_bytes(b"x" * 1000)
    (run / "train.csv").write_text("step\n1\n")


def test_archive_keeps_curves_programs_and_decisions_not_checkpoints(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    archive = load_bench("archive")
    out = tmp_path / "runs" / "grid"
    _fake_run(out / "mira-sac-s0", 42.0)
    _fake_run(out / "halfcheetah" / "no_progress" / "hars-sac-s1", 7.0)  # the older flawed-benchmark layout
    (out / "not-a-run").mkdir()

    copied = archive.archive(out, tmp_path / "archive")

    assert len(copied) == 2
    kept = tmp_path / "archive" / "grid" / "mira-sac-s0"
    assert (kept / "eval.csv").read_text().endswith("10000,42.0,0.1,20\n")
    assert (kept / "programs" / "v000.json").exists()
    assert json.loads((kept / "interventions" / "001" / "decision.json").read_text()) == {"step": 7000}
    assert not (kept / "checkpoints").exists() and not (kept / "train.csv").exists()
    assert (tmp_path / "archive" / "grid" / "halfcheetah" / "no_progress" / "hars-sac-s1" / "eval.csv").exists()
    # Copying again refreshes a run that has gone further.
    (out / "mira-sac-s0" / "eval.csv").write_text("step,return_mean,return_std,wall_s\n10000,43.0,0.1,20\n")
    archive.archive(out, tmp_path / "archive")
    assert "43.0" in (kept / "eval.csv").read_text()

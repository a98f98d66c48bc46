"""End-to-end MIRA runs (small budgets): the outer loop never stops training, and leaves a full trail."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

import mira.outer.loop
from mira.cli import main
from mira.runio.csvlog import read_csv

FAST_MIRA = ["--set", "mira.mcm.delta_t=400", "--set", "mira.holdout_episodes=1",
             "--set", "mira.mcm.k_warm=1", "--set", "mira.mcm.buffer_min=1", "--set", "mira.mcm.min_scores=1"]


# The no-MCM ablation calls SRR every cycle, so that two 400-step cycles see two interventions: patched in this
# process (the fixture below) and in a `python -m mira.cli` of its own (PERIODIC_MIRA_CLI).
PERIODIC_MIRA_CLI = [sys.executable, "-c", "; ".join([
    "import os, sys", "import mira.outer.loop", "mira.outer.loop.PERIODIC_CYCLES = 1",
    "os.environ.setdefault('PYTHONUNBUFFERED', '1')", "from mira.cli import main", "sys.exit(main(sys.argv[1:]))"])]


@pytest.fixture(autouse=True)
def _periodic_srr_every_cycle(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(mira.outer.loop, "PERIODIC_CYCLES", 1)


def _train(out: Path, fast: list[str], method: str, *extra: str, steps: int = 800) -> int:
    return main(["train", "--task", "halfcheetah", "--method", method, "--steps", str(steps), "--seed", "0",
                 "--out", str(out), *fast, *FAST_MIRA, *extra])


@pytest.mark.slow
def test_mira_writes_diagnostics_programs_and_llm_audit(tmp_path: Path, fast_train_args: list[str]) -> None:
    run = tmp_path / "run"
    assert _train(run, fast_train_args, "mira") == 0
    rows = read_csv(run / "diagnostics.csv")
    assert [r["step"] for r in rows] == ["400", "800"]
    assert {"raw_pvc", "d_rpe", "score", "threshold", "trigger", "cooldown_left", "buffer_fill"} <= set(rows[0])
    assert (run / "programs" / "v000.json").is_file()
    exchanges = (run / "llm" / "exchanges.jsonl").read_text()
    assert "rule-based" in exchanges  # the offline engineer says what it is


AGENT_COLUMNS = ("train_return", "critic_loss", "q_mean", "actor_loss", "entropy", "alpha")


@pytest.mark.slow
def test_the_monitor_leaves_the_agent_as_hars_trains_it(tmp_path: Path, fast_train_args: list[str]) -> None:
    """Without an edit, MIRA's agent is HARS's bit for bit (κ = 0: the agent learns from r̂ alone): the
    monitor reads the run, it draws none of the agent's random numbers and feeds nothing back. Only
    Φ's own figures may differ (reading Φ each cycle lands HARS's pending training step earlier)."""
    runs = {m: tmp_path / m for m in ("hars", "mira-no-srr")}
    for method, run in runs.items():
        assert _train(run, fast_train_args, method, steps=2000) == 0
    assert len(read_csv(runs["mira-no-srr"] / "diagnostics.csv")) == 5  # the monitor did run
    evals = {m: [(r["step"], r["return_mean"]) for r in read_csv(run / "eval.csv")] for m, run in runs.items()}
    assert evals["hars"] == evals["mira-no-srr"] and len(evals["hars"]) == 2
    train = {m: [[r[k] for k in AGENT_COLUMNS] for r in read_csv(run / "train.csv")] for m, run in runs.items()}
    assert train["hars"] == train["mira-no-srr"] and len(train["hars"]) == 4


@pytest.mark.slow
def test_endpoint_down_records_failed_interventions_and_training_goes_on(tmp_path: Path,
                                                                         fast_train_args: list[str]) -> None:
    run = tmp_path / "run"
    program = Path(__file__).parents[1] / "src" / "mira" / "examples" / "halfcheetah_f0.json"
    code = _train(run, fast_train_args, "mira-no-mcm", "--program", str(program),
                  "--llm", "openai:deepseek-reasoner", "--base-url", "http://127.0.0.1:9/v1",
                  "--set", "llm.max_retries=0", "--set", "llm.timeout_s=2")
    assert code == 0
    decisions = sorted((run / "interventions").glob("*/decision.json"))
    assert len(decisions) == 2
    for path in decisions:
        decision = json.loads(path.read_text())
        assert decision["failed"] and not decision["accepted"] and "LLM call failed" in decision["reason"]
    assert read_csv(run / "eval.csv")[-1]["step"] == "800"


@pytest.mark.slow
def test_diagnosis_only_on_humanoidstandup_logs_every_cycle_and_never_edits(tmp_path: Path,
                                                                             fast_train_args: list[str]) -> None:
    run = tmp_path / "run"
    code = main(["train", "--task", "humanoidstandup", "--method", "mira-no-srr", "--steps", "800", "--seed", "0",
                 "--out", str(run), *fast_train_args, *FAST_MIRA])
    assert code == 0
    rows = read_csv(run / "diagnostics.csv")
    assert len(rows) == 2 and all(r["version"] == "0" for r in rows)
    assert not (run / "interventions").exists() or not any((run / "interventions").iterdir())
    assert sorted(p.name for p in (run / "programs").glob("*.json")) == ["origin.json", "v000.json"]


@pytest.mark.slow
def test_interventions_are_reported_as_they_happen(tmp_path: Path, fast_train_args: list[str]) -> None:
    """Each verified candidate and each decision is one line of the run's output (here --quiet, as in a log
    file), with its figures; no progress bar is redrawn into it."""
    import subprocess

    run = tmp_path / "run"
    proc = subprocess.run([*PERIODIC_MIRA_CLI, "train", "--task", "halfcheetah", "--method", "mira-no-mcm",
                           "--steps", "800", "--seed", "0", "--out", str(run), "--quiet", *fast_train_args,
                           *FAST_MIRA],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout + proc.stderr
    assert "\r" not in out
    candidates = [ln for ln in out.splitlines() if ": candidate " in ln]
    decisions = [ln for ln in out.splitlines() if "installed program v" in ln or "backed off, program v" in ln]
    assert candidates and all("step " in ln for ln in candidates)
    assert len(decisions) == len(sorted((run / "interventions").glob("*/decision.json"))) >= 1


@pytest.mark.slow
def test_mira_runs_on_hopper_a_terminating_task(tmp_path: Path, fast_train_args: list[str]) -> None:
    """A built-in task whose episodes end early: the offline program from the card's declarations, the
    outer loop's cycles and the evaluations all run."""
    run = tmp_path / "run"
    code = main(["train", "--task", "hopper", "--method", "mira", "--steps", "1200", "--seed", "0",
                 "--out", str(run), *fast_train_args, *FAST_MIRA])
    assert code == 0
    program = json.loads((run / "programs" / "v000.json").read_text())
    assert {f["name"] for f in program["factors"]} == {"r_torso_height", "r_torso_angle", "r_x_velocity", "r_ctrl"}
    assert len(read_csv(run / "diagnostics.csv")) >= 2 and read_csv(run / "eval.csv")[-1]["step"] == "1200"

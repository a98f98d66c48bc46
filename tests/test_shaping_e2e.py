"""``mira train --method hars`` end to end (a few thousand steps, small networks)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from mira.cli import main
from mira.factors.examples import example_program
from mira.runio.checkpoint import load_latest
from mira.runio.csvlog import read_csv
from mira.shaping import source

HARS_COLUMNS = ("phi_mean", "phi_std", "l_align", "l_aux", "attn_entropy", "rpe")


def _check(run: Path, phi_names: list[str]) -> None:
    rows = read_csv(run / "train.csv")
    assert rows
    for col in (*HARS_COLUMNS, *(f"attn_{n}" for n in phi_names)):
        assert col in rows[0], col
    trained = [r for r in rows if r["l_align"] != ""]
    assert trained and all(float(r["rpe"]) >= 0 for r in trained)
    attn = sum(float(trained[-1][f"attn_{n}"]) for n in phi_names)
    assert attn == pytest.approx(1.0, abs=1e-3)
    program = json.loads((run / "programs" / "v000.json").read_text())
    assert [f["name"] for f in program["factors"] if f["type"] == "PHI"] == phi_names
    config = json.loads((run / "config.json").read_text())
    assert config["config"]["hars"]["alignment"] == "decomposed"
    assert config["method"]["method"] == "hars"
    assert int(read_csv(run / "eval.csv")[-1]["step"]) == 3000


@pytest.mark.slow
@pytest.mark.parametrize(
    ("task", "algo", "phi_names"),
    [
        ("halfcheetah", "sac", ["r_vel", "r_upright", "r_stable"]),
        ("halfcheetah", "ddpg", ["r_vel", "r_upright", "r_stable"]),
        ("humanoidstandup", "sac", ["r_height", "r_stable"]),
    ],
)
def test_train_hars_with_the_offline_engineer(tmp_path: Path, fast_train_args: list[str], task: str, algo: str,
                                              phi_names: list[str]) -> None:
    run = tmp_path / "run"
    code = main(["train", "--task", task, "--method", "hars", "--algo", algo, "--steps", "3000", "--seed", "0",
                 "--out", str(run), *fast_train_args])
    assert code == 0
    _check(run, phi_names)
    assert (run / "llm" / "exchanges.jsonl").is_file()  # the LSFS exchange is audited


@pytest.mark.slow
def test_train_hars_from_a_program_file(tmp_path: Path, fast_train_args: list[str]) -> None:
    program = tmp_path / "f1.json"
    program.write_text(json.dumps(example_program("halfcheetah", 1).to_json()))
    run = tmp_path / "run"
    code = main(["train", "--task", "halfcheetah", "--method", "hars", "--algo", "ddpg", "--steps", "3000",
                 "--out", str(run), "--program", str(program), *fast_train_args])
    assert code == 0
    phi = [f.name for f in example_program("halfcheetah", 1).phi_factors]
    _check(run, phi)
    assert not (run / "llm" / "exchanges.jsonl").exists()  # no engineer was asked


def test_program_for_another_task_is_a_usage_error(tmp_path: Path, fast_train_args: list[str]) -> None:
    program = tmp_path / "p.json"
    program.write_text(json.dumps(example_program("humanoidstandup", 0).to_json()))
    code = main(["train", "--task", "halfcheetah", "--method", "hars", "--steps", "600", "--out",
                 str(tmp_path / "run"), "--program", str(program), *fast_train_args])
    assert code == 2


def _tensors(state: object, prefix: str = "") -> dict[str, torch.Tensor]:
    """Every tensor in a nested checkpoint state, by path."""
    if isinstance(state, torch.Tensor):
        return {prefix: state}
    items = state.items() if isinstance(state, dict) else enumerate(state) if isinstance(state, list | tuple) else ()
    out: dict[str, torch.Tensor] = {}
    for key, value in items:
        out.update(_tensors(value, f"{prefix}/{key}"))
    return out


def test_training_in_background_is_the_same_run(tmp_path: Path, fast_train_args: list[str],
                                                monkeypatch: pytest.MonkeyPatch) -> None:
    """HARS's training step on its own thread or on the caller's: the same computation, bit for bit."""
    monkeypatch.setattr(source, "TCE_EVERY", 1)  # the TCE's windows in every step, on either thread
    runs = {}
    for background in (True, False):
        # Whether a core is free decides where the step runs: force each answer in turn.
        monkeypatch.setattr(source, "_has_spare_core", lambda background=background: background)
        run = tmp_path / f"bg-{background}"
        code = main(["train", "--task", "halfcheetah", "--method", "hars", "--algo", "sac", "--steps", "1500",
                     "--seed", "5", "--out", str(run), *fast_train_args, "--set", "hars.update_every=3"])
        assert code == 0
        assert json.loads((run / "config.json").read_text())["method"]["train_in_background"] is background
        runs[background] = run
    rows = {b: read_csv(r / "train.csv") for b, r in runs.items()}
    assert len(rows[True]) == len(rows[False]) > 0
    for a, b in zip(rows[True], rows[False], strict=True):
        assert {k: v for k, v in a.items() if k != "steps_per_s"} == {k: v for k, v in b.items() if k != "steps_per_s"}
    states = {b: load_latest(r / "checkpoints") for b, r in runs.items()}
    assert states[True] is not None and states[False] is not None
    assert states[True][0] == states[False][0]
    bg, fg = _tensors(states[True][1]["reward"]), _tensors(states[False][1]["reward"])
    bg.update(_tensors(states[True][1]["agent"], "agent"))
    fg.update(_tensors(states[False][1]["agent"], "agent"))
    assert bg.keys() == fg.keys() and any("fab" in k for k in bg)
    assert all(torch.equal(bg[k], fg[k]) for k in bg)

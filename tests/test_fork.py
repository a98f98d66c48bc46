"""``mira train --fork``: a run continued from another's checkpoint under a seed of its own."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from mira.cli import main
from mira.errors import UsageError
from mira.explain import explain
from mira.runio.csvlog import read_csv

FAST_MIRA = ["--set", "mira.mcm.delta_t=400", "--set", "mira.holdout_episodes=1", "--set", "mira.mcm.k_warm=1",
             "--set", "mira.mcm.buffer_min=1", "--set", "mira.mcm.min_scores=1"]


@pytest.fixture(scope="module")
def parent(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small ``mira`` run with checkpoints at steps 800 and 1200."""
    from tests.conftest import FAST_TRAIN

    run = tmp_path_factory.mktemp("fork") / "parent"
    assert main(["train", "--task", "halfcheetah", "--method", "mira", "--steps", "1200", "--seed", "0",
                 "--out", str(run), *FAST_TRAIN, *FAST_MIRA]) == 0
    return run


def _fork(parent: Path, out: Path, *extra: str) -> int:
    return main(["train", "--fork", str(parent), "--fork-step", "800", "--steps", "2000", "--out", str(out),
                 "--quiet", *extra])


def _evals(run: Path) -> list[tuple[str, str]]:
    return [(r["step"], r["return_mean"]) for r in read_csv(run / "eval.csv")]


@pytest.mark.slow
def test_forks_with_one_seed_are_one_run_and_other_seeds_part(parent: Path, tmp_path: Path) -> None:
    runs = {name: tmp_path / name for name in ("a5", "b5", "nosrr5", "a6")}
    assert _fork(parent, runs["a5"], "--seed", "5") == 0
    assert _fork(parent, runs["b5"], "--seed", "5") == 0
    # The pair of a paired experiment: the same checkpoint and seed, SRR off. Without an edit (the task's
    # own program makes none here) the two are the same run.
    assert _fork(parent, runs["nosrr5"], "--seed", "5", "--method", "mira-no-srr") == 0
    assert _fork(parent, runs["a6"], "--seed", "6") == 0
    evals = {name: _evals(run) for name, run in runs.items()}
    assert [s for s, _ in evals["a5"]] == ["1000", "2000"]  # its logs start at the fork
    assert evals["a5"] == evals["b5"] == evals["nosrr5"]
    assert evals["a6"] != evals["a5"]

    saved = json.loads((runs["nosrr5"] / "config.json").read_text())
    assert saved["config"]["method"] == "mira-no-srr" and saved["config"]["seed"] == 5
    assert saved["config"]["steps"] == 2000 and saved["config"]["agent"]["hidden"] == [32, 32]  # the parent's
    origin = saved["forked_from"]
    assert origin["step"] == 800 and origin["seed"] == 0 and origin["method"] == "mira"
    manifest = json.loads((parent / "checkpoints" / "ckpt-0000000800.json").read_text())
    assert origin["sha256"] == manifest["sha256"]
    assert (runs["a5"] / "programs" / "v000.json").read_bytes() == (parent / "programs" / "v000.json").read_bytes()


@pytest.mark.slow
def test_a_fork_resumed_from_its_first_checkpoint_repeats_itself(parent: Path, tmp_path: Path) -> None:
    """Killed before its first checkpoint, a fork restarts from the parent's and reseeds as it did."""
    whole, again = tmp_path / "whole", tmp_path / "again"
    assert _fork(parent, whole, "--seed", "3") == 0
    assert _fork(parent, again, "--seed", "3") == 0
    # As it was when it started: the parent's checkpoint only (its own later ones prune the copy).
    shutil.rmtree(again / "checkpoints")
    shutil.copytree(parent / "checkpoints", again / "checkpoints",
                    ignore=lambda _, names: [n for n in names if not n.startswith("ckpt-0000000800.")])
    assert main(["train", "--resume", str(again), "--quiet"]) == 0
    assert _evals(again) == _evals(whole)


def _with_escape(parent: Path, out: Path) -> Path:
    """The parent's program with a bounded SHAPE potential added (an escape ramp on the torso's height)."""
    program = json.loads((parent / "programs" / "v000.json").read_text())
    program["factors"].append({
        "name": "psi_escape", "type": "SHAPE", "units": "1", "range_hint": "[0, 50]",
        "doc": "escape potential: a bounded ramp above the torso height where the policy settles",
        "code": "def psi_escape(s):\n    return 25.0 * (1.0 + np.tanh((s.torso_height - 0.1) / 0.05))\n"})
    program["rationale"] = "an escape ramp"
    out.write_text(json.dumps(program))
    return out


@pytest.mark.slow
def test_a_fork_installs_a_program_as_an_edit_and_a_resume_installs_it_again(parent: Path, tmp_path: Path) -> None:
    escape = _with_escape(parent, tmp_path / "escape.json")
    plain, edited, again = tmp_path / "plain", tmp_path / "edited", tmp_path / "again"
    assert _fork(parent, plain, "--seed", "4", "--method", "mira-no-srr") == 0
    assert _fork(parent, edited, "--seed", "4", "--method", "mira-no-srr", "--fork-program", str(escape)) == 0
    installed = json.loads((edited / "programs" / "v001.json").read_text())
    assert installed["version"] == 1 and installed["parent_version"] == 0
    assert [f["name"] for f in installed["factors"]][-1] == "psi_escape"
    assert (edited / "programs" / "v001.diff").is_file() and not (plain / "programs" / "v001.json").exists()
    assert json.loads((edited / "config.json").read_text())["forked_from"]["program"]["factors"][-1]["type"] == "SHAPE"
    assert _evals(edited) != _evals(plain)  # the same run but for the potential's γΨ(s′) − Ψ(s)
    story = explain(edited)
    assert f"Forked from {parent.resolve()} at step 800" in story and f"installed program {escape.resolve()}" in story

    assert _fork(parent, again, "--seed", "4", "--method", "mira-no-srr", "--fork-program", str(escape)) == 0
    shutil.rmtree(again / "checkpoints")
    shutil.copytree(parent / "checkpoints", again / "checkpoints",
                    ignore=lambda _, names: [n for n in names if not n.startswith("ckpt-0000000800.")])
    assert main(["train", "--resume", str(again), "--quiet"]) == 0
    assert _evals(again) == _evals(edited)


@pytest.mark.slow
def test_a_fork_may_keep_the_policy_more_random(parent: Path, tmp_path: Path) -> None:
    """SAC's target entropy decides no network, so a fork may raise it: an exploration edit at a checkpoint."""
    plain, explore = tmp_path / "plain", tmp_path / "explore"
    assert _fork(parent, plain, "--seed", "4") == 0
    assert _fork(parent, explore, "--seed", "4", "--set", "agent.target_entropy=0") == 0
    saved = json.loads((explore / "config.json").read_text())
    assert saved["config"]["agent"]["target_entropy"] == 0.0
    assert saved["forked_from"]["settings"] == ["agent.target_entropy=0"]  # the arm, for the pairs table
    assert "--set agent.target_entropy=0" in explain(explore)
    alphas = {name: [float(r["alpha"]) for r in read_csv(run / "train.csv")] for name, run in
              (("plain", plain), ("explore", explore))}
    # Above its target of -|A| the temperature falls; towards 0 nats it rises from the same checkpoint.
    assert alphas["explore"][-1] > alphas["plain"][-1]
    assert _evals(explore) != _evals(plain)


@pytest.mark.parametrize(("extra", "message"), [
    (["--lr", "1e-3"], "--lr cannot change"),
    (["--set", "agent.tau=0.01"], "--set agent.tau=0.01 cannot change"),
    (["--method", "hars"], "a mira checkpoint does not continue as hars"),
    (["--fork-step", "400"], "no checkpoint at that step (the run keeps checkpoints at 800, 1200)"),
    (["--fork-step", "1200", "--steps", "1200"], "leaves nothing to train"),
    (["--fork-program", "/nonexistent/program.json"], "/nonexistent/program.json"),
])
@pytest.mark.slow
def test_a_fork_that_cannot_continue_its_parent_is_refused(parent: Path, tmp_path: Path, extra: list[str],
                                                           message: str, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "fork"
    assert main(["train", "--fork", str(parent), "--out", str(out), *extra]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists() or not any(out.iterdir())


def test_a_fork_of_a_directory_without_a_run_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    empty = tmp_path / "empty"
    empty.mkdir()
    assert main(["train", "--fork", str(empty), "--out", str(tmp_path / "fork")]) == 2
    assert "not a usable run directory" in capsys.readouterr().err
    assert main(["train", "--fork", str(tmp_path)]) == 2
    assert "give it --out DIR" in capsys.readouterr().err
    for out in (empty, empty / "inside", tmp_path):
        assert main(["train", "--fork", str(empty), "--out", str(out), "--overwrite"]) == 2
        assert "cannot be the parent's, inside it or around it" in capsys.readouterr().err
    assert empty.is_dir()
    assert main(["train", "--fork-program", str(tmp_path / "p.json"), "--out", str(tmp_path / "x")]) == 2
    assert "give --fork RUN_DIR too" in capsys.readouterr().err


def test_a_sweep_does_not_pass_fork_through(tmp_path: Path) -> None:
    from mira.experiments.grid import check_train_args

    with pytest.raises(UsageError, match="--fork"):
        check_train_args(["--fork", str(tmp_path)])

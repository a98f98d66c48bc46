"""``bench/flawed.py``'s run list (every flawed program per method, the good program's reference runs
with ``hars`` and ``mira`` only, and none of them when they are run elsewhere) and its gathering of runs
over several folders."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest


def test_jobs_give_the_good_program_only_hars_and_mira_and_can_leave_it_out(
        load_bench: Callable[[str], ModuleType]) -> None:
    flawed = load_bench("flawed")
    methods = ["hars", "mira", "mira-no-mcm"]
    with_good = flawed.jobs("halfcheetah", ["no_progress"], methods, [0, 1])
    assert with_good[:5] == [("good", "hars", 0), ("good", "mira", 0), ("no_progress", "hars", 0),
                             ("no_progress", "mira", 0), ("no_progress", "mira-no-mcm", 0)]
    assert len(with_good) == 10
    without = flawed.jobs("halfcheetah", ["no_progress"], methods, [0, 1], good=False)
    assert without == [(n, m, s) for n, m, s in with_good if n != "good"]
    # --good-only passes no flawed program: the good program's hars and mira runs alone
    assert flawed.jobs("halfcheetah", [], methods, [0, 1]) == [
        ("good", "hars", 0), ("good", "mira", 0), ("good", "hars", 1), ("good", "mira", 1)]


def _run(run: Path, returns: list[float]) -> None:
    run.mkdir(parents=True)
    rows = "".join(f"{5000 * (k + 1)},{r},0.0,1000.0,10,1.0\n" for k, r in enumerate(returns))
    (run / "eval.csv").write_text("step,return_mean,return_std,length_mean,episodes,wall_s\n" + rows)


def test_the_table_gathers_seeds_over_folders_and_the_first_folder_wins(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    flawed = load_bench("flawed")
    new, old = tmp_path / "new" / "halfcheetah", tmp_path / "archive" / "halfcheetah"
    _run(new / "no_progress" / "mira-sac-s0", [1.0, 10.0])
    _run(old / "no_progress" / "mira-sac-s0", [1.0, 99.0])     # the same run elsewhere: not read
    _run(old / "no_progress" / "mira-sac-s1", [1.0, 20.0])
    _run(old / "no_progress" / "mira-sac-s2", [1.0])           # not finished at the budget: left out
    (old / "no_progress" / "mira-sac-s3").mkdir()              # no curve: not a run

    assert flawed.finals([new, old], "no_progress", "mira", "sac", 10_000) == {0: 10.0, 1: 20.0}
    assert flawed.finals([old, new], "no_progress", "mira", "sac", 10_000) == {0: 99.0, 1: 20.0}
    assert sorted(flawed.runs([new, old], "no_progress", "mira", "sac")) == [0, 1, 2]


def test_the_table_names_the_code_each_run_recorded(tmp_path: Path,
                                                   load_bench: Callable[[str], ModuleType]) -> None:
    learning = load_bench("learning")
    head, other = "a" * 40, "b" * 40
    sources = {"a/mira-sac-s0": head, "a/mira-sac-s1": head, "b/hars-sac-s0": f"{other}+0123456789ab",
               "b/hars-sac-s1": None}
    for name, source in sources.items():
        _run(tmp_path / "runs" / name, [1.0])
        environment = {"cpu": "x"} if source is None else {"cpu": "x", "source": source}  # None: an older run
        (tmp_path / "runs" / name / "config.json").write_text(json.dumps({"environment": environment}))
    assert learning.run_sources([tmp_path / "runs"]) == "aaaaaaa (2 runs), bbbbbbb+changes (1 run), unrecorded (1 run)"
    assert learning.run_sources([tmp_path / "runs" / "a", tmp_path / "none"]) == "aaaaaaa (2 runs)"
    assert learning.run_sources([tmp_path / "none"]) == "no runs"


def test_the_targets_name_the_rows_not_run_instead_of_counting_them_as_misses(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    flawed = load_bench("flawed")
    root = tmp_path / "out" / "halfcheetah"
    _run(root / "good" / "hars-sac-s0", [100.0])
    _run(root / "no_progress" / "hars-sac-s0", [10.0])
    _run(root / "no_progress" / "mira-sac-s0", [90.0])
    _run(root / "abs_velocity" / "hars-sac-s0", [10.0])          # its `mira` run is missing

    text = flawed.table([root], "halfcheetah", "sac", 5000, ["hars", "mira"], ["header"])
    assert "1 of 4 (no_progress; not run with both `hars` and `mira`: abs_velocity, wrong_gate, " \
           "saturated_velocity)" in text
    assert "0 of 2 (none; not run with both `hars` and `mira`: rewarded_effort, drowning_posture)" in text
    assert "* Good program: `mira` not run." in text
    assert "nan" not in text


def _config(run: Path, **cfg: object) -> None:
    base = {"task": "halfcheetah", "algo": "sac", "method": "mira", "seed": 1, "program": None}
    (run / "config.json").write_text(json.dumps({"config": {**base, **cfg}}))


def test_reference_runs_fill_the_good_programs_missing_seeds_and_refuse_what_is_not_hars(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    """A `mira` run of the task's own program that installed nothing stands for good-program `hars`
    where the folders lack that seed; a run that installed a program, or started from a program file,
    is refused with the reason."""
    flawed = load_bench("flawed")
    root = tmp_path / "out" / "halfcheetah"
    _run(root / "good" / "hars-sac-s0", [100.0])
    elsewhere = tmp_path / "learning" / "mira-sac-s1"
    _run(elsewhere, [300.0])
    _config(elsewhere)
    backed_off = elsewhere / "interventions" / "000-step5000"
    backed_off.mkdir(parents=True)
    (backed_off / "decision.json").write_text(json.dumps({"accepted": False}))
    shadowed = tmp_path / "learning" / "hars-sac-s0"                # seed 0 is in the folders: not read
    _run(shadowed, [999.0])
    _config(shadowed, method="hars", seed=0)

    reference = flawed.reference_runs("halfcheetah", "sac", [elsewhere, shadowed])
    assert flawed.finals([root], "good", "hars", "sac", 5000, reference) == {0: 100.0, 1: 300.0}
    assert flawed.finals([root], "good", "mira", "sac", 5000, reference) == {}
    assert "Reference: good-program `hars` 200" in flawed.table([root], "halfcheetah", "sac", 5000, ["hars"],
                                                                 ["header"], reference)

    edited = tmp_path / "learning" / "mira-sac-s2"
    _run(edited, [300.0])
    _config(edited, seed=2)
    (edited / "interventions" / "000-step5000").mkdir(parents=True)
    (edited / "interventions" / "000-step5000" / "decision.json").write_text(json.dumps({"accepted": True}))
    with pytest.raises(ValueError, match=r"installed a program \(000-step5000\)"):
        flawed.reference_runs("halfcheetah", "sac", [edited])
    flawed_start = tmp_path / "learning" / "hars-sac-s3"
    _run(flawed_start, [300.0])
    _config(flawed_start, method="hars", seed=3, program="bench/flawed/halfcheetah/no_progress.json")
    with pytest.raises(ValueError, match="not the task's own program"):
        flawed.reference_runs("halfcheetah", "sac", [flawed_start])


def test_the_table_tells_each_mira_runs_interventions_from_its_records(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    flawed = load_bench("flawed")
    root = tmp_path / "out" / "halfcheetah"
    _run(root / "good" / "hars-sac-s0", [100.0, 100.0])
    _run(root / "no_progress" / "hars-sac-s0", [1.0, 1.0])
    run = root / "no_progress" / "mira-sac-s0"
    _run(run, [1.0, 90.0])
    _config(run, seed=0, eval_every=5000)
    (run / "programs").mkdir()
    (run / "programs" / "v000.json").write_text(json.dumps({"factors": [{"name": "r_a", "code": "a"}]}))
    (run / "programs" / "v001.json").write_text(json.dumps(
        {"factors": [{"name": "r_a", "code": "a"}, {"name": "r_speed", "code": "b"}]}))
    repaired, refused = run / "interventions" / "000-step6000", run / "interventions" / "001-step9000"
    for folder, accepted in ((repaired, True), (refused, False)):
        folder.mkdir(parents=True)
        (folder / "decision.json").write_text(json.dumps(
            {"accepted": accepted, "operators": ["Add"] if accepted else [], "version": 1 if accepted else None}))
    (repaired / "evidence.json").write_text(json.dumps({"step": 6000, "cause": "structural", "return_attribution": {
        "program_cv_r2": -0.5, "feature_gains": [{"feature": "speed", "form": "value", "cv_r2": 0.9, "gain": 1.4}]}}))
    (refused / "evidence.json").write_text(json.dumps({"step": 9000, "cause": "periodic", "guided": False}))

    text = flawed.table([root], "halfcheetah", "sac", 10_000, ["hars", "mira"], ["header"])
    story = [line.strip() for line in text.split("Interventions of the `mira` runs:")[1].strip().splitlines()]
    assert story[0].startswith("* no_progress s0: step 6000: Add: +r_speed, installed v1 (the returns show a "
                               "structural flaw")
    assert "with speed added 0.90 (+1.40)" in story[0]
    assert story[1].startswith("* no_progress s0: step 9000: nothing installed, backed off (periodic review")

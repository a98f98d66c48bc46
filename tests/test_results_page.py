"""``bench/results_page.py``: the results page is what the archived runs give, and its figures over
seeds say what they are (mean and [min, max] below 5 seeds, never an interval over 3)."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import pytest


def _run(root: Path, method: str, seed: int, finals: tuple[float, float], steps: int = 20_000) -> None:
    run = root / method / f"seed{seed}"
    run.mkdir(parents=True)
    config = {"task": "halfcheetah", "method": method, "algo": "sac", "seed": seed, "steps": steps,
              "program": None, "agent": {"lr": 3e-4}, "eval_every": 10_000, "eval_episodes": 10}
    (run / "config.json").write_text(json.dumps({"config": config, "environment": {"source": "abc1234def",
                                                                                    "cpu": "Test CPU"}}))
    (run / "status.json").write_text(json.dumps({"status": "finished", "step": steps}))
    (run / "eval.csv").write_text("step,return_mean\n" + f"10000,{finals[0]}\n20000,{finals[1]}\n")


def _spec(tmp_path: Path, runs: Path, seeds_note: str = "") -> Path:
    spec = tmp_path / "results.toml"
    spec.write_text(f'''intro = "# Results"
[[table]]
id = "t"
title = "A table"
question = "Does it learn?"
budgets = [10000, 20000]
command = "mira sweep ..."
paper = {{ dense = 100, mira = 120 }}
runs = ["{runs}"]
''')
    return spec


def test_the_page_is_what_the_archives_give(load_bench: Callable[[str], ModuleType]) -> None:
    page = load_bench("results_page")
    assert page.main(["--check"]) == 0


def test_three_seeds_give_mean_and_extremes_five_an_interval(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    page = load_bench("results_page")
    runs = tmp_path / "runs"
    for seed, final in enumerate((10.0, 20.0, 60.0)):
        _run(runs, "dense", seed, (final / 2, final))
    for seed, final in enumerate((1.0, 2.0, 3.0, 4.0, 100.0)):
        _run(runs, "mira", seed, (0.0, final))
    meta, tables = page.load_spec(_spec(tmp_path, runs))

    text = page.render(meta, tables, figures=None)

    dense = next(line for line in text.splitlines() if line.startswith("| Dense"))
    mira = next(line for line in text.splitlines() if line.startswith("| MIRA"))
    assert "mean 30.0 [10.0, 60.0]" in dense and "CI" not in dense
    assert "| 0, 1, 2 |" in dense and dense.rstrip().endswith("| 100 |")
    # 5 seeds: the IQM (drops one seed at each end: 2, 3, 4) and an interval, not the mean (22).
    assert "| 3.00 [" in mira and "mean" not in mira
    # half of dense's 30 is 15: seed 0 (5, 10) never reaches it, seed 1 at 20k, seed 2 at 10k
    assert "15k (2/3)" in dense
    assert "`abc1234`: dense, mira" in text and "Test CPU" in text


def test_a_run_short_of_a_budget_counts_only_where_it_reached_and_is_said(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    page = load_bench("results_page")
    runs = tmp_path / "runs"
    _run(runs, "dense", 0, (1.0, 2.0))
    _run(runs, "dense", 1, (3.0, 4.0), steps=10_000)  # ran to the first budget only
    _run(runs, "mira", 0, (5.0, 6.0), steps=10_000)
    _run(runs, "mira", 1, (5.0, 6.0), steps=5_000)  # short of every budget
    (runs / "mira" / "seed1" / "eval.csv").write_text("step,return_mean\n5000,5.0\n")
    meta, tables = page.load_spec(_spec(tmp_path, runs))

    text = page.render(meta, tables, figures=None)

    dense = next(line for line in text.splitlines() if line.startswith("| Dense"))
    mira = next(line for line in text.splitlines() if line.startswith("| MIRA"))
    # At 10k both dense seeds (mean of 1 and 3); at 20k seed 0 alone, and the cell says so.
    assert "| 0, 1 | mean 2.00 [1.00, 3.00] | 2.00 (seeds 0) |" in dense
    assert "| 0 | 5.00 | not run to 20k | not run to 20k |" in mira
    assert "seed1` stopped at 10,000 steps: in the 10k column only" in text
    assert "mira/seed1` stopped at 5,000 steps: left out" in text


def test_a_run_resumed_on_other_code_names_both_commits(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    page = load_bench("results_page")
    runs = tmp_path / "runs"
    _run(runs, "dense", 0, (1.0, 2.0))
    config = runs / "dense" / "seed0" / "config.json"
    saved = json.loads(config.read_text())
    saved["resumed_elsewhere"] = [{"step": 10_000, "drift": ["source: 'abc1234def' -> '9876543fed'"],
                                   "environment": {"source": "9876543fed"}}]
    config.write_text(json.dumps(saved))
    meta, tables = page.load_spec(_spec(tmp_path, runs))
    assert "`abc1234`, resumed from 10k at `9876543`: dense" in page.render(meta, tables, figures=None)


def test_a_malformed_spec_names_the_table_and_key(tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    page = load_bench("results_page")
    spec = tmp_path / "results.toml"
    spec.write_text('[[table]]\nid = "hc"\ntitle = "t"\nquestion = "q"\nbudgets = [100]\nruns = []\n')
    with pytest.raises(page.SpecError, match="table 'hc': missing key 'command'"):
        page.load_spec(spec)


def test_the_posture_column_reads_each_run_record_and_says_which_lack_one(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    page = load_bench("results_page")
    runs = tmp_path / "runs"
    _run(runs, "dense", 0, (1.0, 2.0))
    _run(runs, "dense", 1, (1.0, 2.0))
    (runs / "dense" / "seed0" / "posture.json").write_text(json.dumps(
        {"features": {"torso_height": {"mean": 0.41, "p10": 0.4, "p90": 0.42}}}))
    spec = _spec(tmp_path, runs)
    spec.write_text(spec.read_text().replace("budgets = [10000, 20000]",
                                             'budgets = [10000, 20000]\nposture = "torso_height"'))
    meta, tables = page.load_spec(spec)

    text = page.render(meta, tables, figures=None)

    assert "torso_height at 20k (final evaluation episodes)" in text
    assert "| 0.41 (1 of 2 seeds) |" in text


def _edit(run: Path, name: str, cause: str, step: int, accepted: bool, kept: bool | None = None) -> None:
    folder = run / "interventions" / name
    folder.mkdir(parents=True)
    (folder / "evidence.json").write_text(json.dumps({"step": step, "cause": cause}))
    (folder / "decision.json").write_text(json.dumps({"accepted": accepted}))
    if kept is not None:
        (folder / "probation.json").write_text(json.dumps({"step": step + 5000, "kept": kept}))


def test_the_escapes_column_counts_the_plateau_edits_installed_and_kept_per_seed(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    page = load_bench("results_page")
    runs = tmp_path / "runs"
    _run(runs, "dense", 0, (1.0, 2.0))
    for seed in (0, 1):
        _run(runs, "mira", seed, (1.0, 2.0))
    seed0, seed1 = runs / "mira" / "seed0", runs / "mira" / "seed1"
    _edit(seed0, "000-step4000", "plateau", 4000, True, kept=True)
    _edit(seed0, "001-step6000", "anomaly", 6000, True)  # not the plateau detector's: not counted
    _edit(seed0, "002-step9000", "plateau", 9000, True, kept=False)
    _edit(seed0, "003-step12000", "plateau", 12000, False)  # refused: nothing installed
    _edit(seed1, "000-step17000", "plateau", 17000, True, kept=True)  # judged after the budget: on probation
    (seed1 / "interventions" / "000-step17000" / "probation.json").write_text(
        json.dumps({"step": 27000, "kept": True}))
    spec = _spec(tmp_path, runs)
    spec.write_text(spec.read_text().replace("budgets = [10000, 20000]", "budgets = [10000, 20000]\nescapes = true"))
    meta, tables = page.load_spec(spec)

    text = page.render(meta, tables, figures=None)

    assert "escapes kept/installed by 20k, per seed" in text
    mira = next(line for line in text.splitlines() if line.startswith("| MIRA |"))
    dense = next(line for line in text.splitlines() if line.startswith("| Dense"))
    assert mira.endswith("| 1/2, 0/1 | 120 |")
    assert dense.endswith("| — | 100 |")  # no outer loop, no escapes


def test_a_source_can_rename_its_method_and_count_its_program_file_as_the_task_own(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    page = load_bench("results_page")
    _run(tmp_path / "a", "dense", 0, (1.0, 2.0))
    _run(tmp_path / "b", "mira", 0, (1.0, 3.0))
    config = tmp_path / "b" / "mira" / "seed0" / "config.json"
    saved = json.loads(config.read_text())
    saved["config"]["program"] = "/runs/x/programs/v000.json"
    config.write_text(json.dumps(saved))
    spec = _spec(tmp_path, tmp_path / "a")
    spec.write_text(spec.read_text().replace(
        f'runs = ["{tmp_path / "a"}"]',
        f'runs = ["{tmp_path / "a"}", {{ path = "{tmp_path / "b"}", as = "mira-llm", as_program = "" }}]\n'
        'titles = { mira-llm = "MIRA, LLM replies" }'))
    meta, tables = page.load_spec(spec)

    text = page.render(meta, tables, figures=None)

    assert "| MIRA, LLM replies | 0 |" in text and "Initial program" not in text


def test_the_paper_rows_no_run_answers_are_listed_as_not_run(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    page = load_bench("results_page")
    runs = tmp_path / "runs"
    _run(runs, "dense", 0, (1.0, 2.0))
    spec = _spec(tmp_path, runs)
    spec.write_text(spec.read_text().replace("paper = { dense = 100, mira = 120 }",
                                             "paper = { dense = 100, mira = 120, lare = 90 }"))
    meta, tables = page.load_spec(spec)
    lines = page.render(meta, tables, figures=None).splitlines()
    mira, lare = "| MIRA | not run yet | — | — | — | 120 |", "| LaRe | not run yet | — | — | — | 90 |"
    assert mira in lines and lare in lines
    assert next(i for i, x in enumerate(lines) if x.startswith("| Dense")) < lines.index(mira)


def _fork(root: Path, name: str, parent_seed: int, program: str | None, finals: tuple[float, float],
          settings: tuple[str, ...] = ()) -> None:
    run = root / name
    run.mkdir(parents=True)
    config = {"task": "halfcheetah", "method": "mira-no-srr", "algo": "sac", "seed": 11, "steps": 30_000,
              "program": None}
    fork = {"run": f"/runs/parent{parent_seed}", "step": 10_000, "seed": parent_seed, "method": "mira-no-mcm",
            **({"program_file": f"/forks/{program}_s{parent_seed}.json"} if program else {}),
            **({"settings": list(settings)} if settings else {})}
    (run / "config.json").write_text(json.dumps({"config": config, "forked_from": fork,
                                                 "environment": {"source": "abc1234def", "cpu": "Test CPU"}}))
    (run / "eval.csv").write_text("step,return_mean\n" + f"20000,{finals[0]}\n30000,{finals[1]}\n")


def test_paired_forks_are_read_against_the_control_of_their_own_checkpoint(
        tmp_path: Path, load_bench: Callable[[str], ModuleType]) -> None:
    page = load_bench("results_page")
    forks = tmp_path / "forks"
    _fork(forks, "p0_none", 0, None, (90.0, 100.0))
    _fork(forks, "p0_escape", 0, "escape20", (0.0, 110.0))
    _fork(forks, "p1_none", 1, None, (0.0, 200.0))
    _fork(forks, "p1_escape", 1, "escape20", (0.0, 190.0))
    _fork(forks, "p0_explore", 0, None, (0.0, 80.0), settings=("agent.target_entropy=0",))  # an arm by setting
    spec = tmp_path / "results.toml"
    spec.write_text(f'''intro = "# Results"
[[table]]
kind = "pairs"
id = "p"
title = "Paired forks"
question = "Does the edit pay?"
runs = "{forks}"
arms = [["", "no edit"], ["escape20", "escape"], ["agent.target_entropy=0", "explore"]]
command = "mira train --fork ..."
''')
    meta, tables = page.load_spec(spec)

    lines = page.render(meta, tables, figures=None).splitlines()

    header = next(line for line in lines if line.startswith("| Parent"))
    assert "| no edit | escape | explore | escape vs control | explore vs control |" in header
    p0 = next(line for line in lines if line.startswith("| mira-no-mcm seed 0 at 10k"))
    assert "| 100.0 | 110.0 | 80.0 | +10.0% | -20.0% |" in p0  # the final 10% of 30k: the evaluation at 30k
    p1 = next(line for line in lines if line.startswith("| mira-no-mcm seed 1 at 10k"))
    assert "| 200.0 | 190.0 | — | -5.0% | — |" in p1
    means = next(line for line in lines if line.startswith("| over the 2 parents with a control"))
    assert "+2.5% [-5.0%, +10.0%]" in means and "-20.0% [-20.0%, -20.0%]" in means

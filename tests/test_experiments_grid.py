"""Sweep grids, presets, sweep files (TOML/YAML) and their errors; run planning; the CLI parsers."""

from __future__ import annotations

import argparse
import io
import json
import tempfile
import tomllib
from pathlib import Path

import pytest

from mira.errors import UsageError
from mira.experiments.cli import add_report_parser, add_sweep_parser, main
from mira.experiments.grid import (
    PAPER_SMALL_STEPS,
    RunSpec,
    SweepGrid,
    available_methods,
    build_grid,
    load_sweep_file,
    parse_seeds,
    preset_grid,
)
from mira.experiments.runs import Plan, plan_run, train_command
from mira.experiments.sweep import Progress, SweepOptions, dry_run
from mira.methods import METHODS


def _write(tmp_path: Path, name: str, text: str) -> Path:
    path = tmp_path / name
    path.write_text(text, encoding="utf-8")
    return path


def test_presets_read_methods_at_run_time() -> None:
    small = preset_grid("paper-small")
    assert set(small.methods) == set(METHODS) and small.methods[0] == "dense"
    assert small.algos == ["sac"] and small.tasks == ["halfcheetah", "humanoidstandup"]
    assert small.seeds == [0, 1, 2] and small.steps == PAPER_SMALL_STEPS
    paper = preset_grid("paper")
    assert paper.seeds == [0, 1, 2, 3, 4] and paper.steps == 1_000_000 and set(paper.algos) == {"sac", "ddpg"}
    assert paper.tasks == ["halfcheetah", "humanoidstandup", "humanoid"]  # Table A1's Humanoid SAC included
    assert len(paper.runs()) == len(METHODS) * 2 * 3 * 5
    with pytest.raises(UsageError, match="unknown preset"):
        preset_grid("huge")


def test_run_layout_and_order() -> None:
    grid = SweepGrid(["halfcheetah"], ["sparse", "dense"], ["sac"], [0, 1], 600)
    runs = grid.runs()
    assert [r.run_id for r in runs] == ["halfcheetah/sac/dense/seed0", "halfcheetah/sac/sparse/seed0",
                                        "halfcheetah/sac/dense/seed1", "halfcheetah/sac/sparse/seed1"]
    assert runs[0].run_dir("/x") == Path("/x/halfcheetah/sac/dense/seed0")
    assert RunSpec.from_dict(runs[1].to_dict()) == runs[1]


def test_parse_seeds_forms() -> None:
    assert parse_seeds(3) == [0, 1, 2]
    assert parse_seeds("3") == [0, 1, 2]
    assert parse_seeds("0,2,5") == [0, 2, 5]
    assert parse_seeds("7,") == [7]
    assert parse_seeds("2-4") == [2, 3, 4]
    assert parse_seeds([1, 9]) == [1, 9]
    for bad in ("x", "4-2", 0, [-1], True, 1.5):
        with pytest.raises(UsageError):
            parse_seeds(bad)


def test_toml_sweep_file(tmp_path: Path) -> None:
    path = _write(tmp_path, "s.toml", """
tasks = ["halfcheetah"]
methods = ["dense", "sparse"]
algos = "sac"
seeds = 2
steps = 600
workers = 2
train_args = "--eval-episodes 1"

[train]
learning-starts = 200
hidden = [16, 16]
quiet = true
""")
    grid, settings = build_grid(file=path)
    assert grid.methods == ["dense", "sparse"] and grid.algos == ["sac"] and grid.seeds == [0, 1]
    assert grid.train_args == ["--learning-starts", "200", "--hidden", "16,16", "--quiet",
                               "--eval-episodes", "1"]
    assert settings == {"workers": 2}


def test_yaml_sweep_file_preset_and_overrides(tmp_path: Path) -> None:
    path = _write(tmp_path, "s.yaml", "preset: paper-small\nseeds: [4, 5]\nbackend: ray\ncpus_per_run: 0.5\n")
    grid, settings = build_grid(file=path, overrides={"steps": 1000, "methods": ["dense"], "tasks": None})
    assert grid.preset == "paper-small" and grid.seeds == [4, 5] and grid.steps == 1000
    assert grid.methods == ["dense"] and grid.tasks == ["halfcheetah", "humanoidstandup"]
    assert settings["backend"] == "ray" and settings["cpus_per_run"] == 0.5 and settings["workers"] == 2
    assert load_sweep_file(_write(tmp_path, "all.yml", "methods: all\n"))["methods"] == available_methods()
    # train args accumulate (preset, then file, then flags); `mira train` keeps the last of a flag.
    grid, _ = build_grid(file=path, overrides={"train_args": ["--eval-episodes", "5"]})
    assert grid.train_args[-2:] == ["--eval-episodes", "5"] and "--learning-starts" in grid.train_args


def test_eta_from_completed_wall_times() -> None:
    progress = Progress(8, 2, SweepOptions(stream=io.StringIO(), tqdm=False))
    assert progress.eta_s(3, []) is None  # nothing completed yet
    progress.walls = [10.0, 10.0]
    assert progress.eta_s(1, []) == 10.0  # one pending run on an idle slot
    assert progress.eta_s(3, [4.0]) == 20.0  # remainder 6 on one slot; 3 × 10 spread over both
    assert progress.eta_s(0, [2.0, 5.0]) == 8.0


@pytest.mark.parametrize(
    ("name", "text", "needle"),
    [
        ("a.toml", "tasks = [\"halfcheetah\"\n", "invalid TOML"),
        ("b.yaml", "tasks: [halfcheetah\n", "invalid YAML"),
        ("c.yaml", "- halfcheetah\n", "top level must be a table"),
        ("d.toml", "taskz = [\"halfcheetah\"]\n", "unknown key 'taskz'"),
        ("e.toml", "methods = [\"dense\", \"magic\"]\n", "unknown method 'magic'"),
        ("f.toml", "algos = [\"ppo\"]\n", "unknown algo 'ppo'"),
        ("g.toml", "seeds = \"many\"\n", "seeds"),
        ("h.toml", "steps = -5\n", "steps must be an integer"),
        ("i.toml", "backend = \"slurm\"\n", "backend must be"),
        ("j.toml", "train_args = \"--out /elsewhere\"\n", "--out is set by the sweep grid"),
        ("k.toml", "train_args = \"--no-such-flag 3\"\n", "bad train args"),
        ("l.toml", "[train]\nbatch-size = \"big\"\n", "bad train args"),
        ("m.json", "{}", "unsupported extension"),
        ("n.toml", "tasks = [\"nowhere.toml\"]\n", "does not exist"),
        ("o.toml", "tasks = [\"mars\"]\n", "unknown task 'mars'"),
        ("p.toml", "methods = 3\n", "expected a list of names"),
        ("q.toml", "train_args = \"--show-config\"\n", "trains nothing: use it with mira train"),
    ],
)
def test_bad_sweep_files_raise_one_line_usage_errors(tmp_path: Path, name: str, text: str,
                                                      needle: str) -> None:
    path = _write(tmp_path, name, text)
    # Axes the file does not set come from flags, so that the error is the file's own.
    defaults = {"tasks": ["halfcheetah"], "methods": ["dense"], "algos": ["sac"], "seeds": [0], "steps": 100}
    set_by_file = {line.split("=", 1)[0].strip() for line in text.splitlines() if "=" in line}
    overrides = {k: v for k, v in defaults.items() if k not in set_by_file}
    with pytest.raises(UsageError) as info:
        build_grid(file=path, overrides=overrides)
    message = str(info.value)
    assert "\n" not in message
    assert needle in message


def test_missing_grid_axis_is_a_usage_error(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="no steps given"):
        build_grid(overrides={"tasks": ["halfcheetah"], "methods": ["dense"], "algos": ["sac"], "seeds": [0]})


def _fake_run(run: Path, *, method: str = "dense", steps: int = 600, status: str = "finished",
              step: int = 600, checkpoint: bool = True) -> None:
    run.mkdir(parents=True)
    cfg = {"task": "halfcheetah", "method": method, "algo": "sac", "seed": 0, "steps": steps}
    (run / "config.json").write_text(json.dumps({"config": cfg}))
    (run / "status.json").write_text(json.dumps({"status": status, "step": step}))
    if checkpoint:
        (run / "checkpoints").mkdir()
        (run / "checkpoints" / "ckpt-0000000200.json").write_text("{}")


def test_plan_run_decisions(tmp_path: Path) -> None:
    spec = RunSpec("halfcheetah", "dense", "sac", 0, 600)
    assert plan_run(spec, tmp_path).action == "start"
    run = spec.run_dir(tmp_path)
    _fake_run(run)
    assert plan_run(spec, tmp_path).action == "skip"
    (run / "status.json").write_text(json.dumps({"status": "running", "step": 0}))
    plan = plan_run(spec, tmp_path)
    assert plan.action == "resume"
    assert train_command(spec, tmp_path, plan)[-5:] == ["--resume", str(run), "--steps", str(spec.steps), "--quiet"]
    for p in (run / "checkpoints").iterdir():
        p.unlink()
    plan = plan_run(spec, tmp_path)
    assert plan == Plan("start", plan.reason, overwrite=True)
    assert "--overwrite" in train_command(spec, tmp_path, plan)
    shorter = RunSpec("halfcheetah", "dense", "sac", 0, 300)
    conflict = plan_run(shorter, tmp_path)
    assert conflict.action == "conflict" and "steps=600" in conflict.reason
    # A longer budget extends the finished run from its last checkpoint.
    (run / "checkpoints" / "ckpt-0000000600.json").write_text("{}")
    longer = RunSpec("halfcheetah", "dense", "sac", 0, 900)
    plan = plan_run(longer, tmp_path)
    assert plan.action == "resume" and "extend from 600 to 900" in plan.reason
    assert train_command(longer, tmp_path, plan)[-5:] == ["--resume", str(run), "--steps", "900", "--quiet"]
    (run / "config.json").write_text("{torn")
    assert plan_run(spec, tmp_path) == Plan("start", plan_run(spec, tmp_path).reason, overwrite=True)


def test_dry_run_writes_nothing(tmp_path: Path) -> None:
    grid = SweepGrid(["halfcheetah"], ["dense", "sparse"], ["sac"], [0], 600, ["--eval-episodes", "1"])
    out = tmp_path / "out"
    buf = io.StringIO()
    plans = dry_run(grid, out, stream=buf)
    assert [p.action for _, p in plans] == ["start", "start"]
    assert "--eval-episodes 1 --quiet" in buf.getvalue() and "2 runs: 2 start" in buf.getvalue()
    assert not out.exists()


def test_cli_parsers_register_and_report_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    parser = argparse.ArgumentParser(prog="mira")
    sub = parser.add_subparsers(dest="command", required=True)
    add_sweep_parser(sub)
    add_report_parser(sub)
    args = parser.parse_args(["sweep", "--tasks", "halfcheetah", "--methods", "dense,sparse",
                              "--algos", "sac", "--seeds", "2", "--steps", "600",
                              "--out", str(tmp_path / "o"), "--workers", "2",
                              "--train-args", "--eval-episodes 1", "--dry-run"])
    assert args.func(args) == 0
    assert "halfcheetah/sac/sparse/seed1" in capsys.readouterr().out
    args = parser.parse_args(["report", str(tmp_path / "a"), str(tmp_path / "b"),
                              "--out", str(tmp_path / "r")])
    assert args.paths == [str(tmp_path / "a"), str(tmp_path / "b")] and callable(args.func)

    bad = _write(tmp_path, "bad.toml", "tasks = [\n")
    assert main(["sweep", "--file", str(bad), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("mira sweep: error: sweep file") and "invalid TOML" in err and "\n" not in err
    assert main(["report", str(tmp_path / "missing"), "--out", str(tmp_path / "r")]) == 2


def test_dry_run_estimates_the_time_from_the_speeds_runs_here_logged(tmp_path: Path) -> None:
    grid = SweepGrid(["halfcheetah"], ["dense", "sparse"], ["sac"], [0, 1], 600, [])
    buf = io.StringIO()
    dry_run(grid, tmp_path, stream=buf)
    assert "estimate: none, no run here has logged its speed" in buf.getvalue()
    run = RunSpec("halfcheetah", "dense", "sac", 0, 600).run_dir(tmp_path)
    _fake_run(run, status="running", step=300)
    (run / "train.csv").write_text("step,steps_per_s\n100,2.0\n200,1.0\n300,1.0\n")
    buf = io.StringIO()
    dry_run(grid, tmp_path, stream=buf, workers=2)
    # dense: 300 steps left of seed 0 and 600 of seed 1 at 1 step/s = 900 s, on 2 workers = 0.125 h.
    assert "estimate: 0.1 h with 2 worker(s)" in buf.getvalue()
    assert "not counted: halfcheetah/sac/sparse" in buf.getvalue()


def test_dry_run_probes_what_no_run_here_has_timed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A (task, algo, method) with logged speeds is not probed; the others are, once each, and a failed
    probe leaves its runs out of the estimate with the reason printed."""
    from mira.experiments import estimate, sweep

    grid = SweepGrid(["halfcheetah"], ["dense", "sparse", "vib"], ["sac"], [0, 1], 3600, [])
    run = RunSpec("halfcheetah", "dense", "sac", 0, 3600).run_dir(tmp_path)
    _fake_run(run, status="running", step=0, steps=3600, checkpoint=False)
    (run / "train.csv").write_text("step,steps_per_s\n100,1.0\n")
    asked: list[str] = []

    def fake_probe(spec: RunSpec) -> estimate.ProbeResult:
        asked.append(spec.method)
        if spec.method == "vib":
            return estimate.ProbeResult(estimate.speed_key(spec), None, "boom")
        return estimate.ProbeResult(estimate.speed_key(spec), 2.0)

    monkeypatch.setattr(sweep, "probe_speed", fake_probe)
    buf = io.StringIO()
    dry_run(grid, tmp_path, stream=buf, workers=2, probe=True)
    text = buf.getvalue()
    assert sorted(asked) == ["sparse", "vib"]
    assert "probing halfcheetah/sac/sparse" in text and "2.0 steps/s" in text and "failed (boom)" in text
    # dense: 2 × 3600 steps at 1 step/s; sparse: 2 × 3600 at 2 steps/s; 10800 s on 2 workers = 1.5 h.
    assert "estimate: 1.5 h with 2 worker(s), at the steps/s of the runs here and of the probes" in text
    assert "not counted: halfcheetah/sac/vib" in text


def test_a_probe_times_a_real_short_run_and_reports_a_failing_one(tmp_path: Path) -> None:
    from mira.experiments.estimate import probe_command, probe_speed

    spec = RunSpec("halfcheetah", "sparse", "sac", 0, 50_000, ["--threads", "1", "--learning-starts", "9"])
    cmd = probe_command(spec, tmp_path / "r", warmup=300, measured=200)
    # The probe's budget comes after the grid's train args, so it wins.
    assert cmd.index("--learning-starts", cmd.index("9")) > cmd.index("9")
    result = probe_speed(spec, warmup=300, measured=200)
    assert result.steps_per_s is not None and result.steps_per_s > 0, result.error
    bad = probe_speed(RunSpec("nosuchtask", "sparse", "sac", 0, 600), warmup=300, measured=200)
    assert bad.steps_per_s is None and "nosuchtask" in bad.error
    assert not list(Path(tempfile.gettempdir()).glob("mira-probe-*/run/config.json"))


def test_the_paper_preset_runs_every_run_with_table_1(tmp_path: Path) -> None:
    """``mira sweep --preset paper --dry-run``: every command carries ``--preset paper``, whose assignments
    (Table 1's learning rate, ΔT 5,000) are printed, and Humanoid SAC is among the runs."""
    import io

    from mira.experiments.sweep import dry_run

    grid = preset_grid("paper")
    out = io.StringIO()
    plans = dry_run(grid, tmp_path / "paper", stream=out)
    text = out.getvalue()
    assert "agent.lr=1e-4" in text and "hars.lr=1e-4" in text and "mira.mcm.delta_t=5000" in text
    commands = [line for line in text.splitlines() if "$ " in line]
    assert len(commands) == len(plans) == len(grid.runs())
    assert all("--preset paper" in line for line in commands)
    assert any("--task humanoid " in line and "--algo sac" in line for line in commands)


def test_a_programs_axis_gives_each_initial_program_its_runs(tmp_path: Path) -> None:
    flawed = _write(tmp_path, "no_progress.json", "{}")
    grid = SweepGrid(["halfcheetah"], ["hars"], ["sac"], [0], 600, programs=["", str(flawed)]).validate()
    runs = grid.runs()
    assert [r.run_id for r in runs] == ["halfcheetah/sac/hars/seed0", "halfcheetah/no_progress/sac/hars/seed0"]
    assert runs[1].run_dir("/x") == Path("/x/halfcheetah/no_progress/sac/hars/seed0")
    assert RunSpec.from_dict(runs[1].to_dict()) == runs[1]
    start = train_command(runs[1], tmp_path, Plan("start", "new run"))
    assert start[start.index("--program") + 1] == str(flawed)
    assert "--program" not in train_command(runs[0], tmp_path, Plan("start", "new run"))
    # A run directory that holds a run of another initial program is not taken for this one's.
    _fake_run(runs[1].run_dir(tmp_path), method="hars")
    conflict = plan_run(runs[1], tmp_path)
    assert conflict.action == "conflict" and "the task's own program" in conflict.reason


def test_a_sweep_file_names_programs_beside_it_and_the_task_own(tmp_path: Path) -> None:
    (tmp_path / "flawed").mkdir()
    _write(tmp_path / "flawed", "wrong_gate.json", "{}")
    path = _write(tmp_path, "s.toml", 'tasks = ["halfcheetah"]\nprograms = ["task", "flawed/wrong_gate.json"]\n'
                                      'methods = ["mira"]\nalgos = ["sac"]\nseeds = 1\nsteps = 600\n')
    grid, _ = build_grid(file=path)
    assert grid.programs == ["", str((tmp_path / "flawed" / "wrong_gate.json").resolve())]
    assert len(grid.runs()) == 2


@pytest.mark.parametrize("programs, message", [
    (["missing.json"], "initial program .*missing.json does not exist"),
    (["a/x.json", "b/x.json"], "two initial programs share a directory name"),
])
def test_bad_programs_are_usage_errors(tmp_path: Path, programs: list[str], message: str) -> None:
    for sub in ("a", "b"):
        (tmp_path / sub).mkdir()
        _write(tmp_path / sub, "x.json", "{}")
    with pytest.raises(UsageError, match=message):
        SweepGrid(["halfcheetah"], ["mira"], ["sac"], [0], 600,
                  programs=[str(tmp_path / p) for p in programs]).validate()
    with pytest.raises(UsageError, match="--program is set by the sweep grid"):
        SweepGrid(["halfcheetah"], ["mira"], ["sac"], [0], 600, ["--program", "x.json"]).validate()


SWEEP_FILES = sorted(p for p in (Path(__file__).parents[1] / "bench").glob("*/*.toml")
                     if "tasks" in tomllib.loads(p.read_text()))  # the flaw lists beside them are not sweeps


@pytest.mark.parametrize("path", SWEEP_FILES, ids=lambda p: f"{p.parent.name}/{p.name}")
def test_every_benchmark_sweep_file_builds_its_grid(path: Path) -> None:
    # The results page prints these files as its tables' commands: each must build a grid as it stands.
    grid, _ = build_grid(file=path)
    assert grid.tasks and grid.methods and grid.seeds


def test_a_dry_run_needs_no_out_and_a_real_sweep_does(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    from mira.cli import main

    monkeypatch.chdir(tmp_path)
    grid = ["sweep", "--tasks", "halfcheetah", "--methods", "dense", "--algos", "sac", "--seeds", "2", "--steps", "1"]
    assert main([*grid, "--dry-run", "--no-probe"]) == 0
    printed = capsys.readouterr().out
    assert "--out OUT/halfcheetah/sac/dense/seed1" in printed
    assert list(tmp_path.iterdir()) == []
    assert main(grid) == 2
    assert "--out DIR is required" in capsys.readouterr().err

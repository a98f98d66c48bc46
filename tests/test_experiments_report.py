"""Reports from synthetic run directories with hand-computed metrics (no training)."""

from __future__ import annotations

import csv
import json
import struct
from collections.abc import Callable
from pathlib import Path

import pytest

from mira.errors import UsageError
from mira.experiments.report import discover_runs, write_report

N = 100_000
EVERY = 5_000
ENV_IDS = {"halfcheetah": "HalfCheetah-v5", "humanoidstandup": "HumanoidStandup-v5"}


def make_run(root: Path, task: str, algo: str, method: str, seed: int, curve: Callable[[int], float], *,
             status: str = "finished", last: int = N, diagnostics: bool = False, attention: bool = False,
             decisions: tuple[tuple[int, bool], ...] = (), program: str | None = None) -> Path:
    run = root / task / (Path(program).stem if program else "") / algo / method / f"seed{seed}"
    run.mkdir(parents=True)
    cfg = {"task": task, "method": method, "algo": algo, "seed": seed, "steps": N, "program": program,
           "eval_every": EVERY}
    card = {"name": task, "env_id": ENV_IDS[task]}
    (run / "config.json").write_text(json.dumps({"config": cfg, "task_card": card}))
    (run / "status.json").write_text(json.dumps({"status": status, "step": last}))
    rows = ["step,return_mean,return_std,length_mean,episodes,wall_s"]
    rows += [f"{t},{curve(t)!r},0.0,1000.0,1,{t / 1000}" for t in range(EVERY, last + 1, EVERY)]
    (run / "eval.csv").write_text("\n".join(rows) + "\n")
    train = ["step,critic_loss" + (",attn_r_vel,attn_r_upright" if attention else "")]
    for t in range(1000, last + 1, 1000):
        a = t / N
        train.append(f"{t},0.5" + (f",{1 - 0.5 * a},{0.5 * a}" if attention else ""))
    (run / "train.csv").write_text("\n".join(train) + "\n")
    if diagnostics:
        diag = ["cycle,step,score,threshold,trigger,warmup"]
        for k, t in enumerate(range(5000, last + 1, 5000)):
            score = "nan" if k < 3 else str(2.0 + (5.0 if t in (35000, 40000) else 0.0))
            thr = "nan" if k < 3 else "4.0"
            diag.append(f"{k},{t},{score},{thr},{int(t == 40000)},{int(k < 3)}")
        (run / "diagnostics.csv").write_text("\n".join(diag) + "\n")
    for i, (step, accepted) in enumerate(decisions):
        d = run / "interventions" / f"{i:03d}"
        d.mkdir(parents=True)
        (d / "decision.json").write_text(json.dumps({"accepted": accepted, "step": step}))
    return run


@pytest.fixture
def runs(tmp_path: Path) -> Path:
    root = tmp_path / "sweep"
    for s in range(3):
        make_run(root, "halfcheetah", "sac", "dense", s, lambda t, s=s: t / 1000 + s)
        make_run(root, "halfcheetah", "sac", "mira", s, lambda t, s=s: t / 500 + 10 * s,
                 diagnostics=s == 0, attention=s == 0, decisions=((40000, True), (60000, False)) if s == 0 else ())
        make_run(root, "halfcheetah", "sac", "mira-no-mcm", s, lambda t, s=s: t / 1000 if s else 0.0)
        make_run(root, "halfcheetah", "sac", "mira-no-srr", s, lambda t: t / 2000)
        make_run(root, "halfcheetah", "sac", "sparse", s, lambda t: -5.0)
        make_run(root, "humanoidstandup", "sac", "dense", s, lambda t: -100.0)
        make_run(root, "humanoidstandup", "sac", "sparse", s, lambda t: -200 + t / 1000)
        make_run(root, "halfcheetah", "ddpg", "dense", s, lambda t, s=s: t / 1000 + s)
        make_run(root, "halfcheetah", "ddpg", "sparse", s, lambda t: 1.0)
    make_run(root, "halfcheetah", "sac", "vib", 0, lambda t: 50.0, status="running", last=50_000)
    return root


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", data[16:24])


def test_tables_have_hand_computed_cells(runs: Path, tmp_path: Path) -> None:
    out = tmp_path / "report"
    result = write_report([runs], out, bootstrap_reps=2000)
    table = (out / "table_sac.md").read_text()
    lines = {line.split(" | ")[0].strip("| "): line for line in table.splitlines() if line.startswith("|")}
    # Dense: asymptotic = mean(95 + s, 100 + s) = 97.5 + s → 98.5 ± 1.0; reaches 49.25 at 50k → 0.50.
    assert lines["Dense R (oracle)"].startswith("| Dense R (oracle) | 98.5 ± 1.0 | 0.50 ± 0.00 | −100.0 ± 0.0 |")
    # MIRA: 195 + 10 s → 205.0 ± 10.0; first ≥ 49.25 at 25k, 20k, 15k → 0.20 ± 0.05.
    assert "| MIRA | 205.0 ± 10.0 | 0.20 ± 0.05 |" in lines["MIRA"]
    # w/o MCM: seed 0 never learns → 2 of 3 seeds reach the bar.
    assert "| 65.0 ± 56.3 | 0.50 ± 0.00 (2/3) |" in lines["MIRA w/o MCM"]
    assert "| 48.8 ± 0.0 | 1.00 ± 0.00 |" in lines["MIRA w/o SRR"]
    # Sparse never reaches 50% of the oracle on HalfCheetah; on HumanoidStandup the oracle is −100,
    # so the bar is −150 (not −50), reached at 50k.
    assert lines["Sparse R"] == "| Sparse R | −5.00 ± 0.00 | — | −102.5 ± 0.0 | 0.50 ± 0.00 |"
    assert "VIB" not in lines  # incomplete run left out ...
    assert any("vib/seed0: running at step 50000" in n for n in result.notes)  # ... and said so
    assert "HalfCheetah: Asymptotic Perf." in table and "HumanoidStandup: Sample Eff. (×10^5)" in table

    metrics = {(r["algo"], r["task"], r["method"]): r for r in _rows(out / "metrics.csv")}
    hs = metrics[("sac", "humanoidstandup", "sparse")]
    assert float(hs["oracle_asymptotic"]) == -100.0 and float(hs["threshold"]) == -150.0
    assert float(hs["sample_eff_steps_mean"]) == 50_000
    assert metrics[("sac", "halfcheetah", "sparse")]["sample_eff_steps_mean"] == ""
    assert metrics[("sac", "halfcheetah", "mira")]["reached"] == "3"
    table_csv = {r["method"]: r for r in _rows(out / "table_sac.csv")}
    assert float(table_csv["mira"]["halfcheetah:sample_eff_1e5_mean"]) == pytest.approx(0.2)
    assert table_csv["sparse"]["halfcheetah:sample_eff_1e5_mean"] == ""
    # DDPG gets its own table.
    ddpg = (out / "table_ddpg.md").read_text()
    assert "Table 2" in ddpg and "| Sparse R | 1.00 ± 0.00 | — |" in ddpg

    agg = {(r["algo"], r["method"]): r for r in _rows(out / "aggregate.csv")}
    assert float(agg[("sac", "dense")]["normalized_iqm"]) == pytest.approx(1.0, abs=0.02)
    assert agg[("sac", "mira")]["tasks"] == "halfcheetah"  # negative oracle task left out, with a note
    assert any("left out of the normalised aggregate" in n and "humanoidstandup" in n for n in result.notes)
    runs_csv = _rows(out / "runs.csv")
    assert len(runs_csv) == 28 and sum(r["used"] == "1" for r in runs_csv) == 27


def test_figures_and_per_run_diagnostics(runs: Path, tmp_path: Path) -> None:
    out = tmp_path / "report"
    result = write_report([runs], out, bootstrap_reps=500)
    assert _png_size(out / "curves_sac.png") == (1200, 480)  # 10 × 4 in at 120 dpi
    assert _png_size(out / "curves_ddpg.png") == (1200, 480)
    assert (out / "ablation_sac.png").is_file() and not (out / "ablation_ddpg.png").exists()
    per_run = sorted(p.name for p in (out / "runs").iterdir())
    assert per_run == ["halfcheetah_sac_mira_seed0.png"]  # runs without diagnostics are skipped
    md = (out / "report.md").read_text()
    for name in ("curves_sac.png", "curves_ddpg.png", "ablation_sac.png", "runs/halfcheetah_sac_mira_seed0.png"):
        assert f"({name})" in md
        assert out / name in result.files


def test_include_incomplete_and_reproducible(runs: Path, tmp_path: Path) -> None:
    a = write_report([runs], tmp_path / "a", bootstrap_reps=1000, plots=False)
    b = write_report([runs], tmp_path / "b", bootstrap_reps=1000, plots=False)
    assert (tmp_path / "a" / "metrics.csv").read_text() == (tmp_path / "b" / "metrics.csv").read_text()
    assert not list((tmp_path / "a").glob("*.png")) and len(a.cells) == len(b.cells)
    c = write_report([runs], tmp_path / "c", include_incomplete=True, plots=False)
    vib = next(x for x in c.cells if x.method == "vib")
    assert vib.asymptotic == [50.0]  # its last evaluation stands in for the final window


def test_discovery_and_errors(runs: Path, tmp_path: Path) -> None:
    one = runs / "halfcheetah" / "sac" / "dense" / "seed0"
    found = discover_runs([runs, one])
    assert len(found) == 28 and found.count(one.resolve()) == 1
    assert discover_runs([one]) == [one.resolve()]
    with pytest.raises(UsageError, match="does not exist"):
        write_report([tmp_path / "nope"], tmp_path / "r")
    (tmp_path / "empty").mkdir()
    with pytest.raises(UsageError, match="no run directories"):
        write_report([tmp_path / "empty"], tmp_path / "r")


def test_a_duplicate_run_is_taken_from_the_path_named_first(tmp_path: Path) -> None:
    # The same (algo, task, program, method, seed) under two roots, e.g. a rerun beside an archive: the
    # caller's order decides which is tabulated, whatever the roots' names sort as.
    make_run(tmp_path / "z_rerun", "halfcheetah", "sac", "hars", 0, lambda t: 2.0)
    make_run(tmp_path / "a_archive", "halfcheetah", "sac", "hars", 0, lambda t: 1.0)
    roots = [tmp_path / "z_rerun", tmp_path / "a_archive"]
    first = write_report(roots, tmp_path / "r1", bootstrap_reps=100, plots=False)
    assert [c.asymptotic for c in first.cells] == [[2.0]]
    assert any("duplicate" in n and "a_archive" in n.rsplit(";", 1)[1] for n in first.notes)
    second = write_report(roots[::-1], tmp_path / "r2", bootstrap_reps=100, plots=False)
    assert [c.asymptotic for c in second.cells] == [[1.0]]


def test_a_diagnosis_without_an_edit_is_reported(tmp_path: Path) -> None:
    # mira-no-srr diagnoses a structural flaw and installs nothing: only diagnostics.csv records it.
    run = make_run(tmp_path / "runs", "halfcheetah", "sac", "mira-no-srr", 0, lambda t: 1.0,
                   program="no_progress.json")
    rows = ["cycle,step,trigger,returns_cv_r2,unexplained_gain,unexplained,structural_flaw",
            "0,5000,0,0.1,0.9,x_velocity,0", "1,10000,0,0.1,0.89,x_velocity,1", "2,15000,0,0.05,0.95,x_velocity,1"]
    (run / "diagnostics.csv").write_text("\n".join(rows) + "\n")
    make_run(tmp_path / "runs", "halfcheetah", "sac", "hars", 0, lambda t: 1.0, program="no_progress.json")
    write_report([tmp_path / "runs"], tmp_path / "r", bootstrap_reps=100, plots=False)
    md = (tmp_path / "r" / "report.md").read_text()
    table = md.split("## Structural diagnoses", 1)[1]
    assert "mira-no-srr" in table and "| 10000 | 2 | x_velocity | 0.10 → 0.99 |" in table
    assert "/hars/" not in table and "## Interventions" not in md  # nothing was installed anywhere


def test_per_run_plots_only_for_factor_attention_or_decomposition_shares(tmp_path: Path) -> None:
    # The head's shares are the agent's reward, so a run that logs them but no attention gets a plot; a
    # share column never filled (before the head's first fit) does not count.
    root = tmp_path / "runs"
    shares = make_run(root, "halfcheetah", "sac", "hars", 2, lambda t: t / 1000)
    (shares / "train.csv").write_text("step,share_r_vel,share_r_ctrl\n1000,,\n2000,0.9,0.1\n")
    empty = make_run(root, "halfcheetah", "sac", "hars", 3, lambda t: t / 1000)
    (empty / "train.csv").write_text("step,share_r_vel\n1000,\n2000,\n")
    summary_only = make_run(root, "halfcheetah", "sac", "hars", 0, lambda t: t / 1000)
    (summary_only / "train.csv").write_text("step,attn_entropy\n1000,0.5\n2000,0.4\n")
    with_program = make_run(root, "halfcheetah", "sac", "hars", 1, lambda t: t / 1000)
    (with_program / "train.csv").write_text("step,attn_entropy,attn_r_vel\n1000,0.5,0.7\n2000,0.4,0.6\n")
    (with_program / "programs").mkdir()
    (with_program / "programs" / "v000.json").write_text(json.dumps({"factors": [{"name": "r_vel"}]}))
    write_report([root], tmp_path / "report", bootstrap_reps=200)
    assert sorted(p.name for p in (tmp_path / "report" / "runs").iterdir()) == [
        "halfcheetah_sac_hars_seed1.png", "halfcheetah_sac_hars_seed2.png"]
    # Only the runs with a recorded intervention, or none: the per-run figures are what make a large
    # report large.
    (shares / "interventions" / "000-step2000").mkdir(parents=True)
    (shares / "interventions" / "000-step2000" / "decision.json").write_text(json.dumps({"accepted": False}))
    write_report([root], tmp_path / "some", bootstrap_reps=200, run_plots="interventions")
    assert [p.name for p in (tmp_path / "some" / "runs").iterdir()] == ["halfcheetah_sac_hars_seed2.png"]
    write_report([root], tmp_path / "none", bootstrap_reps=200, run_plots="none")
    assert not (tmp_path / "none" / "runs").exists() and (tmp_path / "none" / "report.md").is_file()
    with pytest.raises(UsageError, match="run plots must be one of"):
        write_report([root], tmp_path / "bad", bootstrap_reps=200, run_plots="some")


def _structural_repair(run: Path, step: int) -> None:
    """An intervention as the outer loop records it: the returns' evidence, the decision, and the two
    program versions (the second adds a factor)."""
    folder = run / "interventions" / f"000-step{step}"
    folder.mkdir(parents=True)
    gains = [{"feature": "x_velocity", "form": "value", "cv_r2": 0.99, "gain": 0.62}]
    (folder / "evidence.json").write_text(json.dumps({
        "step": step, "cause": "structural", "return_attribution": {"program_cv_r2": 0.37, "feature_gains": gains}}))
    (folder / "decision.json").write_text(json.dumps({"accepted": True, "operators": ["Add"], "version": 1,
                                                      "reason": "accepted candidate 0"}))
    (run / "programs").mkdir()
    old = [{"name": "r_posture", "code": "def r_posture(s):\n    return -s.pitch ** 2\n"}]
    new = [*old, {"name": "r_x_velocity", "code": "def r_x_velocity(s):\n    return s.x_velocity\n"}]
    (run / "programs" / "v000.json").write_text(json.dumps({"factors": old}))
    (run / "programs" / "v001.json").write_text(json.dumps({"factors": new}))


def test_runs_from_program_files_are_their_own_columns_with_their_interventions(tmp_path: Path) -> None:
    """Runs that differ only in their initial program are not duplicates: each program file is a column
    and a curve panel of its own, a per-program table lists them, the aggregate counts the task's own
    program only, and every intervention is listed with its edit and the return around it."""
    root = tmp_path / "flawed"
    for s in range(2):
        make_run(root, "halfcheetah", "sac", "dense", s, lambda t: 100.0)
        make_run(root, "halfcheetah", "sac", "hars", s, lambda t, s=s: 80.0 + s)
        make_run(root, "halfcheetah", "sac", "hars", s, lambda t: 3.0, program="/x/flaws/no_progress.json")
        repaired = make_run(root, "halfcheetah", "sac", "mira", s, lambda t: t / 1000,
                            program="/x/flaws/no_progress.json")
        if s == 0:
            _structural_repair(repaired, 20_000)
    out = tmp_path / "report"
    result = write_report([root], out, bootstrap_reps=200)
    assert not [n for n in result.notes if "duplicate" in n]
    assert len(result.runs) == 8 and sum(len(c.seeds) for c in result.cells) == 8
    metrics = {(r["task"], r["program"], r["method"]): r for r in _rows(out / "metrics.csv")}
    assert float(metrics[("halfcheetah", "", "hars")]["asymptotic_mean"]) == 80.5
    assert float(metrics[("halfcheetah", "no_progress", "hars")]["asymptotic_mean"]) == 3.0
    # mira: mean of the 95k and 100k evaluations (95 and 100) on both seeds.
    assert float(metrics[("halfcheetah", "no_progress", "mira")]["asymptotic_mean"]) == 97.5
    md = (out / "report.md").read_text()
    assert "HalfCheetah · no_progress: Asymptotic Perf." in md
    assert "SAC on HalfCheetah by initial program" in md
    by_program = {ln.split(" | ")[0]: ln for ln in md.split("by initial program")[1].splitlines()
                  if ln.startswith("| ")}
    assert "80.5 [80.0, 81.0] (2)" in by_program["| the task's own"]
    assert "| mean 97.5 [97.5, 97.5] (2) | mean 3.00 [3.00, 3.00] (2) |" in by_program["| no_progress"]
    agg = {(r["algo"], r["method"]): r for r in _rows(out / "aggregate.csv")}
    assert agg[("sac", "hars")]["runs"] == "2"  # the flawed program's hars runs are not in the aggregate
    assert any("program file are left out of the normalised aggregate" in n for n in result.notes)
    rows = _rows(out / "interventions.csv")
    assert len(rows) == 1
    row = rows[0]
    assert (row["program"], row["method"], row["seed"], row["step"]) == ("no_progress", "mira", "0", "20000")
    assert row["edit"] == "Add: +r_x_velocity" and row["accepted"] == "1"
    assert "structural flaw" in row["why"] and "x_velocity" in row["why"]
    # The evaluations within three intervals: 10k, 15k, 20k before (mean 15); 25k, 30k, 35k after (mean 30).
    assert float(row["return_before"]) == 15.0 and float(row["return_after"]) == 30.0
    assert "## Interventions" in md and "halfcheetah[no_progress]/sac/mira/seed0 | 20000 |" in md
    assert (out / "curves_sac.png").is_file()


def test_three_seeds_get_mean_and_min_max_not_a_confidence_interval(runs: Path, tmp_path: Path) -> None:
    """A bootstrap over 3 seeds only restates their [min, max] and an IQM of 3 trims nothing: the report says
    mean [min, max] for such cells and prints no "95% CI"; with 5 seeds the IQM and its interval appear."""
    md = (write_report([runs], tmp_path / "r3", bootstrap_reps=200, plots=False).out_dir / "report.md").read_text()
    assert "95%" not in md
    # mira's seeds average 195 + 10·s over the final 10%: mean 205, [195, 215]
    assert "mean 205.0 [195.0, 215.0]" in md
    for s in range(3, 5):
        make_run(runs, "halfcheetah", "sac", "mira", s, lambda t, s=s: t / 500 + 10 * s)
    md5 = (write_report([runs], tmp_path / "r5", bootstrap_reps=200, plots=False).out_dir / "report.md").read_text()
    assert "IQM [95% bootstrap CI] where a cell has at least 5 seeds" in md5
    assert "mean 205.0 [195.0, 215.0]" not in md5

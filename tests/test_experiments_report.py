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
             decisions: tuple[tuple[int, bool], ...] = ()) -> Path:
    run = root / task / algo / method / f"seed{seed}"
    run.mkdir(parents=True)
    cfg = {"task": task, "method": method, "algo": algo, "seed": seed, "steps": N}
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


def test_per_run_plots_only_for_factor_attention(tmp_path: Path) -> None:
    root = tmp_path / "runs"
    summary_only = make_run(root, "halfcheetah", "sac", "hars", 0, lambda t: t / 1000)
    (summary_only / "train.csv").write_text("step,attn_entropy\n1000,0.5\n2000,0.4\n")
    with_program = make_run(root, "halfcheetah", "sac", "hars", 1, lambda t: t / 1000)
    (with_program / "train.csv").write_text("step,attn_entropy,attn_r_vel\n1000,0.5,0.7\n2000,0.4,0.6\n")
    (with_program / "programs").mkdir()
    (with_program / "programs" / "v000.json").write_text(json.dumps({"factors": [{"name": "r_vel"}]}))
    write_report([root], tmp_path / "report", bootstrap_reps=200)
    assert sorted(p.name for p in (tmp_path / "report" / "runs").iterdir()) == ["halfcheetah_sac_hars_seed1.png"]

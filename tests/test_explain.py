"""``mira explain`` on a hand-made run directory: counts read right, the final program and the
decomposition are named."""

from __future__ import annotations

import json
from pathlib import Path

from mira.explain import explain


def _run(tmp_path: Path, triggers: list[int], versions: int) -> Path:
    run = tmp_path / "run"
    (run / "programs").mkdir(parents=True)
    config = {"method": "mira", "task": "halfcheetah", "algo": "sac", "seed": 0, "steps": 20000, "eval_every": 5000}
    (run / "config.json").write_text(json.dumps({"config": config}))
    for v in range(versions):
        (run / "programs" / f"v{v:03d}.json").write_text(json.dumps(
            {"task": "halfcheetah", "version": v, "factors": [{"name": "r_vel", "type": "PHI"}]}))
    rows = ["step,trigger"] + [f"{s},{int(s in triggers)}" for s in (5000, 10000, 15000, 20000)]
    (run / "diagnostics.csv").write_text("\n".join(rows) + "\n")
    (run / "train.csv").write_text("step,w_r_vel,w_bias,share_r_vel,decomp_r2\n20000,0.95,-0.1,1.0,0.99\n")
    return run


def test_one_trigger_is_singular_and_the_final_version_is_named(tmp_path: Path) -> None:
    text = explain(_run(tmp_path, [10000], versions=2))
    assert "4 cycles, 1 anomaly trigger (at step 10000)." in text
    assert "ended on program v1 (versions: 0, 1)" in text
    assert "r_vel +0.95 (100%)" in text and "R² of returns 0.990" in text


def test_several_triggers_are_plural(tmp_path: Path) -> None:
    text = explain(_run(tmp_path, [10000, 15000], versions=1))
    assert "2 anomaly triggers (at steps 10000, 15000)." in text
    assert "ended on program" not in text


def test_a_structural_diagnosis_is_told_and_an_ablation_without_srr_says_it_did_not_act(tmp_path: Path) -> None:
    run = _run(tmp_path, [], versions=1)
    rows = ["step,trigger,returns_cv_r2,unexplained_gain,unexplained,structural_flaw",
            "5000,0,,,,", "10000,0,0.5,0.2,x_velocity,0", "15000,0,-0.25,1.2,x_velocity,1",
            "20000,0,-0.3,1.3,x_velocity,1"]
    (run / "diagnostics.csv").write_text("\n".join(rows) + "\n")
    text = explain(run)
    assert ("called the program flawed on 2 cycles, first at step 15000 (with x_velocity its factors would "
            "explain them with R² 0.95 instead of -0.25).") in text
    config = json.loads((run / "config.json").read_text())
    config["config"]["method"] = "mira-no-srr"
    (run / "config.json").write_text(json.dumps(config))
    assert "this method has no SRR, so the diagnosis was logged and nothing was installed." in explain(run)
    (run / "diagnostics.csv").write_text("\n".join(r.rsplit(",", 1)[0] for r in rows) + "\n")  # an older run
    assert "Structural check" not in explain(run)

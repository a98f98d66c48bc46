"""A run records what decides its arithmetic (CPU model and capability, torch, GEMM backend), and a
resume on a machine that differs in any of them says so instead of passing for a bit-exact continuation."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest

from mira.cli import REPRODUCIBILITY_KEYS, _environment_facts, main, reproducibility_drift
from mira.explain import explain

NOW = {"cpu": "Intel(R) Xeon(R) Processor", "cpu_capability": "AVX512", "torch": "2.13.0+cpu",
       "gemm_backend": "onednn", "python": "3.11.7"}


def test_environment_records_every_reproducibility_key() -> None:
    facts = _environment_facts()
    for key in REPRODUCIBILITY_KEYS:
        assert isinstance(facts[key], str) and facts[key], key


def test_no_drift_on_the_same_machine() -> None:
    assert reproducibility_drift(dict(NOW), dict(NOW)) == []


@pytest.mark.parametrize("key", REPRODUCIBILITY_KEYS)
def test_each_key_that_changed_is_named(key: str) -> None:
    recorded = {**NOW, key: "something else"}
    assert reproducibility_drift(recorded, NOW) == [f"{key}: 'something else' -> {NOW[key]!r}"]


def test_keys_an_older_run_did_not_record_are_skipped_and_others_ignored() -> None:
    recorded = {"torch": NOW["torch"], "python": "3.12.0"}  # no cpu fields; python is not a key
    assert reproducibility_drift(recorded, NOW) == []


@pytest.mark.slow
def test_resume_on_another_cpu_warns(tmp_path: Path, fast_train_args: list[str],
                                     caplog: pytest.LogCaptureFixture) -> None:
    run = tmp_path / "run"
    assert main(["train", "--task", "halfcheetah", "--method", "sparse", "--steps", "600", "--seed", "0",
                 "--out", str(run), *fast_train_args]) == 0
    config = json.loads((run / "config.json").read_text())
    assert config["environment"]["cpu"] == _environment_facts()["cpu"]
    assert f"Machine: {config['environment']['cpu']} (" in explain(run)
    with caplog.at_level(logging.WARNING, logger="mira.cli"):
        assert main(["train", "--resume", str(run), "--quiet"]) == 0
    assert not [r for r in caplog.records if "different machine" in r.getMessage()]
    config["environment"]["cpu"] = "AMD EPYC 9R45"
    (run / "config.json").write_text(json.dumps(config))
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="mira.cli"):
        assert main(["train", "--resume", str(run), "--quiet"]) == 0
    warnings = [r.getMessage() for r in caplog.records if "different machine" in r.getMessage()]
    assert len(warnings) == 1 and "cpu: 'AMD EPYC 9R45' -> " in warnings[0]

"""A run records what decides its arithmetic (CPU model and capability, torch, GEMM backend, the source
tree), and a resume on a machine that differs in any of them says so instead of passing for a bit-exact
continuation."""

from __future__ import annotations

import json
import logging
import subprocess
from pathlib import Path

import pytest

from mira.cli import REPRODUCIBILITY_KEYS, environment_facts, main, reproducibility_drift, source_revision
from mira.explain import explain

NOW = {"cpu": "Intel(R) Xeon(R) Processor", "cpu_capability": "AVX512", "torch": "2.13.0+cpu",
       "gemm_backend": "onednn", "source_tree": "0123abc", "python": "3.11.7"}


def test_environment_records_every_reproducibility_key() -> None:
    facts = environment_facts()
    for key in REPRODUCIBILITY_KEYS:
        # A wheel has no source tree to name; every other key is always known.
        assert (isinstance(facts[key], str) and facts[key]) or (key == "source_tree" and facts[key] is None), key


def test_source_revision_names_the_commit_and_uncommitted_code(tmp_path: Path) -> None:
    assert source_revision(tmp_path) == {"source": None, "source_tree": None}  # no checkout: nothing to name

    def git(*argv: str) -> str:
        return subprocess.run(["git", "-C", str(tmp_path), *argv], capture_output=True, text=True,
                              check=True).stdout.strip()

    module = tmp_path / "src" / "mira" / "m.py"
    module.parent.mkdir(parents=True)
    module.write_text("x = 1\n")
    (tmp_path / "README.md").write_text("readme\n")
    git("init", "-q")
    git("add", "-A")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "first")
    head, tree = git("rev-parse", "HEAD"), git("rev-parse", "HEAD:src")
    assert source_revision(tmp_path) == {"source": head, "source_tree": tree}
    (tmp_path / "README.md").write_text("edited outside src\n")
    assert source_revision(tmp_path) == {"source": head, "source_tree": tree}  # only the code counts
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qam", "docs only")
    after_docs = source_revision(tmp_path)
    assert after_docs["source"] != head and after_docs["source_tree"] == tree
    head = git("rev-parse", "HEAD")
    module.write_text("x = 2\n")
    first = source_revision(tmp_path)
    digest = (first["source"] or "").removeprefix(head + "+")
    assert len(digest) == 12 and first == {"source": f"{head}+{digest}", "source_tree": f"{tree}+{digest}"}
    module.write_text("x = 3\n")
    assert source_revision(tmp_path)["source"] not in (head, first["source"])  # another change, another digest


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
    assert config["environment"]["cpu"] == environment_facts()["cpu"]
    assert f"Machine: {config['environment']['cpu']} (" in explain(run)
    if config["environment"]["source"]:
        assert f"at commit {config['environment']['source'][:12]}" in explain(run)
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
    # The run directory keeps the record: from which step it continued elsewhere, and what changed.
    resumed = json.loads((run / "config.json").read_text())["resumed_elsewhere"]
    assert len(resumed) == 1 and resumed[0]["step"] == 600 and resumed[0]["drift"][0].startswith("cpu: 'AMD EPYC")
    assert resumed[0]["environment"]["cpu"] == environment_facts()["cpu"]
    assert "Resumed from step 600 on another machine, software or source: cpu: 'AMD EPYC 9R45'" in explain(run)

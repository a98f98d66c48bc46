"""The run configuration stays small, and run directories written before a field was removed still load."""

from __future__ import annotations

import copy
import dataclasses
import json
from pathlib import Path

import pytest

from mira.config import TrainConfig, drop_removed_fields, from_dict, to_dict
from mira.config_history import REMOVED_FIELDS
from mira.errors import UsageError

ROOT = Path(__file__).resolve().parents[1]
ARCHIVED = ROOT / "bench" / "archive" / "hc100_flawed_llm" / "halfcheetah" / "no_progress" / "mira-sac-s0"
ARCHIVED_CONFIG = ARCHIVED / "config.json"


def _leaves(obj: object, prefix: str = "") -> list[str]:
    out: list[str] = []
    for f in dataclasses.fields(obj):  # type: ignore[arg-type]
        value = getattr(obj, f.name)
        if dataclasses.is_dataclass(value):
            out.extend(_leaves(value, f"{prefix}{f.name}."))
        else:
            out.append(prefix + f.name)
    return out


def test_at_most_sixty_fields_reach_the_command_line() -> None:
    fields = _leaves(TrainConfig())
    assert len(fields) <= 60, f"{len(fields)} configuration fields: {fields}"
    assert not set(fields) & set(REMOVED_FIELDS), "a removed field is back: take it out of config_history"


def test_a_config_written_before_the_removals_loads_as_the_same_run() -> None:
    saved = json.loads(ARCHIVED_CONFIG.read_text(encoding="utf-8"))["config"]
    assert "baselines" in saved and "mode" in saved["mira"]  # written with the old fields
    cfg = from_dict(TrainConfig, drop_removed_fields(saved))
    assert cfg.method == saved["method"] and cfg.seed == saved["seed"]
    assert cfg.mira.mcm.delta_t == saved["mira"]["mcm"]["delta_t"]
    assert to_dict(cfg)["agent"]["lr"] == saved["agent"]["lr"]


def test_a_removed_field_at_another_value_is_refused_by_name() -> None:
    saved = json.loads(ARCHIVED_CONFIG.read_text(encoding="utf-8"))["config"]
    changed = copy.deepcopy(saved)
    changed["hars"]["decompose_nonneg"] = True
    with pytest.raises(UsageError, match=r"hars\.decompose_nonneg = True"):
        drop_removed_fields(changed, "config.json")
    assert saved["hars"]["decompose_nonneg"] is False  # the input is not modified


def test_an_unknown_field_is_still_an_error() -> None:
    with pytest.raises(ValueError, match="hars: unknown field"):
        from_dict(TrainConfig, drop_removed_fields({"hars": {"no_such_switch": 1}}))


def test_the_paper_presets_set_table_one_and_the_letter_adds_episodic_alignment() -> None:
    from mira.train_cli import config_from_args, train_parser

    paper = config_from_args(train_parser().parse_args(["--method", "mira", "--preset", "paper"]))
    assert (paper.agent.lr, paper.hars.lr, paper.mira.mcm.delta_t, paper.mira.repair) == (1e-4, 1e-4, 5000, False)
    assert paper.hars.alignment == "decomposed" and paper.hars.kappa() == 0.0
    letter = config_from_args(train_parser().parse_args(["--method", "mira", "--preset", "paper-letter"]))
    assert (letter.agent.lr, letter.mira.mcm.delta_t, letter.mira.repair) == (1e-4, 5000, False)
    assert letter.hars.alignment == "episodic" and letter.hars.kappa() == 1.0
    later = config_from_args(train_parser().parse_args(["--preset", "paper", "--lr", "3e-4"]))
    assert later.agent.lr == 3e-4  # --lr is applied after the preset


def test_a_run_without_threads_gets_the_documented_default_of_one_thread() -> None:
    # The command line's default is the config's: a run started without --threads must not take one
    # thread per core and oversubscribe a machine shared with other seeds.
    from mira.train_cli import config_from_args, train_parser

    assert TrainConfig().threads == 1
    assert config_from_args(train_parser().parse_args(["--out", "x"])).threads == 1
    assert config_from_args(train_parser().parse_args(["--out", "x", "--threads", "4"])).threads == 4


def test_show_config_lists_every_set_key_with_a_value_that_sets_it_back(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from mira.cli import main
    from mira.config import apply_override
    from mira.train_cli import describe_config

    monkeypatch.chdir(tmp_path)
    assert main(["train", "--method", "mira", "--preset", "paper", "--set", "mira.mcm.k_cool=7", "--show-config"]) == 0
    printed = capsys.readouterr().out
    assert list(tmp_path.iterdir()) == []  # nothing written
    keys = [line.split(" = ", 1) for line in printed.splitlines() if not line.startswith(" ")]
    assert ["mira.mcm.k_cool", "7"] in keys and ["agent.lr", "0.0001"] in keys and ["method", '"mira"'] in keys
    # Every printed key is one --set accepts, and its printed value sets it back: the listing is the config.
    rebuilt = TrainConfig()
    for key, value in keys:
        apply_override(rebuilt, f"{key}={value}")
    assert describe_config(rebuilt) == printed.rstrip("\n")

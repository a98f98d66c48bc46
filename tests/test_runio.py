from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from mira.errors import CheckpointError
from mira.runio.atomic import append_line, atomic_write_json, read_jsonl
from mira.runio.checkpoint import list_checkpoints, load_checkpoint, load_latest, save_checkpoint
from mira.runio.csvlog import CsvLog, read_csv


def test_atomic_write_replaces_whole_file(tmp_path: Path) -> None:
    target = tmp_path / "a.json"
    atomic_write_json(target, {"x": 1})
    atomic_write_json(target, {"x": 2})
    assert json.loads(target.read_text()) == {"x": 2}
    assert [p.name for p in tmp_path.iterdir()] == ["a.json"]  # no temporary files left behind


def test_csv_log_drops_torn_last_line_and_rewinds(tmp_path: Path) -> None:
    log = CsvLog(tmp_path / "e.csv", ["step", "v"])
    for step in (1, 2, 3):
        log.append({"step": step, "v": step * 0.5})
    with open(tmp_path / "e.csv", "a") as fh:
        fh.write("4,2.")  # a kill mid-write
    assert [r["step"] for r in read_csv(tmp_path / "e.csv")] == ["1", "2", "3"]
    reopened = CsvLog(tmp_path / "e.csv", ["step", "v"])
    reopened.append({"step": 4, "v": 2.0})
    assert [r["step"] for r in reopened.read()] == ["1", "2", "3", "4"]
    reopened.rewind(2)
    assert [r["step"] for r in reopened.read()] == ["1", "2"]


def test_csv_log_widens_with_new_columns_keeping_earlier_rows(tmp_path: Path) -> None:
    log = CsvLog(tmp_path / "t.csv", ["step", "w_a"])
    log.append({"step": 1, "w_a": 0.5})
    log.widen(["step", "w_a", "w_b"])  # a new program brings w_b
    log.append({"step": 2, "w_b": 1.5})
    log.widen(["step", "w_b"])  # nothing new: the file is left alone
    rows = CsvLog(tmp_path / "t.csv", ["step"]).read()  # reopened, the file's own header is kept
    assert rows == [{"step": "1", "w_a": "0.5", "w_b": ""}, {"step": "2", "w_a": "", "w_b": "1.5"}]


def test_jsonl_tolerates_torn_last_line(tmp_path: Path) -> None:
    path = tmp_path / "x.jsonl"
    append_line(path, json.dumps({"a": 1}))
    with open(path, "a") as fh:
        fh.write('{"a": ')
    assert read_jsonl(path) == [{"a": 1}]


def test_corrupt_checkpoint_is_reported_and_previous_used(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    save_checkpoint(tmp_path, 10, {"w": torch.ones(3)}, keep=3)
    save_checkpoint(tmp_path, 20, {"w": torch.full((3,), 2.0)}, keep=3)
    payload = tmp_path / "ckpt-0000000020.pt"
    data = bytearray(payload.read_bytes())
    data[len(data) // 2] ^= 0xFF
    payload.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="hash"):
        load_checkpoint(tmp_path, 20)
    step, state = load_latest(tmp_path)  # type: ignore[misc]
    assert step == 10 and torch.equal(state["w"], torch.ones(3))
    assert "falling back" in caplog.text


def test_checkpoint_without_manifest_does_not_exist(tmp_path: Path) -> None:
    save_checkpoint(tmp_path, 5, {"a": 1})
    (tmp_path / "ckpt-0000000009.pt").write_bytes(b"partial")  # killed before its manifest was written
    assert list_checkpoints(tmp_path) == [5]


def test_keep_prunes_old_checkpoints(tmp_path: Path) -> None:
    for step in range(1, 6):
        save_checkpoint(tmp_path, step, {"s": step}, keep=2)
    assert list_checkpoints(tmp_path) == [4, 5]

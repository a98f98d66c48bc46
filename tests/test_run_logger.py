"""One logger, several sinks: a record reaches every sink, each keeps what it is for."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from mira.runio.csvlog import read_csv
from mira.runio.logger import CsvSink, RunLogger, TensorBoardSink


class ListSink:
    def __init__(self) -> None:
        self.rows: list[tuple[str, int, dict[str, Any]]] = []
        self.flushed = self.closed = 0

    def record(self, group: str, step: int, values: Any) -> None:
        self.rows.append((group, step, dict(values)))

    def flush(self) -> None:
        self.flushed += 1

    def close(self) -> None:
        self.closed += 1


def test_every_sink_gets_every_record_and_each_file_its_group(tmp_path: Path) -> None:
    csv = CsvSink(tmp_path, {"eval": ["step", "return_mean"], "train": ["step", "loss"]}, resume_step=0)
    other = ListSink()
    logger = RunLogger([csv, other])
    logger.record("eval", 100, {"return_mean": 1.5})
    logger.record("outer", 100, {"S": 2.0})  # no CSV file for this group: the CSV sink leaves it
    csv.widen("train", ["step", "loss", "w_new"])
    logger.record("train", 200, {"loss": 0.25, "w_new": 3.0})
    logger.flush()
    logger.close()
    assert [r["return_mean"] for r in read_csv(tmp_path / "eval.csv")] == ["1.5"]
    assert read_csv(tmp_path / "train.csv") == [{"step": "200", "loss": "0.25", "w_new": "3.0"}]
    assert not (tmp_path / "outer.csv").exists()
    assert [g for g, _, _ in other.rows] == ["eval", "outer", "train"] and other.flushed == other.closed == 1


def test_a_resumed_run_drops_rows_after_its_checkpoint(tmp_path: Path) -> None:
    (tmp_path / "eval.csv").write_text("step,return_mean\n100,1.0\n200,2.0\n300,3.0\n")
    (tmp_path / "diagnostics.csv").write_text("step,S\n100,0.5\n300,0.7\n")
    CsvSink(tmp_path, {"eval": ["step", "return_mean"]}, resume_step=200)
    assert [r["step"] for r in read_csv(tmp_path / "eval.csv")] == ["100", "200"]
    assert [r["step"] for r in read_csv(tmp_path / "diagnostics.csv")] == ["100"]  # every CSV of the run


def test_tensorboard_gets_numeric_values_but_the_skipped_ones(tmp_path: Path) -> None:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    sink = TensorBoardSink(tmp_path / "tb", None, skip={"eval": ["wall_s"]})
    sink.record("eval", 10, {"return_mean": 4.0, "wall_s": 1.0, "note": "text"})
    sink.record("train", 10, {"loss": 0.5, "flag": True})
    sink.close()
    ea = EventAccumulator(str(tmp_path / "tb"))
    ea.Reload()
    assert sorted(ea.Tags()["scalars"]) == ["eval/return_mean", "train/loss"]

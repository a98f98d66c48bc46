"""The layout of a run directory and its writers.

::

    RUN_DIR/
      config.json        resolved TrainConfig + task card + versions (enough to rerun)
      status.json        running / finished / failed, with the last step and message
      eval.csv           step, return mean/std, episode length, wall seconds
      train.csv          losses, entropy / temperature, steps/s, reward-source scalars
      tb/                TensorBoard scalars
      checkpoints/       verified checkpoints (ckpt-<step>.pt + .json manifest)
      programs/          factor-program versions and diffs (methods with programs)
      diagnostics.csv    MCM, one row per cycle (MIRA methods)
      interventions/     one folder per SRR intervention (MIRA)
      llm/               every LLM exchange and the response cache
"""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import Any

from mira.errors import UsageError
from mira.runio.atomic import atomic_write_json
from mira.runio.csvlog import CsvLog

EVAL_FIELDS = ("step", "return_mean", "return_std", "length_mean", "episodes", "wall_s")


def prepare_run_dir(out: str | os.PathLike[str], *, resume: bool, overwrite: bool) -> Path:
    """Create (or reopen for resume) a run directory, refusing to clobber an existing run."""
    path = Path(out)
    if path.exists() and not path.is_dir():
        raise UsageError(f"--out {path}: exists and is not a directory")
    if resume:
        if not (path / "config.json").is_file():
            raise UsageError(f"--resume {path}: not a run directory (no config.json)")
        return path
    if path.exists() and any(path.iterdir()):
        if not overwrite:
            raise UsageError(f"--out {path}: directory exists and is not empty (use --resume or --overwrite)")
        shutil.rmtree(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        probe = path / ".write-probe"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        raise UsageError(f"--out {path}: cannot write there ({exc.strerror})") from exc
    return path


class RunDir:
    """Paths and writers of one run."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.checkpoints = path / "checkpoints"
        self.programs = path / "programs"
        self.interventions = path / "interventions"
        self.llm = path / "llm"
        self._tb: Any = None

    def write_config(self, data: dict[str, Any]) -> None:
        atomic_write_json(self.path / "config.json", data)

    def set_status(self, status: str, step: int, message: str = "", **progress: Any) -> None:
        """``status.json``: the run's state and step, and while it runs its progress figures (steps/s,
        the last evaluation, the program version), rewritten atomically at every log interval."""
        atomic_write_json(
            self.path / "status.json",
            {"status": status, "step": step, "message": message, "time": time.strftime("%Y-%m-%dT%H:%M:%S"),
             **progress},
        )

    def eval_log(self) -> CsvLog:
        return CsvLog(self.path / "eval.csv", EVAL_FIELDS)

    def csv_log(self, name: str, fields: list[str]) -> CsvLog:
        return CsvLog(self.path / name, fields)

    def tensorboard(self, purge_step: int | None = None) -> Any:
        """A TensorBoard writer; on resume, events logged after the checkpoint are purged."""
        if self._tb is None:
            from torch.utils.tensorboard import SummaryWriter

            self._tb = SummaryWriter(str(self.path / "tb"), purge_step=purge_step, flush_secs=30)
        return self._tb

    def close(self) -> None:
        if self._tb is not None:
            self._tb.close()
            self._tb = None

"""Bad input: one line on stderr, exit status 2, no traceback."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest


def _run(args: list[str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "mira.cli", *args], capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["train", "--task", "walker", "--out", "{tmp}/o"], "unknown task 'walker'"),
        (["train", "--method", "magic", "--out", "{tmp}/o"], "invalid choice: 'magic'"),
        (["train", "--algo", "ppo", "--out", "{tmp}/o"], "invalid choice: 'ppo'"),
        (["train", "--steps", "-5", "--out", "{tmp}/o"], "must be a positive integer"),
        (["train", "--out", "/proc/mira-cannot-write"], "cannot write there"),
        (["train", "--out", "{tmp}/full"], "not empty"),
        (["train", "--resume", "{tmp}/nothing"], "not a run directory"),
        (["train", "--task", "{tmp}/bad.toml", "--out", "{tmp}/o"], "does not parse"),
        (["train", "--out", "{tmp}/o", "--set", "hars.update_every=x"], "expected a int like 8"),
        (["train", "--out", "{tmp}/o", "--set", "hars.shaping_weight=yes"], "expected float or null"),
        (["train", "--out", "{tmp}/o", "--set", "hars.shaping_weight=true"], "expected float or null"),
        (["train", "--out", "{tmp}/o", "--set", "hars.nope=1"], "no field 'nope'"),
    ],
)
def test_bad_input_is_one_line_exit_2(tmp_path: Path, args: list[str], needle: str) -> None:
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    (tmp_path / "bad.toml").write_text("name = [unclosed")
    proc = _run([a.replace("{tmp}", str(tmp_path)) for a in args])
    assert proc.returncode == 2, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip() and "settotalmass" not in ln]
    assert len(lines) == 1, proc.stderr
    assert needle in lines[0]
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "o").exists()  # a bad flag, card or task leaves nothing on disk


def test_a_run_whose_program_is_refused_leaves_nothing_and_the_rerun_works(tmp_path: Path) -> None:
    """A failure before training starts (here: an inadmissible --program) removes the run directory, so
    the same command with the cause fixed runs without --overwrite or --resume."""
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"task": "halfcheetah", "version": 0, "factors": [
        {"name": "r_bad", "type": "PHI", "code": "def r_bad(s):\n    import os\n    return s.x_velocity\n",
         "doc": "d", "units": "m/s", "range_hint": "[-1, 1]"}]}))
    out = tmp_path / "run"
    common = ["train", "--method", "hars", "--steps", "300", "--learning-starts", "100", "--eval-every", "300",
              "--eval-episodes", "1", "--threads", "1", "--quiet", "--out", str(out)]
    proc = _run([*common, "--program", str(bad)])
    assert proc.returncode == 2, proc.stderr
    assert not out.exists()
    proc = _run(common)
    assert proc.returncode == 0, proc.stderr
    assert (out / "config.json").is_file()


def test_bad_gemm_backend_is_one_line_exit_2(tmp_path: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "mira.cli", "train", "--out", str(tmp_path / "o")],
                          capture_output=True, text=True, timeout=120, env={**os.environ, "MIRA_GEMM": "fast"})
    assert proc.returncode == 2, proc.stderr
    assert "MIRA_GEMM='fast'" in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "o").exists()  # nothing written

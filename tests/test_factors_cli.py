"""The functions behind `mira factors check` and `mira factors synth`."""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest

from mira.errors import UsageError
from mira.factors import example_program, save_program
from mira.factors.cli_impl import check_program_file

EXAMPLES = Path(__file__).resolve().parents[1] / "src" / "mira" / "examples"


def test_examples_are_admissible() -> None:
    out = io.StringIO()
    assert check_program_file(EXAMPLES / "halfcheetah_f1.json", "halfcheetah", out=out) == 0
    assert out.getvalue().splitlines()[-1].startswith("ok: 4 factor(s) admissible for halfcheetah")


def test_static_only_check(tmp_path: Path) -> None:
    out = io.StringIO()
    assert (
        check_program_file(EXAMPLES / "humanoidstandup_f1.json", "humanoidstandup", sandbox=False, out=out)
        == 0
    )
    assert "sandbox skipped" in out.getvalue()


def _write(tmp_path: Path, factors: list[dict[str, str]], task: str = "halfcheetah") -> Path:
    path = tmp_path / "program.json"
    path.write_text(json.dumps({"task": task, "version": 0, "factors": factors}), encoding="utf-8")
    return path


def test_violations_are_one_line_each(tmp_path: Path) -> None:
    path = _write(
        tmp_path,
        [
            {
                "name": "r_vel",
                "type": "PHI",
                "code": "import os\ndef r_vel(s):\n    return s.next_x_velocity\n",
                "doc": "d",
                "units": "m/s",
                "range_hint": "[-1, 1]",
            },
            {"name": "r_x", "type": "PHI", "code": "def r_x(s):\n    return s.pitch\n"},
        ],
    )
    out = io.StringIO()
    assert check_program_file(path, "halfcheetah", out=out) == 1
    lines = out.getvalue().splitlines()
    assert "r_vel:1: [import] imports are not allowed" in lines
    assert any(line.startswith("r_vel:3: [feature]") for line in lines)
    assert sum(line.startswith("r_x:0: [metadata]") for line in lines) == 3


def test_sandbox_failures_exit_one(tmp_path: Path) -> None:
    path = _write(
        tmp_path,
        [
            {
                "name": "r_log",
                "type": "PHI",
                "code": "def r_log(s):\n    return np.arccosh(s.pitch + 1.0)\n",
                "doc": "d",
                "units": "1",
                "range_hint": "[-5, 5]",
            }
        ],
    )
    out = io.StringIO()
    assert check_program_file(path, "halfcheetah", out=out) == 1
    assert "r_log:0: [non-finite]" in out.getvalue()


def test_contract_breaks_and_task_mismatch_exit_one(tmp_path: Path) -> None:
    path = _write(tmp_path, [{"name": "r", "type": "PHI", "code": "def r(s):\n    return a[:, 0]\n"}])
    out = io.StringIO()
    assert check_program_file(path, "halfcheetah", out=out) == 1
    assert "[phi-action]" in out.getvalue()
    other = tmp_path / "other.json"
    save_program(example_program("halfcheetah", 0), other)
    out = io.StringIO()
    assert check_program_file(other, "humanoidstandup", sandbox=False, out=out) == 1
    assert "[program]" in out.getvalue() and "[feature]" in out.getvalue()


def test_usage_errors(tmp_path: Path) -> None:
    with pytest.raises(UsageError, match="no such file"):
        check_program_file(tmp_path / "missing.json", "halfcheetah")
    bad = tmp_path / "bad.json"
    bad.write_text("{", encoding="utf-8")
    with pytest.raises(UsageError, match="invalid JSON"):
        check_program_file(bad, "halfcheetah")
    with pytest.raises(UsageError):
        check_program_file(EXAMPLES / "halfcheetah_f0.json", "no-such-task")

"""``mira factors synth`` / ``check`` through the real command line and every backend kind."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from chat_server import ChatServer, reply

PROGRAM = {
    "task": "halfcheetah",
    "version": 0,
    "factors": [
        {"name": "r_speed", "type": "PHI", "code": "def r_speed(s):\n    return np.tanh(s.x_velocity)\n",
         "doc": "bounded forward speed", "units": "1", "range_hint": "[-1, 1]"},
        {"name": "r_effort", "type": "AUX", "code": "def r_effort(s, a):\n    return -np.sum(a * a, axis=-1)\n",
         "doc": "control effort", "units": "1", "range_hint": "[-6, 0]"},
    ],
}


def _mira(args: list[str], tmp: Path, **env: str) -> subprocess.CompletedProcess[str]:
    full_env = {**os.environ, "MIRA_CACHE_DIR": str(tmp / "cache"), **env}
    return subprocess.run([sys.executable, "-m", "mira.cli", *args], capture_output=True, text=True, timeout=180,
                          env=full_env)


def test_synth_offline_prints_the_papers_halfcheetah_program(tmp_path: Path) -> None:
    proc = _mira(["factors", "synth", "--task", "halfcheetah"], tmp_path)
    assert proc.returncode == 0, proc.stderr
    program = json.loads(proc.stdout)
    kinds = {f["name"]: f["type"] for f in program["factors"]}
    assert kinds == {"r_vel": "PHI", "r_upright": "PHI", "r_stable": "PHI", "r_ctrl": "AUX"}


def test_synth_script_backend_returns_the_scripted_program(tmp_path: Path) -> None:
    script = tmp_path / "replies.jsonl"
    script.write_text(json.dumps({"content": "Here you go:\n```json\n" + json.dumps(PROGRAM) + "\n```"}) + "\n")
    out = tmp_path / "p.json"
    args = ["factors", "synth", "--task", "halfcheetah", "--llm", f"script:{script}", "--out", str(out)]
    proc = _mira(args, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert [f["name"] for f in json.loads(out.read_text())["factors"]] == ["r_speed", "r_effort"]
    check = _mira(["factors", "check", str(out), "--task", "halfcheetah"], tmp_path)
    assert check.returncode == 0, check.stdout + check.stderr


def test_synth_openai_backend_against_local_server(tmp_path: Path) -> None:
    with ChatServer() as server:
        server.push(reply(json.dumps(PROGRAM)))
        args = ["factors", "synth", "--task", "halfcheetah", "--llm", "openai:test-model", "--base-url", server.url]
        proc = _mira(args, tmp_path, OPENAI_API_KEY="sk-test")
        assert proc.returncode == 0, proc.stderr
        assert json.loads(proc.stdout)["factors"][0]["name"] == "r_speed"
        assert server.count == 1
        again = _mira(args, tmp_path, OPENAI_API_KEY="sk-test")  # served from the cache
        assert again.returncode == 0 and again.stdout == proc.stdout
        assert server.count == 1


def test_check_rejects_hostile_programs_with_reasons(tmp_path: Path) -> None:
    importing = json.loads(json.dumps(PROGRAM))
    importing["factors"][0]["code"] = "def r_speed(s):\n    import os\n    return s.x_velocity\n"
    phi_reads_action = json.loads(json.dumps(PROGRAM))
    phi_reads_action["factors"][1]["type"] = "PHI"
    for name, program, factor in (("imp", importing, "r_speed"), ("act", phi_reads_action, "r_effort")):
        path = tmp_path / f"{name}.json"
        path.write_text(json.dumps(program))
        proc = _mira(["factors", "check", str(path), "--task", "halfcheetah", "--no-sandbox"], tmp_path)
        assert proc.returncode == 1, proc.stdout + proc.stderr
        assert proc.stdout.startswith(factor), proc.stdout


def test_check_missing_or_invalid_file_is_exit_2(tmp_path: Path) -> None:
    assert _mira(["factors", "check", str(tmp_path / "nope.json"), "--task", "halfcheetah"], tmp_path).returncode == 2
    (tmp_path / "x.json").write_text("{not json")
    assert _mira(["factors", "check", str(tmp_path / "x.json"), "--task", "halfcheetah"], tmp_path).returncode == 2

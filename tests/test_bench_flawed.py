"""``bench/flawed.py``'s run list: every flawed program per method, the good program's reference runs
with ``hars`` and ``mira`` only, and none of them when they are run elsewhere."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

BENCH = Path(__file__).parents[1] / "bench"


def _load():
    sys.path.insert(0, str(BENCH))  # flawed.py imports its sibling learning.py as the benchmark runs it
    try:
        spec = importlib.util.spec_from_file_location("bench_flawed", BENCH / "flawed.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(BENCH))


def test_jobs_give_the_good_program_only_hars_and_mira_and_can_leave_it_out() -> None:
    flawed = _load()
    methods = ["hars", "mira", "mira-no-mcm"]
    with_good = flawed.jobs("halfcheetah", ["no_progress"], methods, [0, 1])
    assert with_good[:5] == [("good", "hars", 0), ("good", "mira", 0), ("no_progress", "hars", 0),
                             ("no_progress", "mira", 0), ("no_progress", "mira-no-mcm", 0)]
    assert len(with_good) == 10
    without = flawed.jobs("halfcheetah", ["no_progress"], methods, [0, 1], good=False)
    assert without == [(n, m, s) for n, m, s in with_good if n != "good"]

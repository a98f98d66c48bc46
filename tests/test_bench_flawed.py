"""``bench/flawed.py``'s run list: every flawed program per method, the good program's reference runs
with ``hars`` and ``mira`` only, and none of them when they are run elsewhere."""

from __future__ import annotations

from collections.abc import Callable
from types import ModuleType


def test_jobs_give_the_good_program_only_hars_and_mira_and_can_leave_it_out(
        load_bench: Callable[[str], ModuleType]) -> None:
    flawed = load_bench("flawed")
    methods = ["hars", "mira", "mira-no-mcm"]
    with_good = flawed.jobs("halfcheetah", ["no_progress"], methods, [0, 1])
    assert with_good[:5] == [("good", "hars", 0), ("good", "mira", 0), ("no_progress", "hars", 0),
                             ("no_progress", "mira", 0), ("no_progress", "mira-no-mcm", 0)]
    assert len(with_good) == 10
    without = flawed.jobs("halfcheetah", ["no_progress"], methods, [0, 1], good=False)
    assert without == [(n, m, s) for n, m, s in with_good if n != "good"]

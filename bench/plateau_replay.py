"""Where the plateau detector reports, replayed on archived runs' held-out returns.

A run's ``diagnostics.csv`` keeps the mean held-out return of every cycle (``smoothed_return``), the
series the detector reads. This feeds that series to :class:`mira.mcm.plateau.PlateauDetector` as the
code is now and prints the steps at which it would report, beside the steps at which the run itself
reported (its ``plateau.csv``, made by the detector of the run's commit). Only the return's half of the
test is replayed: the band where the episodes settle needs their states, which no archive keeps, so the
band is taken as narrow (on HumanoidStandup and Humanoid every recorded report had it well inside the
limit). After a report the detector is silent for the run's ``k_cool`` cycles, as while an escape is on
probation. Past a run's first edit its returns are those of the edited run, so a replay there says
where the detector would have looked again, not what the run would have done.

    python bench/plateau_replay.py bench/archive/hum100_sac_mira_s0 bench/archive/hs200_sac_mira_no_mcm_s0
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mira.mcm.config import MCMConfig
from mira.mcm.plateau import PlateauDetector
from mira.runio.csvlog import read_csv

_NARROW = np.zeros(8)
_VISITED = (0.0, 1.0)


def replay(run: Path) -> list[int]:
    """The steps at which today's detector reports a plateau on ``run``'s held-out returns."""
    config = json.loads((run / "config.json").read_text())
    k_cool = int(config.get("mira", {}).get("mcm", {}).get("k_cool", MCMConfig().k_cool))
    detector, quiet, found = PlateauDetector("replayed"), 0, []
    for row in read_csv(run / "diagnostics.csv"):
        if quiet:
            quiet -= 1
            continue
        report = detector.observe(int(float(row["step"])), float(row["smoothed_return"]), _NARROW, _VISITED)
        if report is not None:
            found.append(report.step)
            quiet = k_cool
    return found


def recorded(run: Path) -> list[int]:
    """The steps at which the run itself reported a plateau."""
    path = run / "plateau.csv"
    return [int(float(r["step"])) for r in read_csv(path) if r["event"] == "plateau"] if path.exists() else []


def runs_under(path: Path) -> list[Path]:
    """Every run directory at or under ``path`` that kept its diagnostics."""
    return sorted(p.parent for p in path.rglob("diagnostics.csv"))


def _ks(steps: list[int]) -> str:
    return ", ".join(f"{s // 1000}" for s in steps) or "none"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("paths", nargs="+", type=Path, help="run directories or folders holding them")
    args = parser.parse_args(argv)
    print("| run | recorded reports (k steps) | today's detector (k steps) |\n|---|---|---|")
    for path in args.paths:
        for run in runs_under(path):
            print(f"| `{run}` | {_ks(recorded(run))} | {_ks(replay(run))} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

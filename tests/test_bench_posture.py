"""``bench/posture.py`` replays a run's own evaluation episodes from its checkpoint: the replayed
return is the logged one, and a region or feature the task lacks is named in the error."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from mira.cli import main


def test_replayed_evaluation_matches_the_logged_one(tmp_path: Path, fast_train_args: list[str],
                                                     load_bench: Callable[[str], ModuleType]) -> None:
    posture = load_bench("posture")
    run = tmp_path / "run"
    assert main(["train", "--steps", "1000", "--seed", "3", "--method", "dense", "--out", str(run),
                 *fast_train_args]) == 0
    result = posture.posture(run, ["torso_height", "x_velocity"], [posture.parse_region("x_velocity>0")],
                             episodes=1, step=None)
    assert result.step == 1000
    assert result.logged is not None and result.ret == pytest.approx(result.logged, rel=1e-9)
    mean, lo, hi = result.features["torso_height"]
    assert lo <= hi and np.isfinite(mean)
    assert 0.0 <= result.shares["x_velocity>0"] <= 1.0

    with pytest.raises(SystemExit, match="no feature 'height_of_moon'"):
        posture.posture(run, ["height_of_moon"], [], episodes=1, step=None)
    with pytest.raises(SystemExit, match="no checkpoint at step 7"):
        posture.posture(run, ["torso_height"], [], episodes=1, step=7)


def test_region_syntax(load_bench: Callable[[str], ModuleType]) -> None:
    posture = load_bench("posture")
    assert posture.parse_region("uprightness < 0.3") == ("uprightness", "<", 0.3)
    assert posture.parse_region("torso_height>-1e-2") == ("torso_height", ">", -0.01)
    with pytest.raises(SystemExit, match="FEATURE<VALUE"):
        posture.parse_region("uprightness=0.3")

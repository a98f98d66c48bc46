"""Shared fixtures: small, fast training settings for end-to-end tests."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

# One intra-op thread keeps test runs deterministic and leaves the second core to the test runner.
os.environ.setdefault("OMP_NUM_THREADS", "1")

FAST_TRAIN = [
    "--learning-starts", "500", "--batch-size", "64", "--hidden", "32,32", "--eval-every", "1000",
    "--eval-episodes", "1", "--max-episode-steps", "200", "--checkpoint-every", "400", "--log-every", "500",
    "--threads", "1", "--quiet",
]


@pytest.fixture
def fast_train_args() -> list[str]:
    return list(FAST_TRAIN)


@pytest.fixture
def mira_cmd() -> list[str]:
    return [sys.executable, "-m", "mira.cli"]


def read_rows(path: Path) -> list[dict[str, str]]:
    from mira.runio.csvlog import read_csv

    return read_csv(path)

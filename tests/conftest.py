"""Shared fixtures: small, fast training settings for end-to-end tests."""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType

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


BENCH = Path(__file__).parents[1] / "bench"


def _load_bench(name: str) -> ModuleType:
    """``bench/<name>.py`` as a module, its siblings importable as when the benchmark runs."""
    sys.path.insert(0, str(BENCH))
    try:
        spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCH / f"{name}.py")
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        # Registered before it runs, as an import would: dataclasses look their module up by name.
        sys.modules[spec.name] = module
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(str(BENCH))


@pytest.fixture
def load_bench() -> Callable[[str], ModuleType]:
    """Loads a benchmark script (``bench/`` is not a package) by its name."""
    return _load_bench


@pytest.fixture
def mira_cmd() -> list[str]:
    return [sys.executable, "-m", "mira.cli"]


def read_rows(path: Path) -> list[dict[str, str]]:
    from mira.runio.csvlog import read_csv

    return read_csv(path)

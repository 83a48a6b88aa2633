"""Shared fixtures: repository paths and the benchmark directory (evaluation only, never tuned on)."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from mapf_world.grid import grid_from_text


REPO_ROOT = Path(__file__).resolve().parents[1]
FIXTURES = REPO_ROOT / "tests" / "fixtures"


@pytest.fixture
def repo_root() -> Path:
    return REPO_ROOT


@pytest.fixture
def fixtures_dir() -> Path:
    return FIXTURES


@pytest.fixture
def benchmark_dir() -> Path:
    """MAPF_BENCHMARK_DIR, else ../shared/benchmarks next to the repository; skip when absent."""
    path = Path(os.environ.get("MAPF_BENCHMARK_DIR", REPO_ROOT.parent / "shared" / "benchmarks"))
    if not path.is_dir():
        pytest.skip(f"benchmark directory {path} not found (set MAPF_BENCHMARK_DIR)")
    return path

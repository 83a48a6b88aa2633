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


@pytest.fixture
def two_random_models(tmp_path) -> list[str]:
    """Two model files of the shipped architecture with different random weights (CLI smoke runs)."""
    import torch

    from mapf_policy.config import NetworkConfig
    from mapf_policy.model_io import save_model
    from mapf_policy.network import QNetwork

    torch.manual_seed(0)
    paths = []
    for k in range(2):
        path = tmp_path / f"m{k}.pt"
        save_model(path, QNetwork(NetworkConfig()), NetworkConfig(), {"step": k})
        paths.append(str(path))
    return paths

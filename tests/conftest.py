"""Shared fixtures: paths to ../shared (real data; skipped cleanly where absent, never in CI)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import benchmark  # noqa: F401  (first: pins numpy's BLAS kernels before torch loads numpy; benchmark.core.openblas)

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("BENCH4D_SHARED", ROOT.parent / "shared"))

# Denormals from transmittance products slow CPU compositing several-fold.
try:  # pragma: no cover - torch always present in the test env
    import torch

    torch.set_flush_denormal(True)
    torch.set_num_threads(1)  # xdist already runs one worker per core
except ImportError:  # pragma: no cover
    pass


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED.is_dir():
        pytest.skip(f"{SHARED} is absent (real-data checks need ../shared)")
    return SHARED


@pytest.fixture(scope="session")
def dnerf_dir(shared_dir: Path) -> Path:
    path = shared_dir / "data" / "dnerf"
    if not path.is_dir():
        pytest.skip(f"{path} is absent")
    return path


@pytest.fixture(scope="session")
def hypernerf_json_dir(shared_dir: Path) -> Path:
    path = shared_dir / "formats" / "hypernerf-chickchicken"
    if not path.is_dir():
        pytest.skip(f"{path} is absent")
    return path

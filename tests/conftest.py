"""Shared fixtures: the device parametrisation and the location of ../shared."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_MESHES = REPO_ROOT.parent / "shared" / "meshes"

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.cuda)]


@pytest.fixture(params=DEVICES)
def device(request) -> torch.device:
    """Every device test runs on CPU, and on CUDA where a GPU is present (skipped otherwise)."""
    if request.param == "cuda" and not torch.cuda.is_available():
        pytest.skip("no CUDA device")
    return torch.device(request.param)


@pytest.fixture
def shared_meshes() -> Path:
    """../shared/meshes beside the checkout; tests that need it skip cleanly without it."""
    if not SHARED_MESHES.is_dir():
        pytest.skip("../shared/meshes is absent")
    return SHARED_MESHES

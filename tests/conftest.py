"""Shared fixtures: the device parametrisation and the location of ../shared."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_MESHES = REPO_ROOT.parent / "shared" / "meshes"
SHARED_CAPTURES = REPO_ROOT.parent / "shared" / "captures"

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


@pytest.fixture
def shared_captures() -> Path:
    """../shared/captures beside the checkout (real photos, not part of the project: read in
    place, never copied into it); tests that need it skip cleanly without it."""
    if not (SHARED_CAPTURES / "ethiopian_head" / "poses_bounds.npy").is_file():
        pytest.skip("../shared/captures/ethiopian_head is absent")
    return SHARED_CAPTURES


@pytest.fixture(scope="session")
def tiny_run(tmp_path_factory) -> Path:
    """A real run folder, synthesised and fitted at 32 px in a few steps (the quickstart scene):
    for the diagnosis and the benchmarks that read fitted runs. Tests may diagnose it in place;
    copy it to change anything else."""
    import yaml

    from recon.cli import main

    torch.set_num_threads(1)
    folder = tmp_path_factory.mktemp("diagnose_run")
    config = yaml.safe_load((REPO_ROOT / "configs" / "quickstart.yaml").read_text())
    config["stages"] = ["synth", "fit"]
    config["capture"]["cameras"]["resolution"] = [32, 32]
    config["capture"].update({"train_views": 4, "val_views": 0, "test_views": 2})
    config["scene"]["shape"]["resolution"] = 16
    config["scene"]["material"]["texture_size"] = 32
    config["fit"] = {
        "hull_resolution": 16,
        "geometry": {"steps": 3, "resolutions": [32], "remesh_every": 0},
        "texture": {"steps": 1, "texture_size": 64},
    }
    path = folder / "tiny.yaml"
    path.write_text(yaml.safe_dump(config))
    out = folder / "run"
    assert main(["run", str(path), "--out", str(out), "--device", "cpu"]) == 0
    return out

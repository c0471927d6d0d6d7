"""Same config and seed, same result: with the default thread count, not only with one thread."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
import yaml

from recon.cli import main
from recon.pipeline import seed_everything

REPO_ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def restore_deterministic():
    before = torch.are_deterministic_algorithms_enabled()
    yield
    torch.use_deterministic_algorithms(before)


def _accumulate(rows: int) -> list[torch.Tensor]:
    """The backward of advanced indexing: index_put with accumulate, many repeated indices."""
    generator = torch.Generator().manual_seed(0)
    index = torch.randint(0, rows // 4, (rows,), generator=generator)
    source = torch.randn(rows, 3, generator=generator)
    return [
        torch.zeros(rows // 4, 3).index_put_((index,), source, accumulate=True) for _ in range(8)
    ]


def test_seeding_switches_on_deterministic_accumulation(restore_deterministic):
    """On CPU with two threads, accumulating index_put sums in a thread-dependent order once a
    tensor is large enough to be split; the run's seeding makes it repeatable bit for bit."""
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    seed_everything(0, deterministic=True)
    assert torch.are_deterministic_algorithms_enabled()
    results = _accumulate(400_000)
    assert all(torch.equal(results[0], other) for other in results[1:])
    seed_everything(0, deterministic=False)
    assert not torch.are_deterministic_algorithms_enabled()
    torch.set_num_threads(threads)


def test_same_run_twice_with_default_threads_gives_identical_metrics(tmp_path):
    """The whole pipeline (synth, fit with remeshing, evaluate) twice, with torch's default
    thread count: metrics.json identical but for the stage times."""
    # Other tests may have set one thread in this process; the CLI's default here is two.
    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    config = yaml.safe_load((REPO_ROOT / "configs" / "quickstart.yaml").read_text())
    config["stages"] = ["synth", "fit", "evaluate"]
    config["device"] = "cpu"
    config["capture"]["cameras"]["resolution"] = [48, 48]
    config["capture"].update({"train_views": 4, "val_views": 0, "test_views": 2})
    config["scene"]["shape"]["resolution"] = 24
    config["scene"]["material"]["texture_size"] = 32
    config["fit"] = {
        "hull_resolution": 32,
        "geometry": {"steps": 8, "resolutions": [48], "remesh_every": 4},
        "texture": {"steps": 2, "texture_size": 64},
    }
    path = tmp_path / "twice.yaml"
    path.write_text(yaml.safe_dump(config))
    metrics = []
    for name in ("first", "second"):
        assert main(["run", str(path), "--out", str(tmp_path / name)]) == 0
        recorded = json.loads((tmp_path / name / "metrics.json").read_text())
        recorded.pop("stage_seconds", None)
        metrics.append(recorded)
    torch.set_num_threads(threads)
    assert metrics[0] == metrics[1]

"""`recon fit` with fit.material: pbr writes the material maps and environment, the evaluate
stage renders the PBR model (not the Lambertian one) from them, and the report shows them."""

from __future__ import annotations

import json
from pathlib import Path

import yaml

from recon.cli import main
from recon.io.images import read_exr
from recon.io.meshes import load_material_maps

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_fit_with_the_pbr_material_writes_and_evaluates_it(tmp_path):
    config = yaml.safe_load((REPO_ROOT / "configs" / "quickstart.yaml").read_text())
    config["stages"] = ["synth"]
    config["capture"]["cameras"]["resolution"] = [32, 32]
    config["capture"].update({"train_views": 3, "val_views": 0, "test_views": 2})
    config["scene"]["shape"]["resolution"] = 24
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(config))
    captures = tmp_path / "captures"
    assert main(["synth", str(path), "--out", str(captures)]) == 0
    run = tmp_path / "fitted"
    settings = {
        "fit.material": "pbr",
        "fit.pbr.environment_size": "[8,16]",
        "fit.geometry.steps": "8",
        "fit.geometry.resolutions": "[32]",
        "fit.texture.steps": "3",
        "fit.texture.texture_size": "64",
        "fit.hull_resolution": "32",
    }
    arguments = [item for key, value in settings.items() for item in ("--set", f"{key}={value}")]
    code = main(
        ["fit", str(path), "--data", str(captures / "dataset"), "--out", str(run)] + arguments
    )
    assert code == 0
    maps = load_material_maps(run / "mesh" / "model.obj")
    assert maps is not None and maps.shape[-1] == 2
    assert 0.04 - 1 / 255 <= float(maps[..., 0].min())  # roughness kept above its floor
    assert load_material_maps(run / "mesh" / "model.glb") is not None
    assert read_exr(run / "light" / "environment.exr").shape[:2] == (8, 16)
    assert json.loads((run / "light" / "light.json").read_text())["material"] == "pbr"
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["image"]["psnr"] > 10
    # The report shows the material channels and the environment.
    report = (run / "report.md").read_text()
    assert "Fitted material and environment (pbr)" in report
    # ... and turns the fitted material, not its Lambertian stand-in.
    assert "Fitted mesh, turntable (pbr material)" in report
    link = report.split("Fitted material and environment (pbr)](")[1].split(")")[0]
    assert (run / link).stat().st_size > 0

"""benchmarks.material: the targets' verdicts, the Markdown table it generates for docs/, and
the true roughness read from a config. The runs themselves are the benchmark (minutes)."""

from __future__ import annotations

from benchmarks.material import TARGETS, _meets, _true_roughness, markdown


def test_targets_are_judged_in_their_direction():
    assert _meets(33.0, TARGETS["psnr"]) is True and _meets(31.0, TARGETS["psnr"]) is False
    assert _meets(0.04, TARGETS["roughness_error"]) is True
    assert _meets(0.06, TARGETS["roughness_error"]) is False
    assert _meets(None, TARGETS["seconds"]) is None


def test_true_roughness_comes_from_the_specular_effect():
    config = {"capture": {"effects": [{"name": "specular", "parameters": {"roughness": 0.35}}]}}
    assert _true_roughness(config) == 0.35
    assert _true_roughness({"capture": {"effects": []}}) is None
    # Without its own roughness the effect takes the scene material's.
    config = {
        "scene": {"material": {"roughness": 0.2}},
        "capture": {"effects": [{"name": "specular", "parameters": {}}]},
    }
    assert _true_roughness(config) == 0.2
    # A roughness varying over the surface has no single true value (the surface metric).
    config["scene"]["material"]["roughness_texture"] = "checker"
    assert _true_roughness(config) is None


def test_markdown_has_one_row_per_scene_and_material():
    row = {
        "psnr": 30.5,
        "psnr_masked": 25.0,
        "chamfer_l1": 1.2e-3,
        "seconds": 300.0,
    }
    result = {
        "command": "recon-bench material --size 64",
        "commit": "abc1234",
        "date": "2026-11-24 08:00 UTC",
        "overrides": ["fit.texture.steps=10"],
        "environment": {
            "cpu_count": 2,
            "cpu_model": "test CPU",
            "load_average_at_start": [1.0, 1.0, 1.0],
            "torch": "2",
            "mitsuba": "3",
        },
        "scenes": [
            {
                "config": "configs/bench/glossy_spot_sky.yaml",
                "results": [
                    {**row, "material": "lambert"},
                    {
                        **row,
                        "material": "pbr",
                        "roughness_median": 0.33,
                        "roughness_true": 0.35,
                        "metalness_median": 0.01,
                        "surface_roughness_mae": 0.041,
                        "surface_roughness_within_tolerance": 0.7,
                    },
                    {"material": "pbr", "failed": 1, "seconds": 3.0},
                ],
            }
        ],
    }
    text = markdown(result)
    assert "abc1234" in text and "fit.texture.steps=10" in text
    rows = [line for line in text.splitlines() if line.startswith("| glossy_spot_sky")]
    assert len(rows) == 3 and "0.330 (0.35)" in rows[1] and "1.20e-03" in rows[0]
    assert "failed (1)" in rows[2]
    assert "| 0.041 (70 %) |" in rows[1] and "| - |" in rows[0]
    assert all(row.count("|") == text.splitlines()[4].count("|") for row in rows)

"""Smoke test of benchmarks/render.py in its tiniest mode (one 1k-face 64x64 config)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from benchmarks import render as bench


def test_tiniest_run_reports_positive_times(tmp_path, capsys):
    out = tmp_path / "bench.json"
    report = bench.main(
        [
            "--configs",
            "1k:64:1",
            "--runs",
            "2",
            "--no-peer",
            "--device",
            "cpu",
            "--threads",
            "1",
            "--out",
            str(out),
        ]
    )
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads(out.read_text()) == report
    for key in ("torch", "cpu_count", "device", "mitsuba", "torch_threads"):
        assert key in report["environment"]
    assert report["settings"]["sections"] == ["grid"]
    assert "mitsuba" not in report or report["mitsuba"] == "not installed"
    (entry,) = report["grid"]
    assert "skipped" not in entry, entry
    assert entry["faces"] == 1000 and entry["resolution"] == 64 and entry["views"] == 1
    assert entry["runs"] == 2 and len(entry["forward_ms_all"]) == 2
    for key in ("forward_ms", "backward_ms", "total_ms", "peak_rss_mb"):
        assert entry[key] > 0, key
    assert entry["covered_pixels"] > 0 and entry["gradient_ok"]


def test_config_over_timeout_is_skipped(capsys):
    report = bench.main(
        [
            "--configs",
            "1k:64:1,10k:64:1",
            "--runs",
            "1",
            "--no-peer",
            "--device",
            "cpu",
            "--timeout-per-config",
            "0.05",
        ]
    )
    capsys.readouterr()
    first, second = report["grid"]
    assert "timeout" in first["skipped"]
    assert "already skipped" in second["skipped"]  # larger configs are not attempted


@pytest.mark.parametrize("faces", [1000, 10000])
def test_sphere_has_exact_face_count_and_is_closed(faces):
    verts, tris, uvs, uv_faces = bench.latlong_sphere(faces)
    assert tris.shape == uv_faces.shape == (faces, 3)
    # Closed and consistently oriented: every directed edge appears once, its reverse once.
    edges = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    keys = set(map(tuple, edges.tolist()))
    assert len(keys) == len(edges) and all((b, a) in keys for a, b in keys)
    corners = verts[tris]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    assert (np.einsum("fi,fi->f", normals, corners.mean(1)) > 0).all()  # outward
    assert uvs.min() >= 0 and uvs.max() <= 1


def test_midpoint_subdivision_keeps_uv_faces_in_step():
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], dtype=np.float32)
    faces = np.array([[0, 1, 2], [2, 1, 3]])
    new_points, new_faces = bench.midpoint_subdivide(points, faces)
    assert new_faces.shape == (8, 3) and new_points.shape == (4 + 5, 3)
    # Children tile each parent: areas sum to the parent's.
    corners = new_points[new_faces]
    area = 0.5 * np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])[:, 2]
    assert np.allclose(area.reshape(2, 4).sum(1), 0.5) and (area > 0).all()

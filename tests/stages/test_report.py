"""The report's gap-diagnosis section: verdict, ranking with its evidence, and the refit, in both
report.md and report.html, from whatever diagnosis.json the run folder holds."""

from __future__ import annotations

import json

import torch

from recon.config.run_config import RunConfig
from recon.diagnose.records import Candidate, Evidence
from recon.io.run_folder import prepare_run_folder
from recon.stages.report import report_stage


def candidate(name, decided_by, probe, absorption=None, void=None, parameters=None) -> dict:
    """A candidate's diagnosis.json record: probe (reduction, low, high), absorption reduction."""
    result = Candidate(
        name,
        significant=bool(decided_by),
        status="significant" if decided_by else "not_significant",
        decided_by=decided_by,
        why=f"{name}: why",
        parameters=parameters or {},
    )
    reduction, low, high = probe
    details = {"reduction": reduction, "interval": [low, high]}
    result.add(Evidence("probe", name, low, 0.02, low > 0.02, "probe", details))
    if absorption is not None:
        details = {"reduction": absorption, "interval": [absorption - 0.01, absorption + 0.01]}
        if void:
            details["discounted_by"] = void
        result.add(
            Evidence(
                "absorption",
                name,
                absorption - 0.01,
                0.01,
                True,
                "absorption",
                details,
                void=f"void beside {void}" if void else "",
            )
        )
    return result.to_json()


def test_report_carries_the_diagnosis(tmp_path):
    paths = prepare_run_folder(tmp_path / "run")
    diagnosis = {
        "verdict": "significant unmodelled effects: vignetting",
        "candidates": [
            candidate(
                "vignetting",
                "absorption",
                probe=(0.035, 0.012, 0.06),
                absorption=0.104,
                parameters={"corner_falloff": 0.7, "radius_unit": "half image diagonal ..."},
            ),
            candidate("pose_error", "", probe=(0.05, -0.01, 0.09)),
            candidate(
                "lens_distortion",
                "",
                probe=(0.01, -0.02, 0.03),
                absorption=0.25,
                void="defocus_blur",
            ),
        ],
        "refits": [
            {
                "effects": ["vignetting"],
                "before_rmse": 0.0304,
                "after_rmse": 0.0251,
                "floor": 0.0077**2,
                "closed_fraction": 0.23,
                "relight_closed_fraction": 0.41,
                "parameters": {"vignetting": {"corner_falloff": 0.6543, "covered_radius": 0.57}},
            },
            {
                "effects": ["vignetting", "pose_error"],
                "before_rmse": 0.0251,
                "after_rmse": 0.0249,
                "floor": 0.0077**2,
                "closed_fraction": 0.01,
            },
        ],
        "figures": {},
    }
    paths.diagnosis.write_text(json.dumps(diagnosis))
    report_stage(RunConfig(), paths, torch.device("cpu"))
    markdown = paths.report_markdown.read_text()
    assert "Verdict: significant unmodelled effects: vignetting" in markdown
    assert (
        "| vignetting | absorption | 0.035 | [0.012, 0.060] | 0.104 |  | yes | vignetting: why |"
        in markdown
    )
    assert "| pose_error |  | 0.050 | [-0.010, 0.090] |  |  |  | pose_error: why |" in markdown
    # The recovered parameters: the refit's (training views) over the evidence's; explanations
    # stay in diagnosis.json.
    assert "| vignetting | refit | corner_falloff 0.654, covered_radius 0.57 |" in markdown
    # An absorption voided beside the conditioning effect says so instead of looking decisive.
    assert "| 0.250 (void beside defocus_blur) |  |  | lens_distortion: why |" in markdown
    assert "| vignetting | 0.0304 | 0.0251 | 0.0077 | 23 % | 41 % |" in markdown
    # Without a relight split the refit has no relight figures and the cell stays empty.
    assert "| vignetting + pose_error | 0.0251 | 0.0249 | 0.0077 | 1 % |  |" in markdown
    page = paths.report_html.read_text()
    assert "<h2>Gap diagnosis</h2>" in page
    assert "<td>absorption</td><td>0.035</td>" in page and "<td>23 %</td>" in page

"""kind: diagnosis: the blind benchmark's cases as sweep trials (withheld effect -> fit ->
blind diagnosis -> score), with the truth beside each run folder and a confusion matrix."""

from __future__ import annotations

import json

from sweep_helpers import records, write_sweep

from recon.cli import main


def test_a_diagnosis_sweep_scores_withheld_effects(tmp_path, capsys):
    out = tmp_path / "blind"
    sweep = write_sweep(
        tmp_path,
        out,
        kind="diagnosis",
        grid=None,
        withhold=[["exposure"], []],
        seeds=[0],
        diagnose={"refit": "none", "candidates": ["exposure", "white_balance", "vignetting"]},
        metrics=["score.top1_correct", "score.predicted_top", "fit.loss"],
    )
    text = sweep.read_text().replace("grid: null\n", "")
    sweep.write_text(text)
    assert main(["sweep", str(sweep)]) == 0, capsys.readouterr().err
    found = records(out)
    assert [record["parameters"]["withhold"] for record in found] == ["exposure", "none"]
    withheld, clean = found
    folder = out / "trials" / withheld["trial_id"]
    # The truth lies beside the run folder, never in it; the clean case has none.
    truth = json.loads((folder / "truth.json").read_text())
    assert [item["name"] for item in truth["withheld"]] == ["exposure"]
    assert not list((folder / "run").rglob("truth*.json"))
    assert not (out / "trials" / clean["trial_id"] / "truth.json").exists()
    # The diagnosis ran on the run folder, and the record is its score against the truth.
    diagnosis = json.loads((folder / "run" / "diagnosis.json").read_text())
    significant = [item["name"] for item in diagnosis["candidates"] if item["significant"]]
    assert withheld["diagnosis"]["truth"] == ["exposure"]
    assert withheld["diagnosis"]["predicted_top"] == (significant[0] if significant else "none")
    assert withheld["metrics"]["score.top1_correct"] == (
        withheld["diagnosis"]["predicted_top"] == "exposure"
    )
    assert clean["diagnosis"]["truth"] == []
    assert "alt='confusion matrix'" in (out / "summary.html").read_text()

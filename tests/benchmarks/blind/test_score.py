"""benchmarks/blind/score.py: leave-one-scene-out calibration and the metrics, on stored
diagnoses made up for the purpose (no fit: the scoring is what is tested)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.blind.decide import code_thresholds
from benchmarks.blind.score import (
    inert_effects,
    leave_one_scene_out,
    leave_one_world_and_scene_out,
    load_collected,
    score_one,
    summarise_world,
)
from recon.diagnose.records import Candidate, Diagnosis, Evidence


def _fake_record(
    tmp_path: Path, world: str, scene: str, withheld: tuple, pose: float, shadows: float = 0.0
) -> dict:
    """A collected case whose stored diagnosis has a pose probe reaching `pose`, a shadows probe
    reaching `shadows`, and an exposure probe reaching 0.5 where exposure was withheld (no fit:
    the scoring is what is tested)."""
    folder = tmp_path / world / scene / ("+".join(withheld) or "none")
    folder.mkdir(parents=True)
    exposure = 0.5 if "exposure" in withheld else 0.0

    def item(effect: str, reduction: float) -> dict:
        return {
            "effect": effect,
            "score": reduction,
            "heldout_reduction": reduction,
            "interval": [0.9 * reduction, 1.1 * reduction],
            "significant": False,
        }

    diagnosis = {
        "ranking": [
            item("pose_error", pose),
            item("exposure", exposure),
            item("shadows", shadows),
        ],
        "refits": [],
        "gap": {},
        "timings": {"diagnose_seconds": 1.0},
    }
    (folder / "diagnosis.json").write_text(json.dumps(diagnosis))
    truth = tmp_path / "truth" / f"{world}_{scene}_{'+'.join(withheld)}.json"
    truth.parent.mkdir(parents=True, exist_ok=True)
    truth.write_text(json.dumps({"withheld": [], "realised": {}}))
    return {
        "case": {"world": world, "scene": scene, "withheld": list(withheld), "seed": 0},
        "run_folder": str(folder),
        "truth_file": str(truth),
        "fit_seconds": 10.0,
        "diagnose_seconds": 1.0,
    }


def test_leave_one_scene_out_never_scores_a_scene_it_calibrated_on(tmp_path):
    # The torus' clean fit leaves a large pose misfit (0.3); the blob's a small one (0.01).
    records = [
        _fake_record(tmp_path, "own", "torus", (), pose=0.3),
        _fake_record(tmp_path, "own", "torus", ("exposure",), pose=0.3),
        _fake_record(tmp_path, "own", "blob", (), pose=0.01),
        _fake_record(tmp_path, "own", "blob", ("exposure",), pose=0.01),
        _fake_record(tmp_path, "mitsuba", "spot_glossy", (), pose=0.01),
        # The path tracer's cast shadows are in every render: a clean case's shadows evidence
        # (0.4) is neither a false positive nor a null for calibration.
        _fake_record(tmp_path, "mitsuba", "blob", (), pose=0.01, shadows=0.4),
        _fake_record(tmp_path, "real", "ethiopian_head", (), pose=0.01),
    ]
    for record in records[4:5]:  # the glossy spot
        record["case"]["intrinsic"] = ["specular"]
    loaded = [load_collected(record) for record in records]
    scored, calibrations = leave_one_scene_out(loaded, {"name": "test"})
    assert len(scored) == len(records)
    for record in scored:
        assert record["scene"] not in record["calibrated_on"]
    # The torus is scored with the blob's (and spot's glossy: no clean case) allowance: its own
    # pose misfit of 0.3 clears twice the blob's 0.01 and is named, a spurious second effect.
    torus = {record["case"]: record for record in scored if record["scene"] == "torus"}
    assert calibrations["torus"]["thresholds"]["probe.pose_error"] == pytest.approx(0.02)
    assert torus["none"]["significant"] == ["pose_error"]
    assert torus["none"]["false_positive"] is True
    assert torus["exposure"]["top1_correct"] and not torus["exposure"]["exact_set"]
    # The blob calibrated on the torus: pose allowance 0.6, its own 0.01 stays silent.
    blob = {record["case"]: record for record in scored if record["scene"] == "blob"}
    assert calibrations["blob"]["thresholds"]["probe.pose_error"] == pytest.approx(0.6)
    assert blob["none"]["significant"] == [] and blob["exposure"]["exact_set"]
    # The real photos are calibrated on every synthetic scene with a clean case, never on
    # themselves; the glossy spot has no clean case (its truth is specular), so it calibrates
    # nothing.
    real = next(record for record in scored if record["world"] == "real")
    assert real["calibrated_on"] == ["blob", "torus"]
    glossy = next(record for record in scored if record["scene"] == "spot_glossy")
    assert glossy["kind"] == "single" and glossy["truth"] == ["specular"]
    mitsuba_blob = next(r for r in scored if r["world"] == "mitsuba" and r["scene"] == "blob")
    assert mitsuba_blob["false_positive"] is False and mitsuba_blob["exact_set"]
    assert mitsuba_blob["present_named"] == ["shadows"] and not mitsuba_blob["exact_set_strict"]
    assert calibrations["torus"]["thresholds"]["probe.shadows"] == pytest.approx(0.02)
    summary = summarise_world([record for record in scored if record["world"] == "own"])
    assert summary["false_positive_rate"] == 0.5
    assert summary["top1_accuracy"] == 1.0
    assert summary["exact_set_accuracy"] == 0.5
    provenance = calibrations["blob"]["provenance"]
    assert provenance["scenes"] == ["torus"] and provenance["seeds"] == [0]
    assert provenance["commit"]


def test_leaving_a_world_out_never_calibrates_a_world_or_scene_on_itself(tmp_path):
    # The own torus's clean fit leaves a pose misfit (0.3) that its own world's other scene
    # does not (0.01); the path tracer's blob leaves 0.2.
    records = [
        _fake_record(tmp_path, "own", "torus", (), pose=0.3),
        _fake_record(tmp_path, "own", "blob", (), pose=0.01),
        _fake_record(tmp_path, "mitsuba", "torus", (), pose=0.05),
        _fake_record(tmp_path, "mitsuba", "blob", (), pose=0.2),
        _fake_record(tmp_path, "real", "ethiopian_head", (), pose=0.01),
    ]
    loaded = [load_collected(record) for record in records]
    scored, calibrations = leave_one_world_and_scene_out(loaded, {"name": "test"})
    assert len(scored) == len(records)
    for key, calibration in calibrations.items():
        world, group = key.split("/")
        for case in calibration["provenance"]["calibrated_on"]:
            assert case["scene"] != group
            assert world == "real" or case["world"] != world
    # The own torus is calibrated on the path tracer's blob alone (twice 0.2): its 0.3 stays
    # silent. The path tracer's torus on the own blob alone (twice 0.01; leave-one-scene-out
    # also counts its own world's blob, 0.4): its 0.05 is named.
    assert calibrations["own/torus"]["thresholds"]["probe.pose_error"] == pytest.approx(0.4)
    assert calibrations["mitsuba/torus"]["thresholds"]["probe.pose_error"] == pytest.approx(0.02)
    by_key = {(record["world"], record["scene"]): record for record in scored}
    assert by_key[("own", "torus")]["false_positive"] is False
    assert by_key[("mitsuba", "torus")]["false_positive"] is True
    # The real photos are calibrated on both synthetic worlds' other scenes.
    assert by_key[("real", "ethiopian_head")]["calibrated_on"] == ["blob", "torus"]
    # With one synthetic world there is nothing to calibrate it on: it is left out.
    alone, _ = leave_one_world_and_scene_out(loaded[:2], {"name": "test"})
    assert alone == []


def test_a_defocus_inside_the_centre_pixel_is_inert():
    # Stored cases from before the sampler's 1 px floor hold 0.47 px at 48 px: the identity.
    inert = inert_effects(
        {"withheld": [{"name": "defocus_blur", "parameters": {"radius_px": 0.47}}]}
    )
    assert inert == ["defocus_blur"]
    seen = {"withheld": [{"name": "defocus_blur", "parameters": {"radius_px": 0.95}}]}
    assert inert_effects(seen) == []


def _stored_case(tmp_path: Path, withheld: tuple, radius: float = 0.47) -> dict:
    """A collected case whose diagnosis names nothing and reports white_balance not
    identifiable (schema 2 records), with a defocus of radius where it is withheld."""
    folder = tmp_path / ("+".join(withheld) or "none")
    folder.mkdir(parents=True)
    white = Candidate(
        "white_balance",
        [
            Evidence("probe", "white_balance", 0.001, 0.02, False, "probe", {"reduction": 0.01}),
            Evidence(
                "identifiability",
                "white_balance",
                0.01,
                0.037,
                False,
                "a colour cast common to every view is absorbed by the albedo's colour",
                {"capture": "a grey card"},
            ),
        ],
    )
    (folder / "diagnosis.json").write_text(json.dumps(Diagnosis(candidates=[white]).to_json()))
    truth = tmp_path / f"{folder.name}_truth.json"
    parameters = {"defocus_blur": {"radius_px": radius}, "white_balance": {}}
    truth.write_text(
        json.dumps({"withheld": [{"name": n, "parameters": parameters[n]} for n in withheld]})
    )
    return {
        "case": {"world": "own", "scene": "torus", "withheld": list(withheld), "seed": 0},
        "run_folder": str(folder),
        "truth_file": str(truth),
        "fit_seconds": 10.0,
        "diagnose_seconds": 1.0,
    }


def test_inert_cases_are_clean_and_unidentifiable_truths_are_answered_not_found(tmp_path):
    thresholds = code_thresholds()
    inert = score_one(load_collected(_stored_case(tmp_path, ("defocus_blur",))), thresholds, [])
    assert inert["kind"] == "clean" and inert["truth"] == [] and inert["inert"] == ["defocus_blur"]
    assert inert["exact_set"] and inert["false_positive"] is False
    white = score_one(load_collected(_stored_case(tmp_path, ("white_balance",))), thresholds, [])
    assert white["not_identifiable"] == ["white_balance"]
    assert not white["top1_correct"] and not white["exact_set"]  # strict: a miss
    assert white["top1_answered"] and white["exact_set_answered"]  # answered, not found
    summary = summarise_world([inert, white])
    assert summary["inert"] == {"defocus_blur": 1}
    assert summary["top1_accuracy"] == 0.0 and summary["top1_answered"] == 1.0


def test_gap_closed_is_the_share_of_the_effects_error_a_refit_removes():
    """Known answers: the clean fit's held-out error is 2, the effect case's 10 before and 4
    after its refit, so the refit removes (10 - 4) / (10 - 2) = 3/4 of what the effect added;
    an effect that adds less than a tenth of the clean error has no gap of its own (None), and
    neither has a case without a clean reference or without a refit."""
    from benchmarks.blind.score import SMALLEST_EFFECT_SHARE, gap_closed_of_effect

    refit = {"effects": ["exposure"], "before": 10.0, "after": 4.0}
    assert gap_closed_of_effect(refit, 2.0) == pytest.approx(0.75)
    barely = {"effects": ["vignetting"], "before": 2.0 * (1 + SMALLEST_EFFECT_SHARE / 2)}
    assert gap_closed_of_effect({**barely, "after": 1.0}, 2.0) is None
    assert gap_closed_of_effect(refit, None) is None and gap_closed_of_effect(None, 2.0) is None


def test_the_clean_reference_is_the_untouched_case_of_the_same_scene_and_seed(tmp_path):
    """A refit record of an exposure case is scored against the held-out error of the clean
    case of its world, scene and seed (gap.heldout_mse), and the median counts it."""
    from benchmarks.blind.score import with_clean_references

    records = []
    for withheld, gap, refits in (
        ((), {"heldout_mse": 2.0}, []),
        (
            ("exposure",),
            {"heldout_mse": 10.0},
            [{"effects": ["exposure"], "before": 10.0, "after": 4.0}],
        ),
    ):
        record = load_collected(_fake_record(tmp_path, "own", "spot", withheld, 0.0))
        record["diagnosis"] = {**record["diagnosis"], "gap": gap, "refits": refits}
        records.append(record)
    clean, exposure = with_clean_references(records)
    assert clean["clean_heldout_mse"] == exposure["clean_heldout_mse"] == 2.0
    scored = score_one(exposure, code_thresholds(), [])
    assert scored["closed_of_effect"] == pytest.approx(0.75) and scored["refitted"] == ["exposure"]
    summary = summarise_world([score_one(clean, code_thresholds(), []), scored])
    assert summary["median_closed_of_effect"] == pytest.approx(0.75)
    assert summary["median_closed_of_effect_true"] == pytest.approx(0.75)
    assert summary["refits_scored"] == 1 and summary["refits_no_gap"] == 0


def test_an_injected_exposure_is_measured_against_the_untouched_photos_own_reading():
    """The untouched real photos read per-view gains against the fit (a glossy object under a
    diffuse model); the injected exposure's recovery divides them out (same views, same
    estimator), while the absolute measure keeps them."""
    from benchmarks.blind.score import exposure_errors_vs_untouched, exposure_reading
    from recon.sweep.scoring import parameter_errors

    def diagnosis(ratios):
        return {
            "candidates": [
                {
                    "name": "exposure",
                    "significant": True,
                    "decided_by": "probe",
                    "parameters": {"ratios": ratios},
                }
            ],
            "refits": [],
        }

    own = [1.1, 0.9, 1.0, 1.0]  # what the untouched photos read (their exposure is fixed)
    injected = [0.5, 1.0, 2.0, 1.0]
    truth = {"realised": {"test": [{"name": "exposure", "parameters": {"ratios": injected}}]}}
    case = diagnosis([a * b for a, b in zip(own, injected, strict=True)])
    clean = exposure_reading(diagnosis(own))
    assert clean == {"source": "heldout", "ratios": own, "estimator": "", "backdrop": None}
    errors = exposure_errors_vs_untouched(case, truth, clean)
    assert errors["exposure_ratio_max_vs_untouched"] == pytest.approx(0.0, abs=1e-9)
    assert parameter_errors(case, truth)["exposure_ratio_max"] > 0.09
    # Readings from different views (a refit's training views) are not compared.
    refitted = {**case, "refits": [{"parameters": {"exposure": {"ratios": [1.0] * 4}}}]}
    assert exposure_errors_vs_untouched(refitted, truth, clean) == {}
    assert exposure_errors_vs_untouched(case, truth, None) == {}
    assert exposure_reading({"ranking": []}) is None


def test_a_gain_read_off_the_backdrop_is_compared_with_the_untouched_backdrop():
    """Where the case's exposure was read off the static backdrop (estimator "backdrop"), the
    untouched photos' reading it is divided by is their backdrop's too, not the object's gains
    (which carry the object's own change from view to view)."""
    import math

    from benchmarks.blind.score import exposure_errors_vs_untouched, exposure_reading

    def diagnosis(ratios, estimator, backdrop):
        evidence = {
            "kind": "backdrop",
            "details": {"backdrop_components": [[math.log(value)] for value in backdrop]},
        }
        return {
            "candidates": [
                {
                    "name": "exposure",
                    "significant": True,
                    "decided_by": "probe",
                    "parameters": {"ratios": ratios, "estimator": estimator},
                    "evidence": [evidence],
                }
            ],
            "refits": [],
        }

    frames = [1.04, 0.97, 1.0, 0.99]  # the untouched frames' own change (the backdrop's)
    object_gains = [1.15, 0.85, 1.05, 0.95]  # the object's, with its reflectance's change
    injected = [0.5, 1.0, 2.0, 1.0]
    truth = {"realised": {"test": [{"name": "exposure", "parameters": {"ratios": injected}}]}}
    seen = [a * b for a, b in zip(frames, injected, strict=True)]
    case = diagnosis(seen, "backdrop", seen)
    clean = exposure_reading(diagnosis(object_gains, "highlight_free", frames))
    assert clean["backdrop"] == pytest.approx(frames)
    errors = exposure_errors_vs_untouched(case, truth, clean)
    assert errors["exposure_ratio_max_vs_untouched"] == pytest.approx(0.0, abs=1e-9)
    # Against the object's gains it would be off by the object's own change.
    mixed = {**clean, "backdrop": None}
    assert exposure_errors_vs_untouched(case, truth, mixed) == {}
    object_case = diagnosis(seen, "highlight_free", seen)
    assert (
        exposure_errors_vs_untouched(object_case, truth, clean)["exposure_ratio_max_vs_untouched"]
        > 0.05
    )

"""A diagnosis.json written before the typed records (a "ranking" of flat entries) is read as a
Diagnosis whose measurements are Evidence, and re-deciding it gives the decisions the old
hand-ordered rule gave."""

from __future__ import annotations

from recon.diagnose.decision import redecide
from recon.diagnose.records import Diagnosis


def entry(effect, interval, **fields):
    record = {
        "effect": effect,
        "score": 0.0,
        "heldout_reduction": sum(interval) / 2,
        "interval": list(interval),
        "significant": False,
        "parameters": {},
        "probe_parameters": {"from": "probe"},
        "absorption": None,
        "absorption_interval": None,
        "evidence": "",
    }
    record.update(fields)
    return record


OLD = {
    "gap": {"rmse": 0.1},
    "where": {},
    "ranking": [
        entry("vignetting", (0.3, 0.5), flat_field={"deviation": 0.01, "corner_falloff": 0.99}),
        entry(
            "response_curve",
            (-0.01, 0.01),
            relight_reduction=0.2,
            relight_interval=[0.13, 0.33],
            relight_parameters={"gamma": 0.8},
        ),
        entry(
            "lens_distortion",
            (-0.01, 0.01),
            absorption=0.3,
            absorption_interval=[0.2, 0.4],
            absorption_discounted_by="defocus_blur",
        ),
        entry(
            "shadows",
            (-0.01, 0.0),
            fingerprint={"share": 0.8, "interval": [0.7, 0.9], "coverage": 0.3},
        ),
        entry("exposure", (0.4, 0.6)),
    ],
    "refits": [],
    "verdict": "",
    "timings": {"diagnose_seconds": 1.0},
}


def test_an_old_diagnosis_is_redecided_as_the_old_rule_decided():
    decided = redecide(OLD)
    assert [item.name for item in decided.candidates[:2]] == ["exposure", "response_curve"]
    assert [item.decided_by for item in decided.candidates[:2]] == ["probe", "relight"]
    # The old fingerprint share had no null from the run: recorded, it names nothing now.
    shadows = decided.candidate("shadows")
    fingerprint = shadows.evidence_of("fingerprint")
    assert not shadows.significant and "without placebo lights" in fingerprint.reason
    assert fingerprint.details["slope"] == 0.8
    assert decided.candidate("response_curve").parameters == {"gamma": 0.8}
    lens = decided.candidate("lens_distortion")
    assert (
        not lens.significant and "void beside defocus_blur" in lens.evidence_of("absorption").void
    )
    assert not decided.candidate("vignetting").significant  # the flat field overrules
    assert decided.verdict == "significant unmodelled effects: exposure, response_curve"
    # Written back, it is the current schema.
    assert Diagnosis.from_json(decided.to_json()).candidates[0].name == "exposure"

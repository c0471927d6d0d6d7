"""The diagnosis's typed records survive a JSON round trip exactly."""

from __future__ import annotations

import json
import math

from recon.diagnose.records import Evidence


def test_evidence_round_trips_through_json_including_nan_threshold():
    evidence = Evidence(
        kind="specificity",
        candidate="exposure",
        statistic=0.31,
        threshold=math.nan,
        passed=False,
        reason="per-view gains vary with n.h (r = 0.31): view-dependent reflectance",
        details={"gains": [1.0, 0.9]},
    )
    text = json.dumps(evidence.to_json(), allow_nan=False)
    back = Evidence.from_json(json.loads(text))
    assert back.kind == evidence.kind and back.candidate == evidence.candidate
    assert back.statistic == evidence.statistic and math.isnan(back.threshold)
    assert back.passed is False and back.details == {"gains": [1.0, 0.9]}

"""The geometric specificity verdict from its pair records (recon.diagnose.geometric_specificity).

The pair records hold what each geometric candidate and each confuser removes alone and on top
of the other (held-out reductions with bootstrap intervals); the verdict compares them with the
probes' allowances. It is kept apart from the measurement so the decision (recon.diagnose.
decision) can judge the stored records again with another calibration's allowances: a
candidate that only a leave-one-scene-out calibration makes significant is checked with the
allowances that name it, not with those the diagnosis ran with.

A verdict applies to the probe's claim only: when the candidate's probe lower bound
(``details["probe_lower_bound"]``) does not clear its allowance, the probes' comparison does not
speak to it (an absorption refit sees a distortion the fit bent into the geometry, which the
probes cannot), and the check passes as not judged.

The same records give a second way for a probe to clear (``beyond_confusers``, the decision
table's "beyond_confusers" row): what it still removes on top of each confuser's probe. A
poor silhouette fit (the path-traced teapot at 48 px) is reduced by any warp or blur, so each
geometric probe alone removes 10 % of a clean fit's error and the allowances calibrated on it
(twice that) hide a real pose error elsewhere; on top of the confusers that common part is
gone (the clean teapot's pose probe keeps 2 %, a pose error 8-30 %). It is a null that
scales with the fit: the confusers are this run's own placebos of the same family, and the
allowance (``diagnose.decision.beyond_confusers_allowance``) is calibrated on clean fits
as the probes' are. Where it clears, the comparison is judged even if the probe alone does
not clear (the candidate's claim is then the records').
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

from recon.diagnose.records import Evidence

KIND = "specificity"
BEYOND = "beyond_confusers"
# The data's edge widths by direction (recon.diagnose.edge_width) break a tie between the two
# blurs: details["edges_favour"] of a specificity check names the one they favour.
EDGES = "edges"
EDGE_PAIR = frozenset({"defocus_blur", "motion_blur"})


def _excess(entry: dict, allowance: float) -> float:
    return entry["interval"][0] - allowance


def swapped(record: dict) -> dict:
    """The pair record seen from the confuser's side."""
    return {
        **record,
        "candidate": record["confuser"],
        "confuser": record.get("candidate"),
        "alone": record["confuser_alone"],
        "confuser_alone": record["alone"],
        "on_top_of_confuser": record["confuser_on_top"],
        "confuser_on_top": record["on_top_of_confuser"],
        "allowance": record["confuser_allowance"],
        "confuser_allowance": record["allowance"],
    }


def redundant(record: dict, margin: float) -> bool:
    """Whether the pair cannot be told apart and the confuser explains more: both clear alone,
    neither clears its allowance on top of the other, neither takes the other's place
    (``dominated``), and the confuser alone clears its allowance by more than the candidate
    alone (one cause suffices; the stronger is named)."""
    if dominated(swapped(record), margin):
        return False
    confuser_excess = _excess(record["confuser_alone"], record["confuser_allowance"])
    own_excess = _excess(record["alone"], record["allowance"])
    neither_adds = (
        _excess(record["on_top_of_confuser"], record["allowance"]) <= 0
        and _excess(record["confuser_on_top"], record["confuser_allowance"]) <= 0
    )
    return confuser_excess > 0 and own_excess > 0 and neither_adds and confuser_excess > own_excess


def tied(record: dict, margin: float) -> bool:
    """Whether the probes see both and cannot separate them: each clears its allowance alone,
    and neither's reduction on top of the other exceeds the other's on top of it (lower bound
    above upper bound + margin)."""
    both_clear = (
        record["alone"]["interval"][0] > record["allowance"]
        and record["confuser_alone"]["interval"][0] > record["confuser_allowance"]
    )
    on_top, confuser_on_top = record["on_top_of_confuser"], record["confuser_on_top"]
    separated = (
        on_top["interval"][0] > confuser_on_top["interval"][1] + margin
        or confuser_on_top["interval"][0] > on_top["interval"][1] + margin
    )
    return both_clear and not separated


def _edge_tie(name: str, record: dict, margin: float, favoured: str | None) -> bool:
    """Whether the edges settle candidate name's record: it pairs the two blurs, the probes
    tie, and the edges favour one of the two."""
    pair = {name, record["confuser"]}
    return favoured in pair and pair == EDGE_PAIR and tied(record, margin)


def dominated(record: dict, margin: float) -> bool:
    """Whether the confuser takes the candidate's place: it clears its own allowance alone, the
    candidate on top of it does not clear the candidate's, and the confuser adds more on top of
    the candidate than the candidate adds on top of it (lower bound above upper bound + margin)."""
    confuser_clears = record["confuser_alone"]["interval"][0] > record["confuser_allowance"]
    candidate_adds = record["on_top_of_confuser"]["interval"][0] > record["allowance"]
    separated = (
        record["confuser_on_top"]["interval"][0]
        > record["on_top_of_confuser"]["interval"][1] + margin
    )
    return confuser_clears and not candidate_adds and separated


def _percent(entry: dict) -> str:
    low, high = entry["interval"]
    return f"{100 * entry['reduction']:.1f} % ({100 * low:.1f} to {100 * high:.1f})"


def _kept_because(name: str, record: dict) -> str:
    """Why the confuser of the least clear pair does not take the candidate's place."""
    confuser, on_top = record["confuser"], record["on_top_of_confuser"]
    if _excess(on_top, record["allowance"]) > 0:
        return (
            f"on top of every confuser it still clears its allowance (least: on top of "
            f"{confuser}, {_percent(on_top)} of the held-out error)"
        )
    if _excess(record["confuser_alone"], record["confuser_allowance"]) <= 0:
        return (
            f"on top of {confuser} it removes {_percent(on_top)}, but {confuser} alone "
            f"({_percent(record['confuser_alone'])}) does not clear its own allowance "
            f"{100 * record['confuser_allowance']:.1f} %, so it cannot take its place"
        )
    return (
        f"on top of {confuser} it removes {_percent(on_top)}, {confuser} on top of it "
        f"{_percent(record['confuser_on_top'])}: not separable, and {name} alone explains "
        f"as much or more ({_percent(record['alone'])} against "
        f"{_percent(record['confuser_alone'])})"
    )


def judge(
    name: str,
    records: list[dict],
    margin: float,
    probe_lower_bound: float | None = None,
    allowance: Callable[[str], float] | None = None,
    edges_favour: str | None = None,
) -> Evidence:
    """The specificity Evidence of one geometric candidate from its pair records (pair_record
    in recon.diagnose.geometric_specificity). allowance: each effect's probe allowance, to
    judge with instead of the records' own; probe_lower_bound: the candidate's probe lower
    bound (the check passes, not judged, when it does not clear the allowance); edges_favour:
    the blur the data's edge widths favour (recon.diagnose.edge_width), which settles a tie
    between the two blurs: the other one loses it."""
    if allowance is not None:
        records = [
            {
                **record,
                "allowance": allowance(record["candidate"]),
                "confuser_allowance": allowance(record["confuser"]),
            }
            for record in records
        ]
    details: dict = {"pairs": records, "margin": margin}
    if probe_lower_bound is not None:
        details["probe_lower_bound"] = probe_lower_bound
    if edges_favour is not None:
        details["edges_favour"] = edges_favour
    own_allowance = records[0]["allowance"] if records else float("nan")
    if probe_lower_bound is not None and not probe_lower_bound > own_allowance:
        details["not_judged"] = True
        reason = (
            f"not judged: {name}'s probe (lower bound {100 * probe_lower_bound:.1f} %) does not "
            f"clear its allowance {100 * own_allowance:.1f} %, so the probes' comparison does "
            "not speak to it"
        )
        return Evidence(KIND, name, probe_lower_bound, own_allowance, True, reason, details)
    settled = [record for record in records if _edge_tie(name, record, margin, edges_favour)]
    lost_at_edges = [record for record in settled if record["confuser"] == edges_favour]
    if lost_at_edges:
        record = lost_at_edges[0]
        confuser = record["confuser"]
        details["alternative"] = confuser
        reason = (
            f"the probes cannot separate {name} and {confuser} (on top of each other they "
            f"remove {_percent(record['on_top_of_confuser'])} and "
            f"{_percent(record['confuser_on_top'])}), and the data's edges are {confuser}'s: "
            f"{'wider across one direction per view' if confuser == 'motion_blur' else 'as wide in every direction'}"
        )
        statistic = record["on_top_of_confuser"]["interval"][0]
        return Evidence(KIND, name, statistic, record["allowance"], False, reason, details)
    # A tie the edges settle in the candidate's favour takes nothing from it.
    records = [record for record in records if record not in settled]
    if not records:
        record = settled[0]
        reason = (
            f"{name} is specific: the probes cannot separate it from {record['confuser']}, and "
            f"the data's edges are {name}'s"
        )
        statistic = record["on_top_of_confuser"]["interval"][0]
        return Evidence(KIND, name, statistic, record["allowance"], True, reason, details)
    losing = [record for record in records if dominated(record, margin)]
    ties = [record for record in records if record not in losing and redundant(record, margin)]
    if not losing and ties:
        stronger = max(
            ties, key=lambda record: _excess(record["confuser_alone"], record["confuser_allowance"])
        )
        confuser = stronger["confuser"]
        details["alternative"] = confuser
        reason = (
            f"{name} and {confuser} are not separable here (on top of each other they remove "
            f"{_percent(stronger['on_top_of_confuser'])} and {_percent(stronger['confuser_on_top'])}"
            f", neither clearing its allowance), and {confuser} alone explains more "
            f"({_percent(stronger['confuser_alone'])} against {_percent(stronger['alone'])}): "
            f"one cause suffices, {confuser}"
        )
        statistic = stronger["on_top_of_confuser"]["interval"][0]
        return Evidence(KIND, name, statistic, stronger["allowance"], False, reason, details)
    if not losing:
        closest = min(
            records,
            key=lambda record: _excess(record["on_top_of_confuser"], record["allowance"]),
        )
        reason = f"{name} is specific: " + _kept_because(name, closest)
        statistic = closest["on_top_of_confuser"]["interval"][0]
        return Evidence(KIND, name, statistic, closest["allowance"], True, reason, details)
    # The confuser that leaves the candidate least.
    worst = min(losing, key=lambda record: record["on_top_of_confuser"]["reduction"])
    confuser = worst["confuser"]
    details["alternative"] = confuser
    reason = (
        f"on top of {confuser} (alone {_percent(worst['confuser_alone'])}), {name} removes only "
        f"{_percent(worst['on_top_of_confuser'])} of the held-out error, while {confuser} on "
        f"top of {name} removes {_percent(worst['confuser_on_top'])}: the signature is "
        f"{confuser}'s, not {name}'s"
    )
    statistic = worst["on_top_of_confuser"]["interval"][0]
    return Evidence(KIND, name, statistic, worst["allowance"], False, reason, details)


def rejudge(evidence: Evidence, allowance: Callable[[str], float]) -> Evidence:
    """A stored geometric specificity Evidence (one with details["pairs"]) judged again with
    other probe allowances; any other evidence comes back unchanged."""
    records = evidence.details.get("pairs")
    if evidence.kind != KIND or not records:
        return evidence
    judged = judge(
        evidence.candidate,
        records,
        float(evidence.details.get("margin", 0.0)),
        evidence.details.get("probe_lower_bound"),
        allowance,
        evidence.details.get("edges_favour"),
    )
    return Evidence(
        judged.kind,
        judged.candidate,
        judged.statistic,
        judged.threshold,
        judged.passed,
        judged.reason,
        judged.details,
        evidence.void,
    )


def beyond_confusers(
    evidence: list[Evidence],
    allowance: Callable[[str], float],
    beyond_allowance: Callable[[str], float] | None,
) -> list[Evidence]:
    """One candidate's evidence with its "beyond_confusers" Evidence derived again from its
    geometric specificity records (any stored one is replaced): statistic the least lower bound
    of what its probe removes on top of a confuser's, threshold beyond_allowance(candidate).
    Where it clears and the specificity check was not judged (the probe alone does not clear),
    the check is judged with the probes' allowances (allowance), as it would be for a probe that
    cleared. beyond_allowance None (an effect without one): nothing is derived."""
    kept = [item for item in evidence if item.kind != BEYOND]
    check = next((item for item in kept if item.kind == KIND and item.details.get("pairs")), None)
    if check is None or beyond_allowance is None:
        return kept
    records = check.details["pairs"]
    name = check.candidate
    least = min(records, key=lambda record: record["on_top_of_confuser"]["interval"][0])
    statistic = float(least["on_top_of_confuser"]["interval"][0])
    threshold = float(beyond_allowance(name))
    passed = statistic > threshold
    reason = (
        f"{name}'s probe still removes part of the held-out error on top of every confuser's "
        f"(least: on top of {least['confuser']}'s, {_percent(least['on_top_of_confuser'])}); "
        "lower bound"
    )
    derived = Evidence(
        BEYOND,
        name,
        statistic,
        threshold,
        passed,
        reason,
        {"confuser": least["confuser"], "reduction": least["on_top_of_confuser"]["reduction"]},
        check.void,
    )
    if passed and check.details.get("not_judged"):
        judged = judge(
            name,
            records,
            float(check.details.get("margin", 0.0)),
            None,
            allowance,
            check.details.get("edges_favour"),
        )
        judged = replace(judged, void=check.void)
        judged.details["probe_lower_bound"] = check.details.get("probe_lower_bound")
        kept = [judged if item is check else item for item in kept]
    return kept + [derived]


# The confusers that move or spread pixels: a prediction that one of them explains a candidate
# as well is measured by the candidate's pair record with it.
MEASURED_CONFUSERS = ("pose_error", "motion_blur", "defocus_blur")


def measured_condition(evidence: list[Evidence]) -> list[Evidence]:
    """One candidate's evidence with an identifiability condition that asks to be measured
    (details["measured_by"] == "pairs": the lens distortion's, predicted from a reference
    distortion) judged by the run's own records instead, where they exist: the candidate's
    probe passed its per-run null (placebo fields of its size), and its pair records say what
    it keeps on top of each confuser that moves or spreads pixels. A confuser is told apart when
    that lower bound exceeds the null's placebo 95th percentile (this run's, not a constant);
    the condition passes when every one is, else it names those that explain it as well. The
    prediction is kept (details["prediction"]) and the judgement derived again each time."""
    condition = next(
        (
            item
            for item in evidence
            if item.kind == "identifiability"
            and (item.details.get("measured_by") == "pairs" or "prediction" in item.details)
        ),
        None,
    )
    if condition is None:
        return evidence
    prediction = (
        Evidence.from_json(condition.details["prediction"])
        if "prediction" in condition.details
        else condition
    )
    check = next(
        (item for item in evidence if item.kind == KIND and item.details.get("pairs")), None
    )
    null = next((item for item in evidence if item.kind == "null"), None)
    favour = check.details.get("edges_favour") if check is not None else None
    margin = float(check.details.get("margin", 0.0)) if check is not None else 0.0
    records = [
        record
        for record in (check.details["pairs"] if check is not None else [])
        if record["confuser"] in MEASURED_CONFUSERS
        # The edges told this blur from the other: that one explains it no longer.
        and not (
            favour == condition.candidate and _edge_tie(condition.candidate, record, margin, favour)
        )
    ]
    if not records or null is None or not null.counts or not null.passed:
        judged = prediction
    else:
        judged = _judge_measured(prediction, records, max(0.0, float(null.threshold)))
    return [judged if item is condition else item for item in evidence]


def _judge_measured(prediction: Evidence, records: list[dict], placebo: float) -> Evidence:
    """The condition from the pair records against the placebo null's 95th percentile."""
    name = prediction.candidate
    kept = {record["confuser"]: record["on_top_of_confuser"] for record in records}
    alike = sorted(
        (confuser for confuser, entry in kept.items() if not entry["interval"][0] > placebo),
        key=lambda confuser: kept[confuser]["interval"][0],
    )  # the one that leaves it least first (the decision names the first as its alternative)
    least = min(kept, key=lambda confuser: kept[confuser]["interval"][0])
    details = {
        **{key: value for key, value in prediction.details.items() if key != "measured_by"},
        "prediction": prediction.to_json(),
        "on_top_of": kept,
        "placebo_95th": placebo,
        "confused_with": alike,
    }
    if not alike:
        reason = (
            f"{name} is identifiable here: on top of each of {', '.join(kept)} its probe still "
            f"removes at least {_percent(kept[least])} of the held-out error (least: on top of "
            f"{least}), more than placebo fields of its size ({100 * placebo:.1f} %, 95th "
            "percentile)"
        )
        return Evidence(
            prediction.kind, name, kept[least]["interval"][0], placebo, True, reason, details
        )
    worst = alike[0]
    capture = prediction.details.get("capture")
    details["capture"] = f"{capture}, or a higher resolution" if capture else "a higher resolution"
    others = [confuser for confuser in alike if confuser != worst]
    also = f" (and {', '.join(others)})" if others else ""
    reason = (
        f"{worst}{also} explains it as well here: on top of {worst}'s probe the {name} probe "
        f"removes {_percent(kept[worst])} of the held-out error, no more than placebo fields of "
        f"its size ({100 * placebo:.1f} %, 95th percentile)"
    )
    return Evidence(
        prediction.kind, name, kept[worst]["interval"][0], placebo, False, reason, details
    )


def with_edges_favour(evidence: list[Evidence]) -> list[Evidence]:
    """One candidate's evidence with its geometric specificity check told which blur the data's
    edge widths favour (details["edges_favour"], from its "edges" Evidence; removed where it
    has none), so the check is judged with it at every decision."""
    edges = next((item for item in evidence if item.kind == EDGES and item.counts), None)
    favour = edges.details.get("favours") if edges is not None else None
    updated = []
    for item in evidence:
        if item.kind == KIND and item.details.get("pairs"):
            details = {key: value for key, value in item.details.items() if key != "edges_favour"}
            if favour is not None:
                details["edges_favour"] = favour
            item = replace(item, details=details)
        updated.append(item)
    return updated

"""benchmarks/blind/cases.py: worlds, scenes, truths and the order of an interruptible run."""

from __future__ import annotations

from benchmarks.blind.cases import (
    CAMERA_EFFECTS,
    DEFAULT_PAIRS,
    DEFAULT_SCENES,
    LIGHT_TRANSPORT_EFFECTS,
    REAL_EFFECTS,
    BlindCase,
    build_cases,
    case_config,
    interleaved,
    scene_group,
)


def test_every_world_gets_its_effects_and_glossy_scenes_hold_specular():
    cases = build_cases(
        ["own", "mitsuba", "real"], list(DEFAULT_SCENES), None, [0], list(DEFAULT_PAIRS)
    )
    own = {case.withheld for case in cases if case.world == "own" and case.scene == "spot"}
    mitsuba = {case.withheld for case in cases if case.world == "mitsuba" and case.scene == "spot"}
    assert {(name,) for name in CAMERA_EFFECTS} < own and not any(
        set(LIGHT_TRANSPORT_EFFECTS) & set(withheld) for withheld in own
    )
    assert {(name,) for name in CAMERA_EFFECTS + LIGHT_TRANSPORT_EFFECTS} < mitsuba
    assert {case.withheld for case in cases if case.world == "real"} == {
        (name,) for name in REAL_EFFECTS
    } | {()}
    glossy = [case for case in cases if case.scene == "spot_glossy"]
    assert {case.world for case in glossy} == {"mitsuba"}
    assert {case.truth for case in glossy} == {("specular",), ("specular", "exposure")}
    assert scene_group("spot_glossy") == "spot"
    # The path tracer's cast shadows are present, not injected; a shadows case requires them.
    assert BlindCase("mitsuba", "spot", (), 0).present == ("shadows",)
    assert BlindCase("mitsuba", "spot", ("shadows",), 0).present == ()
    assert BlindCase("own", "spot", (), 0).present == ()


def test_an_interrupted_run_has_every_effect_once_after_the_clean_cases():
    cases = interleaved(
        build_cases(
            ["own", "mitsuba", "real"], list(DEFAULT_SCENES), None, [0], list(DEFAULT_PAIRS)
        )
    )
    clean = [case for case in cases if case.kind == "clean"]
    assert cases[: len(clean)] == clean
    first_round: dict[tuple, str] = {}
    for case in cases:
        first_round.setdefault((case.world, case.withheld), case.scene)
    # Within the first 45 cases every world has seen every one of its single effects.
    head = {(case.world, case.withheld) for case in cases[:45]}
    for world, effects in (
        ("own", CAMERA_EFFECTS),
        ("mitsuba", CAMERA_EFFECTS + LIGHT_TRANSPORT_EFFECTS),
        ("real", REAL_EFFECTS),
    ):
        assert {(world, (name,)) for name in effects} <= head, world
    # ... and on different scenes (the rotation spreads them).
    scenes = {first_round[("own", (name,))] for name in CAMERA_EFFECTS}
    assert len(scenes) >= 4


def test_case_config_sets_backend_scene_and_seed():
    base = {"scene": {"shape": {"procedural": "torus"}, "material": {"albedo": "checker"}}}
    config = case_config(base, BlindCase("mitsuba", "spot_glossy", ("exposure",), 7, ("specular",)))
    assert config["capture"]["backend"] == "mitsuba" and config["seed"] == 7
    assert config["scene"]["shape"]["procedural"] is None
    assert config["scene"]["shape"]["mesh_path"].endswith("spot_triangulated.obj")
    assert config["capture"]["effects"][0]["name"] == "specular"
    assert base["scene"]["shape"]["procedural"] == "torus"  # the base is not modified


def test_every_seed_draws_its_own_pairs():
    # A seed is one draw of every effect's strength; a pair scored on one seed only would
    # weigh that draw's pairs alone in a record over several (decision 0222).
    cases = build_cases(["own"], ["spot"], None, [0, 1, 2], list(DEFAULT_PAIRS))
    pairs = [case for case in cases if len(case.withheld) == 2]
    assert len(pairs) == 3 * len(DEFAULT_PAIRS)
    assert {case.seed for case in pairs} == {0, 1, 2}

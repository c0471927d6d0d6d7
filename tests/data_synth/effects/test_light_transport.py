"""data_synth.effects.light_transport: the specular effect's glossy variants (a GGX conductor
through metalness, Mitsuba's roughplastic) reach the Mitsuba options. The renders of those
materials are checked in tests/data_synth/test_mitsuba_backend.py."""

from __future__ import annotations

import pytest

from data_synth.effects.light_transport import make_light_transport_effect, mitsuba_options_for
from recon.config.run_config import EffectConfig
from recon.errors import ReconError


def test_specular_metalness_and_plastic_select_the_bsdf() -> None:
    conductor = mitsuba_options_for([("specular", {"roughness": 0.2, "metalness": 1.0})])
    assert conductor.material == "specular" and conductor.metalness == 1.0
    assert conductor.roughness == pytest.approx(0.2)
    plastic = mitsuba_options_for([("specular", {"roughness": 0.35, "plastic": True})])
    assert plastic.material == "roughplastic" and plastic.metalness == 0.0
    assert plastic.roughness == pytest.approx(0.35)
    # The default stays the principled dielectric.
    assert mitsuba_options_for(["specular"]).material == "specular"


def test_run_config_effect_carries_the_new_parameters() -> None:
    effect = EffectConfig(name="specular", parameters={"metalness": 0.5, "plastic": 0})
    options = mitsuba_options_for([effect])
    assert options.material == "specular" and options.metalness == 0.5


def test_plastic_conductor_and_out_of_range_metalness_are_rejected() -> None:
    with pytest.raises(ReconError, match="metalness"):
        make_light_transport_effect("specular", {"metalness": 1.5})
    with pytest.raises(ReconError, match="roughplastic.*dielectric"):
        mitsuba_options_for([("specular", {"metalness": 1.0, "plastic": True})])

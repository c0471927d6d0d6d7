"""World-side light-transport effects: specular, shadows, interreflection.

These are not image post-processes: each one is a configuration of the Mitsuba path-traced
render (data_synth/mitsuba_backend.py) of the same scene, so the world produces them the way
light does (a GGX lobe with Fresnel, ray-traced soft shadows from a light of finite size,
multi-bounce diffuse transport) while recon's model-side modules approximate them. Without any
light-transport effect the reference render is recon's own Renderer (the default backend).

    effects = [make_light_transport_effect("specular", {"roughness": 0.3})]
    options = mitsuba_options_for(effects, MitsubaOptions(spp=64, seed=7))
    images, alpha = render_mitsuba(mesh, cameras, world_lighting, options)

The effect list alone decides the light transport: without ``specular`` the material is
diffuse, without ``interreflection`` max_depth is 2 (direct light only); the base options
supply the rest (spp, seed, sampler, variant, extra lights).

Mitsuba always traces visibility, so any Mitsuba render also carries the cast shadows of the
scene's own lights and the environment's occlusion on non-convex shapes, whichever effect asked
for it; on convex shapes (sphere, blob) there is none, and a diffuse direct-only Mitsuba render
agrees with recon's (tests/data_synth/test_mitsuba_backend.py).

The effects share WorldEffect's parameter machinery (ParameterSpec ranges, errors naming the
effect and parameter, sample_strength for blind datasets) but are not applied to images:
``apply`` refuses, ``configure`` changes MitsubaOptions instead.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any, ClassVar

import torch

from data_synth.effects.base import AppliedEffect, Capture
from data_synth.effects.world_effect import (
    ParameterSpec,
    WorldEffect,
    round_float,
    sample_uniform,
)
from data_synth.mitsuba_backend import DiskSun, MitsubaOptions
from recon.camera import Cameras
from recon.errors import ReconError


class LightTransportEffect(WorldEffect):
    """Base class: validated parameters (WorldEffect) and the change made to MitsubaOptions.

    Subclasses set name, PARAMETERS and SAMPLE_RANGES (the [low, high] blind sampling draws
    each float or int parameter from; others keep their default) and implement configure().
    """

    stage = "light_transport"
    SAMPLE_RANGES: ClassVar[dict[str, tuple[float, float]]] = {}

    @classmethod
    def sample_strength(
        cls, generator: torch.Generator, cameras: Cameras | None = None
    ) -> dict[str, float | int | bool]:
        """Plausible random parameters for a blind benchmark, drawn from SAMPLE_RANGES."""
        drawn = cls.default_parameters()
        for key, (low, high) in cls.SAMPLE_RANGES.items():
            spec = cls.PARAMETERS[key]
            if spec.kind == "int":
                # Uniform over the integers low..high inclusive.
                drawn[key] = int(math.floor(sample_uniform(generator, low, high + 1)))
                drawn[key] = min(drawn[key], int(high))
            else:
                drawn[key] = round_float(sample_uniform(generator, low, high))
        return cls.validate(drawn)

    def configure(self, options: MitsubaOptions) -> MitsubaOptions:
        """The options with this effect switched on."""
        raise NotImplementedError

    def applied(self) -> AppliedEffect:
        """What was injected, for the truth file (every parameter, defaults included)."""
        return AppliedEffect(name=self.name, parameters=dict(self.parameters))

    def apply(self, capture: Capture, generator: torch.Generator) -> AppliedEffect:
        raise ReconError(
            f"effect {self.name}: a light-transport effect is rendered, not applied to images; "
            "pass it to data_synth.effects.light_transport.mitsuba_options_for and render with "
            "data_synth.mitsuba_backend.render_mitsuba"
        )


class Specular(LightTransportEffect):
    """A GGX microfacet specular lobe with Fresnel over the diffuse albedo (principled BSDF).

    roughness: perceptual roughness r (GGX alpha = r^2); specular_level: principled's level,
    normal-incidence reflectance 0.08 * level (0.5 -> 4%, a typical dielectric); metalness:
    principled's metallic (1: a GGX conductor whose F0 is the albedo, no diffuse); plastic:
    Mitsuba's roughplastic instead (a GGX dielectric coating with exact Fresnel over a diffuse
    base; metalness must be 0).
    """

    name = "specular"
    PARAMETERS = {
        "roughness": ParameterSpec(0.25, 0.01, 1.0, "perceptual roughness (GGX alpha = r^2)"),
        "specular_level": ParameterSpec(0.5, 0.0, 1.0, "Fresnel F0 = 0.08 * level"),
        "metalness": ParameterSpec(0.0, 0.0, 1.0, "principled metallic (1 = GGX conductor)"),
        "plastic": ParameterSpec(False, 0, 1, "Mitsuba's roughplastic BSDF", kind="bool"),
    }
    SAMPLE_RANGES = {"roughness": (0.15, 0.4), "specular_level": (0.3, 0.8)}

    def configure(self, options: MitsubaOptions) -> MitsubaOptions:
        return replace(
            options,
            material="roughplastic" if self.parameters["plastic"] else "specular",
            roughness=float(self.parameters["roughness"]),
            specular_level=float(self.parameters["specular_level"]),
            metalness=float(self.parameters["metalness"]),
        )


class Shadows(LightTransportEffect):
    """Ray-traced soft shadows from a sun of finite angular size that gives most direct light.

    The sun is a uniform disk in the environment map (so it is never in a camera's frame and
    never part of the alpha mask), at elevation_deg above the horizon (world +y up) and
    azimuth_deg about +y measured from +z toward +x, giving ``irradiance`` to a surface facing
    it; its angular diameter sets the penumbra width. With replace_directional (default) the
    scene's own directional lights are left out, so this sun is the dominant direct light; the
    environment, point and area lights stay.
    """

    name = "shadows"
    PARAMETERS = {
        "angular_diameter_deg": ParameterSpec(8.0, 0.5, 45.0, "apparent diameter of the sun"),
        "elevation_deg": ParameterSpec(45.0, 5.0, 89.0, "sun height above the horizon"),
        "azimuth_deg": ParameterSpec(30.0, -180.0, 180.0, "about +y, from +z toward +x"),
        "irradiance": ParameterSpec(2.5, 0.1, 20.0, "irradiance facing the sun"),
        "replace_directional": ParameterSpec(
            True, 0, 1, "leave out the scene's directional lights", kind="bool"
        ),
    }
    SAMPLE_RANGES = {
        "angular_diameter_deg": (3.0, 15.0),
        "elevation_deg": (25.0, 70.0),
        "azimuth_deg": (-180.0, 180.0),
        "irradiance": (1.5, 3.5),
    }

    def direction_to_light(self) -> tuple[float, float, float]:
        """World unit vector toward the sun's centre."""
        elevation = math.radians(self.parameters["elevation_deg"])
        azimuth = math.radians(self.parameters["azimuth_deg"])
        return (
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
            math.cos(elevation) * math.cos(azimuth),
        )

    def configure(self, options: MitsubaOptions) -> MitsubaOptions:
        irradiance = float(self.parameters["irradiance"])
        sun = DiskSun(
            direction_to_light=self.direction_to_light(),
            angular_diameter_deg=float(self.parameters["angular_diameter_deg"]),
            irradiance=(irradiance, irradiance, irradiance),
        )
        return replace(
            options,
            suns=(*options.suns, sun),
            include_directional=options.include_directional
            and not self.parameters["replace_directional"],
        )

    def applied(self) -> AppliedEffect:
        parameters = dict(self.parameters)
        parameters["direction_to_light"] = [
            round_float(value) for value in self.direction_to_light()
        ]
        return AppliedEffect(name=self.name, parameters=parameters)


class Interreflection(LightTransportEffect):
    """Diffuse multi-bounce light transport: paths of up to max_depth segments (>= 3).

    albedo_scale multiplies the albedo (clipped to 1) for stronger bounce light; it changes the
    surface's true albedo, so blind sampling keeps it at 1.
    """

    name = "interreflection"
    PARAMETERS = {
        "max_depth": ParameterSpec(6, 3, 16, "longest path in segments (2 = direct)", kind="int"),
        "albedo_scale": ParameterSpec(1.0, 1.0, 1.5, "albedo multiplier (changes the truth)"),
    }
    SAMPLE_RANGES = {"max_depth": (4, 8)}

    def configure(self, options: MitsubaOptions) -> MitsubaOptions:
        return replace(
            options,
            max_depth=int(self.parameters["max_depth"]),
            albedo_scale=options.albedo_scale * float(self.parameters["albedo_scale"]),
        )


LIGHT_TRANSPORT_EFFECTS: dict[str, type[LightTransportEffect]] = {
    effect.name: effect for effect in (Specular, Shadows, Interreflection)
}


def make_light_transport_effect(
    name: str, parameters: Mapping[str, object] | None = None
) -> LightTransportEffect:
    """Build the effect ``name`` with ``parameters`` (defaults for the rest).

    Raises ReconError for an unknown name (suggesting the closest) or a bad parameter.
    """
    if name not in LIGHT_TRANSPORT_EFFECTS:
        suggestion = difflib.get_close_matches(str(name), list(LIGHT_TRANSPORT_EFFECTS), n=1)
        hint = f"; did you mean '{suggestion[0]}'?" if suggestion else ""
        raise ReconError(
            f"unknown light-transport effect '{name}'{hint} "
            f"(known: {', '.join(LIGHT_TRANSPORT_EFFECTS)})"
        )
    return LIGHT_TRANSPORT_EFFECTS[name](parameters)


def _build(effect: Any, material: Any) -> LightTransportEffect:
    """An effect instance from an instance, a name, a (name, parameters) pair or an object with
    .name and .parameters (a run config's EffectConfig)."""
    if isinstance(effect, LightTransportEffect):
        return effect
    if isinstance(effect, str):
        name, parameters = effect, {}
    elif isinstance(effect, tuple) and len(effect) == 2:
        name, parameters = effect
    elif hasattr(effect, "name") and hasattr(effect, "parameters"):
        name, parameters = effect.name, effect.parameters
    else:
        raise ReconError(
            "mitsuba_options_for: expected light-transport effects (specular, shadows, "
            f"interreflection), their names or (name, parameters) pairs, got {effect!r}"
        )
    parameters = dict(parameters or {})
    if name == "specular" and material is not None:
        # The scene's material gives the specular lobe unless the effect sets it itself.
        for key in ("roughness", "specular_level", "metalness"):
            if key not in parameters and hasattr(material, key):
                parameters[key] = getattr(material, key)
    return make_light_transport_effect(name, parameters)


def mitsuba_options_for(
    effects: Sequence[Any], base: MitsubaOptions | None = None, material: Any = None
) -> MitsubaOptions:
    """Combine light-transport effects into one Mitsuba configuration.

    effects: effect instances, names, (name, parameters) pairs or run-config EffectConfig
        objects; each name at most once.
    base: spp, seed, sampler, variant and extra lights; its material and max_depth are replaced
        by what the effects ask for (diffuse and 2 = direct only, unless specular /
        interreflection is in the list).
    material: the scene's material config (roughness, specular_level): the specular lobe where
        the specular effect does not set them.
    """
    options = MitsubaOptions() if base is None else base
    options = replace(options, material="diffuse", max_depth=2, integrator="path")
    built = [_build(effect, material) for effect in effects]
    names = [effect.name for effect in built]
    repeated = sorted({name for name in names if names.count(name) > 1})
    if repeated:
        raise ReconError(
            f"mitsuba_options_for: each effect may be given once; repeated: {repeated}"
        )
    for effect in built:
        options = effect.configure(options)
    options.validate()
    return options


def uses_mitsuba(effect_names: Sequence[str]) -> bool:
    """True when any named effect is a light-transport effect (rendered with Mitsuba)."""
    return any(name in LIGHT_TRANSPORT_EFFECTS for name in effect_names)

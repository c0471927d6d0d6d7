"""The run config schema: what a YAML config may say. Every section is strict (unknown keys are
errors with a suggestion) and validated where it is loaded.

Every field is declared with ``setting(default, doc)``: its doc is the user-facing description
that docs/config.md and ``recon config keys`` are generated from (recon/config/reference.py;
a test fails when a field has none or the file is stale). Over 500 lines because it is the whole
schema in one place; the per-section split is a later step of the layout (docs/decisions).

Sections consumed by data_synth (scene, capture) are declared here so that a config is checked
whole before any stage runs; data_synth imports them (recon never imports data_synth).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from recon.config.checks import ConfigFieldError, check_range
from recon.config.schema import setting

# The smallest view recon can evaluate: SSIM's 11-tap window needs more than 5 pixels a side;
# 16 leaves the window room to slide.
MINIMUM_VIEW_SIZE = 16


@dataclass
class ShapeConfig:
    """The reference geometry: a built-in procedural shape or a mesh file (OBJ/PLY/GLB/OFF)."""

    procedural: str | None = setting(
        "torus",
        "Built-in shape to use: sphere, torus (genus 1), rounded_box, dumbbell, double_torus (genus 2) or blob; null when mesh_path is given.",
    )
    mesh_path: str | None = setting(
        None,
        "Mesh file of the reference (OBJ/PLY/GLB/OFF, with its texture); null for a procedural shape.",
    )
    resolution: int = setting(
        64, "Tessellation resolution of the procedural shape (segments around its main circle)."
    )
    texture_path: str | None = setting(
        None, "Texture image for the mesh file, when the file does not name its own."
    )

    def __post_init__(self) -> None:
        if (self.procedural is None) == (self.mesh_path is None):
            raise ConfigFieldError("procedural", "give exactly one of 'procedural' and 'mesh_path'")
        if self.texture_path is not None and self.mesh_path is None:
            raise ConfigFieldError(
                "texture_path",
                f"applies only to a mesh_path shape; the procedural shape {self.procedural!r} "
                f"would ignore {self.texture_path!r} (use material.albedo for its texture)",
            )
        check_range(self.resolution, "resolution", low=8, high=512)


@dataclass
class MaterialConfig:
    """Albedo: a procedural texture (checker, stripes, noise, patches), the mesh file's own
    texture ('file'), or a procedural vertex colour field ('vertex_noise')."""

    albedo: Literal["checker", "stripes", "noise", "patches", "file", "vertex_noise"] = setting(
        "checker",
        "Where the albedo comes from: a procedural pattern, the mesh file's own texture ('file') or a procedural vertex colour field ('vertex_noise').",
    )
    texture_size: int = setting(256, "Side in texels of the procedural albedo texture.")
    seed: int = setting(0, "Seed of the procedural albedo pattern (independent of the run's seed).")
    roughness: float = setting(
        0.3,
        "Specular roughness (GGX alpha); used only where light transport renders the 'specular' effect.",
    )
    specular_level: float = setting(
        0.5,
        "Specular reflectance level; used only where light transport renders the 'specular' effect.",
    )
    roughness_texture: Literal["none", "checker", "stripes", "noise", "patches"] = setting(
        "none",
        "A spatially varying roughness: this procedural pattern over the texture's UVs, scaled into roughness_range (seeded with seed + 1); replaces roughness where the 'specular' effect is rendered (principled BSDF), and the ground truth's reference mesh carries it (map_Pr). Needs a textured mesh.",
    )
    roughness_range: list[float] = setting(
        factory=lambda: [0.1, 0.4],
        doc="Lowest and highest roughness of roughness_texture's pattern.",
    )

    def __post_init__(self) -> None:
        check_range(self.texture_size, "texture_size", low=4, high=8192)
        check_range(self.roughness, "roughness", low=0.01, high=1.0)
        check_range(self.specular_level, "specular_level", low=0.0, high=1.0)
        if len(self.roughness_range) != 2 or not (
            0.01 <= self.roughness_range[0] <= self.roughness_range[1] <= 1.0
        ):
            raise ConfigFieldError(
                "roughness_range",
                f"expected [low, high] with 0.01 <= low <= high <= 1, got {self.roughness_range}",
            )
        if self.roughness_texture != "none" and self.albedo == "vertex_noise":
            raise ConfigFieldError(
                "roughness_texture",
                f"{self.roughness_texture!r} is a texture over UVs, but albedo 'vertex_noise' "
                "gives the mesh vertex colours and no texture; use a textured albedo",
            )


@dataclass
class SunConfig:
    """A directional light: direction toward the light (world), irradiance per channel."""

    direction: list[float] = setting(
        factory=lambda: [0.4, 0.8, 0.5],
        doc="Direction toward the light, world frame (normalised on use).",
    )
    irradiance: list[float] = setting(
        factory=lambda: [2.0, 2.0, 2.0], doc="Irradiance per channel (R, G, B), linear."
    )

    def __post_init__(self) -> None:
        if len(self.direction) != 3:
            raise ConfigFieldError("direction", f"expected 3 values, got {len(self.direction)}")
        if len(self.irradiance) != 3:
            raise ConfigFieldError("irradiance", f"expected 3 values, got {len(self.irradiance)}")
        check_range(self.irradiance, "irradiance", low=0.0)


def _check_vector(values: list[float], key: str, length: int = 3) -> None:
    if len(values) != length:
        raise ConfigFieldError(key, f"expected {length} values, got {len(values)}")


@dataclass
class PointLightConfig:
    """An isotropic bulb: position (world), intensity per channel."""

    position: list[float] = setting(
        factory=lambda: [1.5, 2.0, 1.5], doc="Position of the bulb, world frame."
    )
    intensity: list[float] = setting(
        factory=lambda: [5.0, 5.0, 5.0], doc="Radiant intensity per channel (R, G, B), linear."
    )

    def __post_init__(self) -> None:
        _check_vector(self.position, "position")
        _check_vector(self.intensity, "intensity")
        check_range(self.intensity, "intensity", low=0.0)


@dataclass
class AreaLightConfig:
    """A one-sided rectangular emitter facing the origin from center (soft shadows in the path
    tracer; recon's renderer treats it as a point light with a cosine lobe at its centre)."""

    center: list[float] = setting(
        factory=lambda: [1.0, 2.5, 1.0],
        doc="Centre of the rectangle, world frame; it faces the origin.",
    )
    size: list[float] = setting(
        factory=lambda: [1.0, 1.0], doc="Width and height of the rectangle, world units."
    )
    radiance: list[float] = setting(
        factory=lambda: [4.0, 4.0, 4.0], doc="Emitted radiance per channel (R, G, B), linear."
    )

    def __post_init__(self) -> None:
        _check_vector(self.center, "center")
        _check_vector(self.size, "size", 2)
        check_range(self.size, "size", low=0.0, low_inclusive=False)
        _check_vector(self.radiance, "radiance")
        check_range(self.radiance, "radiance", low=0.0)


@dataclass
class EnvironmentConfig:
    """An environment map: none, an HDR equirectangular EXR, a procedural sky (with a sun as a
    directional light) or a procedural studio with softboxes."""

    kind: Literal["none", "exr", "sky", "studio"] = setting(
        "none",
        "Environment map: none, an HDR equirectangular EXR file, a procedural sky with a sun, or a procedural studio with softboxes.",
    )
    path: str | None = setting(None, "The EXR file when kind is 'exr'.")
    strength: float = setting(1.0, "Multiplier of the environment's radiance.")
    sun_elevation_deg: float = setting(
        45.0, "Sky only: the sun's elevation above the horizon, degrees."
    )
    sun_azimuth_deg: float = setting(30.0, "Sky only: the sun's azimuth, degrees.")
    sun_irradiance: float = setting(
        3.0, "Sky only: the sun's irradiance (added as a directional light)."
    )
    resolution: list[int] = setting(
        factory=lambda: [64, 128], doc="Procedural map size [height, width] in texels."
    )

    def __post_init__(self) -> None:
        if self.kind == "exr" and not self.path:
            raise ConfigFieldError("path", "kind 'exr' needs the path of an EXR file")
        check_range(self.strength, "strength", low=0.0)
        check_range(self.sun_elevation_deg, "sun_elevation_deg", low=-90.0, high=90.0)
        check_range(self.sun_irradiance, "sun_irradiance", low=0.0)
        _check_vector(self.resolution, "resolution", 2)
        check_range(self.resolution, "resolution", low=4, high=8192)


@dataclass
class LightingConfig:
    """SH environment (ambient radiance per channel + a sky/ground gradient), suns, point and
    area lights, and an optional environment map (projected to SH for recon's renderer)."""

    ambient: list[float] = setting(
        factory=lambda: [0.6, 0.6, 0.6], doc="SH ambient radiance per channel (R, G, B), linear."
    )
    sky_gradient: float = setting(
        0.2, "Sky/ground gradient of the ambient term: positive brightens light from above."
    )
    suns: list[SunConfig] = setting(factory=lambda: [SunConfig()], doc="Directional lights.")
    points: list[PointLightConfig] = setting(factory=list, doc="Point lights.")
    areas: list[AreaLightConfig] = setting(factory=list, doc="Rectangular area lights.")
    environment: EnvironmentConfig = setting(
        factory=EnvironmentConfig,
        doc="Optional environment map (projected to SH for recon's renderer, used whole by the path tracer).",
    )

    def __post_init__(self) -> None:
        _check_vector(self.ambient, "ambient")
        check_range(self.ambient, "ambient", low=0.0)
        check_range(self.sky_gradient, "sky_gradient", low=-1.0, high=1.0)


@dataclass
class SceneConfig:
    """The synthetic scene data_synth renders the captures of: geometry, material and light."""

    shape: ShapeConfig = setting(factory=ShapeConfig, doc="The reference geometry.")
    material: MaterialConfig = setting(
        factory=MaterialConfig, doc="The reference albedo and specular material."
    )
    lighting: LightingConfig = setting(factory=LightingConfig, doc="The capture light.")


@dataclass
class CameraRigConfig:
    """Where the captures are taken from."""

    rig: Literal["fibonacci", "orbit", "random", "hemisphere"] = setting(
        "fibonacci", "How camera positions are placed on the sphere around the object."
    )
    distance: float = setting(3.0, "Distance of every camera from the origin, world units.")
    fov_deg: float = setting(40.0, "Vertical field of view, degrees.")
    resolution: list[int] = setting(
        factory=lambda: [128, 128], doc="Image size [height, width] in pixels."
    )
    jitter_deg: float = setting(
        0.0, "Random perturbation of each camera's viewing direction, degrees."
    )
    near: float = setting(0.1, "Near clipping distance (0 < near < far).")
    far: float = setting(100.0, "Far clipping distance.")

    def __post_init__(self) -> None:
        check_range(self.distance, "distance", low=0.0, low_inclusive=False)
        check_range(self.fov_deg, "fov_deg", low=1.0, high=170.0)
        if len(self.resolution) != 2:
            raise ConfigFieldError("resolution", f"expected [height, width], got {self.resolution}")
        # Evaluation's SSIM uses an 11-tap window: smaller views could be fitted but never scored.
        check_range(self.resolution, "resolution", low=MINIMUM_VIEW_SIZE, high=8192)
        check_range(self.jitter_deg, "jitter_deg", low=0.0, high=90.0)
        if not 0 < self.near < self.far:
            raise ConfigFieldError(
                "near", f"expected 0 < near < far, got near={self.near}, far={self.far}"
            )


EFFECT_NAMES = (
    "exposure",
    "white_balance",
    "vignetting",
    "response_curve",
    "lens_distortion",
    "defocus_blur",
    "motion_blur",
    "pose_error",
    "noise",
    "specular",
    "shadows",
    "interreflection",
)


@dataclass
class EffectConfig:
    """One injected real-world effect and its strength parameters (names, defaults and ranges
    per effect: docs/effect_parameters.md). Per-view values are drawn from these with the run's
    seed."""

    name: Literal[EFFECT_NAMES] = setting(
        "exposure", "Which real-world effect to inject (the effect catalogue; see `recon effects`)."
    )  # type: ignore[valid-type]
    parameters: dict[str, float] = setting(
        factory=dict,
        doc="The effect's strength parameters by name (per effect: docs/effect_parameters.md); left out, a parameter takes its default. Per-view values are drawn from these with the run's seed.",
    )


@dataclass
class RelightConfig:
    """An extra split of the test cameras rendered under another light (relight test)."""

    views: int = setting(
        0, "Number of test cameras also rendered under the relight light (0: no relight split)."
    )
    lighting: LightingConfig = setting(
        factory=LightingConfig,
        doc="The second light of the relight split (written to dataset/lighting_relight.json).",
    )

    def __post_init__(self) -> None:
        check_range(self.views, "views", low=0, high=10000)


@dataclass
class FlatFieldConfig:
    """Flat-field frames: the capture camera imaging a uniformly lit white card that fills the
    frame (the usual vignetting calibration). They pass through the camera, optics, sensor and
    response effects like the views; effects that leave a uniform field uniform (pose error,
    lens distortion, blur) and light transport do not touch them. Written as the dataset's
    flat_field split; the fit never reads them, the diagnosis measures the full-frame falloff on
    them (the object's own pixels reach only part of the way to the corners)."""

    views: int = setting(0, "Number of flat-field frames (0: none).")
    radiance: float = setting(
        0.5,
        "Linear radiance of the card before exposure: mid-grey keeps the corners and a bright exposure away from both ends of the 8-bit range.",
    )

    def __post_init__(self) -> None:
        check_range(self.views, "views", low=0, high=1000)
        check_range(self.radiance, "radiance", low=1e-3, high=1.0)


@dataclass
class LineTargetConfig:
    """Line-target frames: the capture camera imaging a card of straight black and white stripes
    that fills the frame, at a small random tilt (the plumb-line calibration of a lens). A
    pinhole camera images straight lines as straight lines, whatever the card's pose; a lens
    distortion bends them, most near the corners, which an object in the middle of the frame
    never reaches. The frames pass through the camera, optics, sensor and response effects like
    the views (a pose error and light transport do not apply). Written as the dataset's
    line_target split; the fit never reads them, the diagnosis measures the lines' bend."""

    views: int = setting(
        0, "Number of line-target frames (0: none); they alternate horizontal and vertical stripes."
    )
    period_pixels: float = setting(
        12.0,
        "Stripe period (one black and one white stripe) at the image centre, in output pixels: wide enough that a blur of a few pixels leaves each edge's crossing, narrow enough for several lines per frame.",
    )
    radiance: float = setting(
        0.5,
        "Linear radiance of the white stripes before exposure (the black ones: dark_share of it).",
    )
    dark_share: float = setting(
        0.1,
        "Radiance of the black stripes as a share of the white ones (the card's printed contrast, known from its data sheet): the diagnosis reads the camera's response curve off the two levels.",
    )
    contrast_tolerance: float = setting(
        0.02,
        "How well dark_share is known, as a share of it (the card's data sheet: a printed card's contrast is known to a few per cent; 0 for a card whose contrast is exact, as data_synth renders it). It moves the response's exponent over the two levels by up to -ln(1 - contrast_tolerance) / ln(1 / dark_share) (0.0088 for 0.02 at 0.1), the least distance from 1 the diagnosis requires before the levels name a response curve.",
    )
    tilt_deg: float = setting(
        20.0, "Largest tilt of the card away from facing the camera, per axis, in degrees."
    )
    supersampling: int = setting(
        4,
        "Samples per output pixel side: box-filters the stripes' edges and integrates a lens distortion (as capture.distortion_supersampling does for the views).",
    )

    def __post_init__(self) -> None:
        check_range(self.views, "views", low=0, high=1000)
        check_range(self.period_pixels, "period_pixels", low=4.0)
        check_range(self.radiance, "radiance", low=1e-3, high=1.0)
        check_range(self.tilt_deg, "tilt_deg", low=0.0, high=60.0)
        check_range(self.dark_share, "dark_share", low=1e-3, high=0.5)
        check_range(self.contrast_tolerance, "contrast_tolerance", low=0.0, high=0.5)
        check_range(self.supersampling, "supersampling", low=1, high=16)


@dataclass
class OwnSpecularConfig:
    """The 'specular' effect rendered by backend 'own': recon's split-sum GGX shading
    (recon.render.pbr) under the world's environment (map and SH, resampled to one lat-long
    map) and directional lights, with no shadows or interreflection; the Mitsuba backend path
    traces the same material."""

    environment_size: list[int] = setting(
        factory=lambda: [32, 64],
        doc="Lat-long size [h, w] the world's environment is resampled to before pre-filtering (the brute-force pre-filter's cost grows with the square of its texel count).",
    )
    prefilter_levels: int = setting(
        8, "Pre-filtered roughness levels besides the map itself (roughness linspace(0, 1, n + 1))."
    )

    def __post_init__(self) -> None:
        if len(self.environment_size) != 2:
            raise ConfigFieldError(
                "environment_size", f"expected [h, w], got {self.environment_size}"
            )
        check_range(self.environment_size, "environment_size", low=4, high=256)
        check_range(self.prefilter_levels, "prefilter_levels", low=1, high=32)


@dataclass
class CaptureConfig:
    """Views per split; the train/val/test cameras are drawn from one rig, disjoint."""

    cameras: CameraRigConfig = setting(
        factory=CameraRigConfig, doc="The camera rig all splits are drawn from."
    )
    train_views: int = setting(16, "Number of training views.")
    val_views: int = setting(2, "Number of validation views.")
    test_views: int = setting(4, "Number of held-out test views.")
    relight: RelightConfig = setting(
        factory=RelightConfig, doc="Optional relight split of the test cameras under another light."
    )
    flat_field: FlatFieldConfig = setting(
        factory=FlatFieldConfig, doc="Optional flat-field frames (vignetting calibration)."
    )
    line_target: LineTargetConfig = setting(
        factory=LineTargetConfig,
        doc="Optional line-target frames (plumb-line lens-distortion calibration).",
    )
    background: list[float] = setting(
        factory=lambda: [0.0, 0.0, 0.0],
        doc="Background colour (R, G, B), linear, composited behind the object.",
    )
    effects: list[EffectConfig] = setting(
        factory=list,
        doc="Real-world effects to inject, each at most once, applied in physical order.",
    )
    backend: Literal["auto", "own", "mitsuba"] = setting(
        "auto",
        "Renderer of the captures: own (recon's rasterizer; the specular effect with its split-sum shading, no shadows or interreflection), mitsuba (the path tracer), or auto (mitsuba only when a light-transport effect, specular, shadows or interreflection, is requested).",
    )
    mitsuba_spp: int = setting(64, "Samples per pixel of the Mitsuba path tracer.")
    distortion_supersampling: int = setting(
        4,
        "With a lens_distortion effect, views are rendered at this many times the resolution "
        "per side, bent there, and each pixel averages its samples: a lens bends the optical "
        "image before the sensor integrates it, while bending the finished image resamples it "
        "(bilinearly: a blur of up to 0.5 px). 1: bend the finished image. Mitsuba's samples "
        "per pixel are divided by its square (at least 1), so the samples per output pixel stay.",
    )
    own_specular: OwnSpecularConfig = setting(
        factory=OwnSpecularConfig,
        doc="How backend 'own' renders the 'specular' effect (recon's split-sum shading).",
    )
    write_exr: bool = setting(True, "Also write each view as linear EXR beside the PNG.")
    write_depth_normals: bool = setting(False, "Also write depth and normal EXRs per view.")
    contact_sheet: bool = setting(True, "Write captures_contact_sheet.png into the run folder.")

    def __post_init__(self) -> None:
        check_range(self.train_views, "train_views", low=1, high=10000)
        check_range(self.val_views, "val_views", low=0, high=10000)
        check_range(self.test_views, "test_views", low=0, high=10000)
        check_range(self.mitsuba_spp, "mitsuba_spp", low=1, high=65536)
        check_range(self.distortion_supersampling, "distortion_supersampling", low=1, high=16)
        _check_vector(self.background, "background")
        names = [effect.name for effect in self.effects]
        # recon's own renderer shades 'specular' with its split-sum model; it traces no rays.
        light_transport = [name for name in names if name in ("shadows", "interreflection")]
        if self.backend == "own" and light_transport:
            raise ConfigFieldError(
                "backend",
                f"'own' cannot render light-transport effects {light_transport}; use 'auto' or "
                "'mitsuba'",
            )
        duplicates = sorted({name for name in names if names.count(name) > 1})
        if duplicates:
            raise ConfigFieldError("effects", f"each effect at most once, got {duplicates} twice")


@dataclass
class GeometryStageConfig:
    """Stage 1: vertex positions (Large Steps), per-vertex albedo and lighting, with remeshing."""

    steps: int = setting(400, "Optimisation steps of the geometry stage.")
    views_per_step: int = setting(4, "Training views rendered per step (random batch).")
    resolutions: list[int] = setting(
        factory=lambda: [64, 128, 256],
        doc="Coarse-to-fine rendering resolutions (longer side, capped at the data's), switched at equal fractions of the steps.",
    )
    learning_rate: float = setting(
        0.02, "Step size of the vertex positions (Large Steps latent, uniform Adam)."
    )
    albedo_learning_rate: float = setting(0.03, "Step size of the per-vertex albedo.")
    light_learning_rate: float = setting(0.02, "Step size of the SH light and the sun.")
    large_steps_lambda: float = setting(
        20.0, "Smoothing weight lambda of the Large Steps parameterisation u = (I + lambda L) v."
    )
    remesh_every: int = setting(50, "Steps between isotropic remeshings (0: never).")
    remesh_until: float = setting(0.8, "Share of the steps after which remeshing stops.")
    edge_length_start: float = setting(
        0.04,
        "Remesher target edge length at the start, as a fraction of the initial shape's bounding-box diagonal.",
    )
    edge_length_end: float = setting(
        0.012,
        "Remesher target edge length at the end of the remeshing period (shrinks geometrically from the start value).",
    )
    mask_weight: float = setting(
        1.0, "Weight of the L1 loss of the antialiased coverage against the masks."
    )
    image_loss: Literal["l1", "log_srgb_l1"] = setting(
        "l1", "Image loss: L1 in linear radiance or L1 of log-sRGB."
    )
    directional_light: bool = setting(True, "Fit a sun (directional light) beside the SH light.")

    def __post_init__(self) -> None:
        check_range(self.steps, "steps", low=0)
        check_range(self.views_per_step, "views_per_step", low=1)
        if not self.resolutions:
            raise ConfigFieldError("resolutions", "expected at least one resolution, got []")
        check_range(self.resolutions, "resolutions", low=8, high=8192)
        for key in ("learning_rate", "albedo_learning_rate", "light_learning_rate"):
            check_range(getattr(self, key), key, low=0.0)
        check_range(self.large_steps_lambda, "large_steps_lambda", low=0.0)
        check_range(self.remesh_every, "remesh_every", low=0)
        check_range(self.remesh_until, "remesh_until", low=0.0, high=1.0)
        check_range(self.edge_length_start, "edge_length_start", low=0.0, low_inclusive=False)
        check_range(self.edge_length_end, "edge_length_end", low=0.0, low_inclusive=False)
        check_range(self.mask_weight, "mask_weight", low=0.0)


@dataclass
class SimplifyConfig:
    """Simplification of the geometry stage's mesh before it is unwrapped and textured."""

    target_faces: int = setting(
        20000, "Face count the fitted mesh is simplified to before unwrapping."
    )

    def __post_init__(self) -> None:
        check_range(self.target_faces, "target_faces", low=4)


@dataclass
class TextureStageConfig:
    """Stage 2: UV texture (trilinear), lighting and vertex positions on a fixed topology."""

    steps: int = setting(200, "Optimisation steps of the texture stage.")
    views_per_step: int = setting(4, "Training views rendered per step (random batch).")
    texture_size: int = setting(512, "Side in texels of the unwrapped texture.")
    learning_rate: float = setting(0.01, "Step size of the vertex positions on the fixed topology.")
    texture_learning_rate: float = setting(0.03, "Step size of the texture.")
    light_learning_rate: float = setting(0.01, "Step size of the SH light and the sun.")
    large_steps_lambda: float = setting(
        20.0, "Smoothing weight lambda of the Large Steps parameterisation of the positions."
    )
    smoothness_weight: float = setting(0.01, "Weight of the total-variation term on the texture.")
    mask_weight: float = setting(
        1.0, "Weight of the L1 loss of the antialiased coverage against the masks."
    )
    image_loss: Literal["l1", "log_srgb_l1"] = setting(
        "l1",
        "As fit.geometry.image_loss: log_srgb_l1 weighs dark regions as the sRGB metrics do.",
    )

    def __post_init__(self) -> None:
        check_range(self.steps, "steps", low=0)
        check_range(self.views_per_step, "views_per_step", low=1)
        check_range(self.texture_size, "texture_size", low=8, high=8192)
        for key in ("learning_rate", "texture_learning_rate", "light_learning_rate"):
            check_range(getattr(self, key), key, low=0.0)
        check_range(self.smoothness_weight, "smoothness_weight", low=0.0)


@dataclass
class PbrFitConfig:
    """The `pbr` material's settings (used only with fit.material: pbr): textures base colour +
    roughness + metalness and an optimised lat-long environment light (recon.render.pbr)."""

    environment_size: list[int] = setting(
        factory=lambda: [32, 64],
        doc="Environment map [height, width] the fit optimises (lat-long, row 0 looks up); 32 x 64 since docs/decisions/0190-pbr-benchmark-recipe.md.",
    )
    prefilter_levels: int = setting(
        6, "Pre-filtered roughness levels besides the map itself (roughness linspace(0, 1, n + 1))."
    )
    initial_roughness: float = setting(0.5, "Starting roughness of every texel.")
    initial_metalness: float = setting(0.0, "Starting metalness of every texel.")
    specular_level: float = setting(
        0.5, "Dielectric reflectance at normal incidence is 0.08 x this (0.5 gives the usual 0.04)."
    )
    diffuse_weighting: Literal["none", "specular_albedo"] = setting(
        "none",
        "none: diffuse = base (1 - metalness) / pi x irradiance (Karis; Mitsuba's principled); specular_albedo: times 1 - the specular lobe's albedo (never exceeds a white furnace).",
    )
    material_learning_rate: float = setting(
        0.02, "Adam learning rate of the roughness/metalness texture."
    )
    material_warmup_steps: int = setting(
        0,
        "Texture steps during which roughness and metalness stay at their initial values while the environment and base colour settle (with a low initial_roughness the light is fitted sharp first).",
    )
    material_texture_size: int = setting(
        0,
        "Height of the grid the roughness/metalness texture is optimised on (bilinearly upsampled to the base colour's texels): 0 = the base colour's own size, 1 = one uniform material.",
    )
    environment_learning_rate: float = setting(
        0.03,
        "Adam learning rate of the environment texels (of their log with parameterization log).",
    )
    environment_seed: Literal["light", "highlights"] = setting(
        "highlights",
        "Starting environment: light = the geometry stage's SH light (+ sun lobe); highlights = that light plus the training views' specular excess back-projected along mirror-reflection directions (recon/render/environment_seed.py: the light starts sharp; docs/decisions/0190-pbr-benchmark-recipe.md).",
    )
    environment_seed_prior_weight: float = setting(
        0.01,
        "highlights seed: pull of each texel toward the geometry stage's light, in units of one voting pixel of specular weight 1 (a dielectric pixel weighs about 0.04^2).",
    )
    environment_parameterization: Literal["linear", "log"] = setting(
        "linear",
        "log: the fit optimises the log radiance of each environment texel (relative steps: bright lights are reached as fast as dim ones); linear: the radiance itself.",
    )
    material_smoothness_weight: float = setting(
        0.01, "Total variation of the roughness/metalness texture (keeps unseen texels quiet)."
    )
    normal_map: bool = setting(
        False,
        "Also fit a tangent-space normal map on the base colour's UVs (tangents from the UVs); exported as the MTL's norm / map_Bump and the GLB's normalTexture.",
    )
    normal_map_smoothness_weight: float = setting(
        0.01, "Total variation of the normal map's tilts (used with normal_map)."
    )
    environment_smoothness_weight: float = setting(
        0.01, "Total variation of the environment map (neighbouring texels alike)."
    )
    environment_whiteness_weight: float = setting(
        0.01,
        "Pull of each environment texel toward grey (its channel mean): light colour and base colour are otherwise interchangeable.",
    )
    lobe_steps: int = setting(
        0,
        "Texture steps after texture.steps that shade the specular lobe per pixel by visible-normal samples (recon/render/lobe_sampling.py) instead of the split sum, which cannot tell a blurry light from a rough surface (docs/decisions/0193-pbr-roughness-lobe.md); the fitted scene is then rendered that way too.",
    )
    lobe_samples: int = setting(
        16, "Visible-normal samples per pixel of the full-lobe shading (used with lobe_steps)."
    )
    lobe_filter_width: float = setting(
        0.5,
        "Full-lobe shading: each sample looks the environment up pre-filtered at GGX width alpha = this x the angular radius (radians) of the solid angle the sample stands for (filtered importance sampling); 0 = unfiltered.",
    )
    lobe_views_per_step: int = setting(
        1,
        "Training views per full-lobe step (each costs lobe_samples look-ups per pixel; texture.views_per_step applies to the split-sum steps).",
    )
    lobe_learning_rate_scale: float = setting(
        0.25,
        "Full-lobe steps: factor on the learning rates of the base colour, the material and the environment (a refinement of a settled fit on fewer views per step).",
    )
    sun_lights: int = setting(
        0,
        "Directional lights (suns) split off the starting environment's brightest spots and fitted with shadow-map visibility and the exact BRDF (recon/optimize/sun_light.py; docs/decisions/0194-pbr-sun-visibility.md); 0: the environment alone, unshadowed.",
    )
    sun_cone_degrees: float = setting(
        10.0,
        "Half-angle of the cone around an environment peak whose excess radiance (over the ring around it) becomes a sun.",
    )
    sun_learning_rate: float = setting(
        0.01, "Adam learning rate of each sun's direction and log irradiance."
    )
    shadow_map_resolution: int = setting(
        512, "Side in texels of a sun's shadow map (the mesh's bounding sphere fills it)."
    )
    shadow_bias_texels: float = setting(
        2.0, "Constant depth bias of the shadow test, in shadow-map texels (against acne)."
    )
    shadow_slope_bias_texels: float = setting(
        2.0, "Depth bias per unit tan of the sun's angle to the normal, in shadow-map texels."
    )
    shadow_softness_texels: float = setting(
        0.5, "Softness of the shadow test's sigmoid in depth, in shadow-map texels."
    )
    shadow_map_every: int = setting(
        10, "Texture steps between redrawings of the suns' shadow maps (the mesh and suns move)."
    )
    sun_reclaim_share: float = setting(
        1.0,
        "Share of the starting environment's linear SH band along each sun moved into that sun (a Lambertian geometry stage leaves most of a sun in its SH; recon/optimize/sun_light.py reclaim_sun).",
    )

    def __post_init__(self) -> None:
        _check_vector(self.environment_size, "environment_size", length=2)
        for value, key in zip(self.environment_size, ("height", "width"), strict=True):
            check_range(value, f"environment_size {key}", low=2, high=512)
        check_range(self.prefilter_levels, "prefilter_levels", low=1, high=16)
        check_range(self.material_texture_size, "material_texture_size", low=0, high=8192)
        check_range(self.material_warmup_steps, "material_warmup_steps", low=0)
        check_range(self.lobe_steps, "lobe_steps", low=0)
        check_range(self.lobe_samples, "lobe_samples", low=1, high=4096)
        check_range(self.lobe_filter_width, "lobe_filter_width", low=0.0)
        check_range(self.lobe_views_per_step, "lobe_views_per_step", low=1)
        check_range(self.lobe_learning_rate_scale, "lobe_learning_rate_scale", low=0.0)
        check_range(self.initial_roughness, "initial_roughness", low=0.0, high=1.0)
        check_range(self.initial_metalness, "initial_metalness", low=0.0, high=1.0)
        check_range(self.specular_level, "specular_level", low=0.0, high=1.0)
        for key in (
            "material_learning_rate",
            "environment_learning_rate",
            "environment_seed_prior_weight",
            "material_smoothness_weight",
            "normal_map_smoothness_weight",
            "environment_smoothness_weight",
            "environment_whiteness_weight",
        ):
            check_range(getattr(self, key), key, low=0.0)
        check_range(self.sun_lights, "sun_lights", low=0, high=4)
        check_range(self.sun_cone_degrees, "sun_cone_degrees", low=1.0, high=45.0)
        check_range(self.shadow_map_resolution, "shadow_map_resolution", low=16, high=4096)
        check_range(self.shadow_map_every, "shadow_map_every", low=1)
        check_range(self.sun_reclaim_share, "sun_reclaim_share", low=0.0, high=1.0)
        for key in (
            "sun_learning_rate",
            "shadow_bias_texels",
            "shadow_slope_bias_texels",
        ):
            check_range(getattr(self, key), key, low=0.0)
        check_range(
            self.shadow_softness_texels, "shadow_softness_texels", low=0.0, low_inclusive=False
        )


@dataclass
class FitLightConfig:
    """The fit's light model. frame 'world': the light is fixed in the scene (the default);
    'camera': it is fixed to the camera (OpenCV camera axes), as in turntable captures where the
    object turns under studio lights, so that in the object's frame the light turns with the
    view."""

    frame: Literal["world", "camera"] = setting(
        "world",
        "world: the light is fixed in the scene; camera: fixed to the camera (turntable captures, where the object turns under studio lights).",
    )


@dataclass
class NormalizeConfig:
    """Recentring and rescaling of a dataset's cameras before the fit (the fit works in the
    normalised frame; meshes and lights are written in the dataset's own frame too)."""

    enabled: bool | None = setting(
        None,
        "Move the object (centre and size from the cameras' look-at point and a coarse carving of the masks) to the origin; null: on for datasets given with 'data', off for the synth stage's own.",
    )
    radius: float = setting(
        1.0, "Half the longest side of the object's box in the normalised frame."
    )
    grid: int = setting(48, "Voxels per side of the coarse carving grid.")
    image_size: int = setting(
        128, "Longer side of the masks the coarse carving reads (downsampled)."
    )
    up: Literal["auto", "x", "y", "z", "-x", "-y", "-z"] = setting(
        "auto",
        "The scene's up axis for figures: auto (the cameras' mean up) or an axis of the dataset's frame.",
    )

    def __post_init__(self) -> None:
        check_range(self.radius, "radius", low=0.0, low_inclusive=False)
        check_range(self.grid, "grid", low=8, high=256)
        check_range(self.image_size, "image_size", low=16, high=4096)


@dataclass
class SfmConfig:
    """Structure from motion for plain folders of photos (recon.io.sfm, pycolmap)."""

    peak_threshold: float = setting(
        0.004,
        "SIFT contrast threshold (COLMAP's default 0.0067): lower keeps more features on small photos.",
    )
    init_min_inliers: int = setting(
        50,
        "Inlier matches the first image pair needs (COLMAP's default 100): lower lets few, small photos start a model.",
    )
    seed: int = setting(0, "Random seed of the mapper (the same photos give the same poses).")

    def __post_init__(self) -> None:
        check_range(self.peak_threshold, "peak_threshold", low=0.0, low_inclusive=False)
        check_range(self.init_min_inliers, "init_min_inliers", low=8)


@dataclass
class DatasetConfig:
    """How a dataset folder (config key 'data', or the synth stage's dataset) is read."""

    max_resolution: int | None = setting(
        1024,
        "Longer image side after loading: larger photos are downsampled on load (antialiased, intrinsics scaled) with a message; null keeps the stored size.",
    )
    background_key: list[float] | None = setting(
        None,
        "For photos without masks or alpha: a linear RGB background colour (pixels within background_tolerance are background); null: such a dataset is an error.",
    )
    background_tolerance: float = setting(
        0.08, "Largest channel difference from background_key still counted as background."
    )
    holdout_every: int = setting(
        8,
        "Datasets without splits (LLFF, COLMAP, plain folders) hold out every N-th image as the test split.",
    )
    exposure: Literal["none", "exif"] = setting(
        "none",
        "exif: divide every photo by its EXIF exposure (time x ISO / f-number^2) relative to the median, a known per-view gain; none: pixels as they are.",
    )
    normalize: NormalizeConfig = setting(
        factory=NormalizeConfig, doc="Recentring and rescaling of the cameras before the fit."
    )
    sfm: SfmConfig = setting(
        factory=SfmConfig,
        doc="Structure from motion for folders of photos without poses (the result is cached in the folder).",
    )

    def __post_init__(self) -> None:
        if self.max_resolution is not None:
            check_range(self.max_resolution, "max_resolution", low=8, high=16384)
        if self.background_key is not None:
            _check_vector(self.background_key, "background_key")
        check_range(self.background_tolerance, "background_tolerance", low=0.0, high=1.0)
        check_range(self.holdout_every, "holdout_every", low=2)


@dataclass
class FitConfig:
    """The reconstruction recipe (two passes, nvdiffrec style)."""

    init: Literal["visual_hull", "icosphere"] = setting(
        "visual_hull",
        "Initial shape: the visual hull of the masks (keeps holes) or an icosphere filling the hull's bounds.",
    )
    hull_resolution: int = setting(128, "Voxel grid side of the visual hull.")
    geometry: GeometryStageConfig = setting(
        factory=GeometryStageConfig, doc="Stage 1: geometry, per-vertex albedo and light."
    )
    simplify: SimplifyConfig = setting(
        factory=SimplifyConfig, doc="Simplification between the stages."
    )
    texture: TextureStageConfig = setting(
        factory=TextureStageConfig,
        doc="Stage 2: texture, light and positions on the fixed topology.",
    )
    checkpoint_every: int = setting(
        50, "Steps between checkpoints (resume continues from the last one)."
    )
    effects: list[str] = setting(
        factory=list,
        doc="Model-side effect modules to fit with the scene (names from `recon effects`; none by default).",
    )
    material: Literal["lambert", "pbr"] = setting(
        "lambert",
        "Appearance model of the texture stage: lambert (albedo under SH + sun) or pbr (base colour, roughness, metalness under an optimised environment map, split-sum GGX).",
    )
    pbr: PbrFitConfig = setting(
        factory=PbrFitConfig, doc="Settings of the pbr material (used only with material: pbr)."
    )
    light: FitLightConfig = setting(
        factory=FitLightConfig, doc="The fit's light model (world or camera frame)."
    )

    def __post_init__(self) -> None:
        check_range(self.hull_resolution, "hull_resolution", low=8, high=512)
        check_range(self.checkpoint_every, "checkpoint_every", low=1)


# Twice the largest shared per-view colour spread of the blind check's clean synthetic fits
# (2 x 0.0083, Mitsuba teapot; 12 clean cases of the own and Mitsuba worlds, glossy ones
# included, re-diagnosed from b48v17 with the agreement of decision 0207;
# docs/decisions/0207-white-balance-exposure.md).
AGREEMENT_WHITE_BALANCE = 0.017
# The lobe evidence's allowance for specular (docs/decisions/0196-diagnosis-light-transport-lobe.md).
LOBE_SPECULAR = 0.02


@dataclass
class DecisionConfig:
    """The significance decision's allowances (recon.diagnose.decision): what each kind of
    evidence must clear. Defaults were measured with ``recon-bench calibrate`` on clean fits of
    the benchmark world (twice the largest clean reduction, floored at minimum_share);
    ``recon.diagnose.decision.redecide`` re-decides a stored diagnosis with other values."""

    minimum_share: float = setting(
        0.02,
        "Least held-out reduction a probe must clear to name any effect (the floor of every probe allowance).",
    )
    probe_allowance: dict[str, float] = setting(
        factory=lambda: {
            "defocus_blur": 0.157,
            "motion_blur": 0.14,
            "pose_error": 0.108,
            "lens_distortion": 0.056,
        },
        doc="Per effect: the held-out reduction its probe's bootstrap lower bound must clear (twice the largest on clean fits); effects left out take minimum_share.",
    )
    absorption_minimum_share: float = setting(
        0.01,
        "Floor of an absorption refit's allowance (two refits from one start: a smaller null than a probe's).",
    )
    regression_minimum_share: float = setting(
        0.005,
        "Floor of the closed-form (regression) absorption evidence's allowance (a share of interior-pixel error).",
    )
    absorption_allowance: dict[str, float] = setting(
        factory=lambda: {"lens_distortion": 0.043, "vignetting": 0.005, "specular": 0.01},
        doc="Per effect: the reduction over the control refit its absorption lower bound must clear.",
    )
    relight_allowance: float = setting(
        0.03,
        "The relight split's response-curve probe: what the lower bound of its compression (1 - the shading ratio's exponent) must clear.",
    )
    flat_field_allowance: float = setting(
        0.02,
        "Deviation from flat (corner or half-way falloff) above which flat-field frames name vignetting.",
    )
    line_target_allowance: float = setting(
        0.3,
        "Displacement at the image corners, in pixels, that the line-target frames' straightened lines must show for them to name a lens distortion (below it no lens is named, whatever its significance).",
    )
    line_target_levels_allowance: float = setting(
        0.001,
        "The least distance from 1 of the response's exponent over the line target's two levels for them to name a response curve, whatever the card: a guard on reading the levels off the plateaus between the stripes' edges (data_synth's exact card reads within line_target_z standard errors of 1 through every other effect; decision 0229). The card's own contrast tolerance (capture.line_target.contrast_tolerance) and the frames' standard errors raise it.",
    )
    line_target_z: float = setting(
        4.0,
        "How many standard errors the line-target frames' readings must clear: the corner displacement's (leave-one-frame-out, or the fit's own where there are fewer than three frames) and the levels' exponent's (over the frames).",
    )
    shadow_share: float = setting(
        0.6,
        "Fingerprint share at or above which the missing light transport is shadows, below it interreflection.",
    )
    fingerprint_minimum_coverage: float = setting(
        0.02,
        "Share of interior pixels the fitted mesh must shadow for the fingerprint to be testable at all.",
    )
    agreement_allowance: dict[str, float] = setting(
        factory=lambda: {"white_balance": AGREEMENT_WHITE_BALANCE},
        doc="Per effect with agreement evidence (recon.diagnose.agreement): the per-view colour spread (RMS log gain) that separate halves of each view must share (twice the largest on the blind check's clean synthetic fits, docs/decisions/0191-blind-misses.md).",
    )
    agreement_minimum: float = setting(
        0.01,
        "Floor of every agreement allowance: a 1 % per-view colour change, about a just-noticeable colour difference.",
    )
    agreement_alpha: float = setting(
        0.01,
        "Level of the agreement's permutation test (views of one half permuted): conventional, not tuned.",
    )
    lobe_allowance: dict[str, float] = setting(
        factory=lambda: {"specular": LOBE_SPECULAR},
        doc="Per effect with lobe evidence (recon.diagnose.lobe): how far the partial correlation of the view-to-view residual with a highlight's lobe under the fitted light must exceed the placebo lights' 95th percentile (the floor: on the blind check's clean synthetic fits the excess is below zero, docs/decisions/0196-diagnosis-light-transport-lobe.md).",
    )
    lobe_minimum: float = setting(
        0.02,
        "Floor of every lobe allowance: an excess correlation of 0.02 over the placebo lights' 95th percentile.",
    )
    lobe_alpha: float = setting(
        0.05,
        "Level of the lobe's placebo-light test (the share of placebo lights reaching the fitted light's correlation): the level of the 95th percentile its excess is measured over, not tuned; at 0.01 it asked to beat every one of ~170 placebo lights (docs/decisions/0208-response-specular.md).",
    )
    cast_shadow_minimum: float = setting(
        0.05,
        "Floor of the cast-shadow evidence (recon.diagnose.cast_shadow): how far the partial correlation of the relight residual with the relight sun's shadow from the fitted mesh must exceed the placebo directions' 95th percentile (docs/decisions/0203-diagnosis-interreflection-shadows.md).",
    )
    cast_shadow_alpha: float = setting(
        0.05,
        "Level of the cast-shadow evidence's placebo-direction test (the share of placebo directions reaching the relight sun's correlation): the level of the 95th percentile its excess is measured over, as the lobe's; at 0.01 it asked to beat every one of ~170 placebo directions, and a direction just past the separation shares the sun's shadow (docs/decisions/0211-shadows-specular-mitsuba.md).",
    )
    fingerprint_minimum: float = setting(
        0.02,
        "Floor of the visibility fingerprint (recon.diagnose.fingerprint): how far the partial correlation of the fitted albedo with the fitted mesh's self-shadowing under the fitted light must exceed the placebo lights' 95th percentile (docs/decisions/0206-fingerprint-share.md).",
    )
    fingerprint_alpha: float = setting(
        0.01,
        "Level of the visibility fingerprint's placebo-light test (the share of placebo lights reaching the fitted light's correlation): conventional, not tuned.",
    )
    bounce_minimum: float = setting(
        0.05,
        "Floor of the bounce evidence (recon.diagnose.bounce): how far the correlation of the relight residual with the relight sun's one diffuse bounce off the fitted mesh must exceed the placebo suns' 95th percentile (docs/decisions/0210-interreflection-bounce.md); the blind check's calibration raises it to twice the largest excess another scene's clean case reaches with its bounce evidence otherwise passing (docs/decisions/0215-interreflection-blind.md).",
    )
    bounce_alpha: float = setting(
        0.01,
        "Level of the bounce evidence's placebo-sun test (the share of placebo suns reaching the relight sun's correlation): conventional, not tuned; at 0.05 with a floor of 0.02 the path-traced torus's response curve gets a spurious interreflection (docs/decisions/0215-interreflection-blind.md).",
    )
    bounce_maximum_strength: float = setting(
        2.5,
        "Largest strength of the bounce evidence (the residual's coefficient on the predicted one bounce) that is bounced light: all bounces together give at most 1 / (1 - albedo) of one bounce, 2.5 at albedo 0.6; a pattern that needs more is something else following the relight sun (docs/decisions/0210-interreflection-bounce.md).",
    )
    beyond_confusers_allowance: dict[str, float] = setting(
        factory=lambda: {
            "defocus_blur": 0.031,
            "lens_distortion": 0.02,
            "motion_blur": 0.02,
            "pose_error": 0.045,
        },
        doc="Per geometric effect (recon.diagnose.geometric_judgement.beyond_confusers): the reduction its probe must keep on top of every confuser's probe (lower bound of the least); a null that scales with the fit, since a poor silhouette fit that any warp or blur reduces is reduced by the confusers too. Twice the largest on the blind check's clean synthetic fits (b48v18, all scenes; floored at minimum_share; docs/decisions/0213-geometric-allowances.md).",
    )
    relight_lobe_minimum: float = setting(
        0.05,
        "Floor of the relight split's lobe evidence (kind relight_lobe; the lobe's own allowance applies when higher): the relight split's floor, as the cast shadow's, set before its pixels were weighted (docs/decisions/0211-shadows-specular-mitsuba.md) and kept. Weighted (lobe.relight_spread_bins), its excess without a highlight reached +0.022 on the blind check's own and Mitsuba cases, with one +0.047 to +0.407 (docs/decisions/0216-relight-specular.md).",
    )

    edge_blur_minimum_ratio: float = setting(
        0.5,
        "Least share of the widening a blur probe's blur gives the fitted render's silhouette edges that the data's own edges must show (kind edge_blur, a null: recon.diagnose.edge_width.edge_blur_evidence); below it the probe's reduction is the fit's silhouette misfit, which any blur reduces, not a blur in the data. Half: on the blind check's four draws the injected blurs' edges showed 0.57-1.35 of their probes' widening, the own world's other cases none (all below 0) (docs/decisions/0223-edge-blur-null.md).",
    )

    def __post_init__(self) -> None:
        check_range(self.relight_lobe_minimum, "relight_lobe_minimum", low=0.0, high=1.0)
        check_range(self.edge_blur_minimum_ratio, "edge_blur_minimum_ratio", low=0.0, high=10.0)
        check_range(self.agreement_minimum, "agreement_minimum", low=0.0, high=1.0)
        check_range(self.agreement_alpha, "agreement_alpha", low=0.0, high=1.0)
        check_range(self.lobe_minimum, "lobe_minimum", low=0.0, high=1.0)
        check_range(self.lobe_alpha, "lobe_alpha", low=0.0, high=1.0)
        check_range(self.cast_shadow_minimum, "cast_shadow_minimum", low=0.0, high=1.0)
        check_range(self.cast_shadow_alpha, "cast_shadow_alpha", low=0.0, high=1.0)
        check_range(self.bounce_minimum, "bounce_minimum", low=0.0, high=1.0)
        check_range(self.bounce_alpha, "bounce_alpha", low=0.0, high=1.0)
        check_range(self.bounce_maximum_strength, "bounce_maximum_strength", low=0.0)
        for name in ("minimum_share", "absorption_minimum_share", "regression_minimum_share"):
            check_range(getattr(self, name), name, low=0.0, high=1.0)
        check_range(self.fingerprint_minimum, "fingerprint_minimum", low=0.0, high=1.0)
        check_range(self.fingerprint_alpha, "fingerprint_alpha", low=0.0, high=1.0)
        for name in ("relight_allowance", "flat_field_allowance"):
            check_range(getattr(self, name), name, low=0.0, high=1.0)
        check_range(self.line_target_allowance, "line_target_allowance", low=0.0)
        check_range(self.line_target_levels_allowance, "line_target_levels_allowance", low=0.0)
        check_range(self.line_target_z, "line_target_z", low=0.0)
        check_range(self.shadow_share, "shadow_share", low=0.0, high=1.0)


@dataclass
class SpecificityConfig:
    """The specificity checks (recon.diagnose.specificity): is a gain-like candidate's gain its
    own, or a confusable domain's profile? Block size and bootstrap resamples are the
    section's (diagnose.block_pixels, diagnose.bootstrap_samples)."""

    angle_bins: int = setting(
        6,
        "Quantile bins of n.h, n.v and radius: enough to follow a highlight's falloff, few enough that every view has pixels in most bins at 32-64 px.",
    )
    intensity_bins: int = setting(6, "Quantile bins of the rendered intensity.")
    surface_cells: int = setting(
        3, "Cells per axis of the grid over the fitted object's bounding box (surface regions)."
    )
    position_cells: int = setting(3, "Cells per axis of the image-position grid.")
    normal_cells: int = setting(
        4,
        "Cells per axis of the grid over the x and y components of the normal in camera axes (the domain of everything a light fixed to the camera does).",
    )
    alpha: float = setting(
        0.01,
        "The F-test's level: a candidate is specific when its own gain stands out above its scatter across every confusable domain's bins at this level (conventional, not tuned), unless the held-out pixels keep the retained share of its reduction with confidence (the interval's lower end at or above it).",
    )
    retained_share: float = setting(
        0.5,
        "Share of the held-out reduction that must survive the domain's profile (interval reaching it); a failed candidate names the mismatch only when its point estimate is below it.",
    )
    interval: float = setting(
        0.9, "Probability of the central bootstrap interval of the retained share."
    )
    seed: int = setting(0, "Random seed of the retained share's bootstrap over views.")

    def __post_init__(self) -> None:
        for name in (
            "angle_bins",
            "intensity_bins",
            "surface_cells",
            "position_cells",
            "normal_cells",
        ):
            check_range(getattr(self, name), name, low=1)
        for name in ("alpha", "retained_share", "interval"):
            check_range(getattr(self, name), name, low=0.0, high=1.0)


@dataclass
class GeometricSpecificityConfig:
    """The specificity checks of the geometric and blur candidates (recon.diagnose.
    geometric_specificity): does the candidate keep a reduction on top of the effect it is
    most often confused with, or does that effect take its place? The allowances are the
    decision's probe allowances; bootstrap resamples are the section's."""

    enabled: bool = setting(
        True, "Run the checks (each costs one joint probe fit per confuser of a cleared candidate)."
    )
    margin: float = setting(
        0.0,
        "How far the confuser's reduction on top of the candidate (its lower bound) must exceed the candidate's on top of the confuser (its upper bound) to take its place.",
    )
    edge_widths: bool = setting(
        True,
        "Measure the width of the data's silhouette edges by direction (recon.diagnose.edge_width): an isotropic widening is a defocus's, one wider across a direction per view a motion blur's.",
    )
    edge_gradient_minimum: float = setting(
        0.05,
        "Alpha gradient (per pixel) above which a pixel counts as an edge pixel of the matte.",
    )
    edge_soft_minimum: float = setting(
        0.5,
        "Share of the fitted render's edge pixels the observed matte must hold soft values at (strictly between 0 and 1) for its edges to have a width: a binary mask has none.",
    )
    edge_blur_soft_minimum: float = setting(
        0.1,
        "For the edge_blur null only (recon.diagnose.edge_width.edge_blur_evidence): the share of the fitted render's edge pixels the observed matte must hold soft values at. Lower than edge_soft_minimum: a matte harder than the render's (a renderer whose coverage is fractional on few edge pixels) is itself what a blur-free capture shows; a binary mask (none soft) still carries no width.",
    )
    edge_anisotropy_margin: float = setting(
        2.0,
        "How many times the anisotropy an isotropic blur of the run's own silhouettes shows (its null) the data's edges must show to be wider across one direction (the calibration's 'twice').",
    )

    def __post_init__(self) -> None:
        check_range(self.margin, "margin", low=0.0, high=1.0)
        check_range(self.edge_gradient_minimum, "edge_gradient_minimum", low=0.0, high=1.0)
        check_range(self.edge_soft_minimum, "edge_soft_minimum", low=0.0, high=1.0)
        check_range(self.edge_blur_soft_minimum, "edge_blur_soft_minimum", low=0.0, high=1.0)
        check_range(self.edge_anisotropy_margin, "edge_anisotropy_margin", low=1.0, high=100.0)


@dataclass
class NullConfig:
    """The run-derived nulls (recon.diagnose.nulls): placebo effects of a candidate's size and
    split-half agreement of per-view gains against permuted views."""

    placebo_draws: int = setting(
        20,
        "Random placebo effects per candidate: enough for the quantile to be read off (20: the largest but one for 95 %).",
    )
    quantile: float = setting(
        0.95,
        "Placebo quantile a candidate's reduction (its interval's lower bound) must exceed: a one-sided 5 % test.",
    )
    field_cells: int = setting(
        4,
        "Placebo fields are bilinear upsamplings of a field_cells^2 grid of normal draws less their mean: smooth like an effect, never its own signature.",
    )
    permutations: int = setting(1000, "View permutations of the split-half agreement's null.")
    seed: int = setting(0, "Random seed of the placebos and permutations.")

    def __post_init__(self) -> None:
        for name in ("placebo_draws", "field_cells", "permutations"):
            check_range(getattr(self, name), name, low=1)
        check_range(self.quantile, "quantile", low=0.0, high=1.0)


@dataclass
class IdentifiabilityConfig:
    """The identifiability conditions (recon.diagnose.identifiability): what the capture must
    hold for an effect to be told apart."""

    minimum_exposure_ratio: float = setting(
        2.0 ** (1 / 3),
        "Known exposure range (largest over smallest per-view gain) that lets a tone curve be read off: a third of a stop, the finest common bracketing step.",
    )
    corner_radius: float = setting(
        0.9,
        "Normalised radius (half diagonal = 1) the object must reach for a corner falloff to be measured rather than extrapolated.",
    )
    minimum_radius_spread: float = setting(
        0.1,
        "How far apart (normalised radius) the same surface region must be seen across views for a falloff to be told from the albedo.",
    )
    reference_corner_shift: float = setting(
        0.1,
        "Distortion judged when none was recovered: corner displacement over the half diagonal (a strong consumer-lens barrel).",
    )
    minimum_distinguishable_pixels: float = setting(
        0.5,
        "RMS (pixels) of the distortion flow no per-view zoom, shift and rotation reproduces, below which a pose correction explains it as well. Provenance: docs/decisions/0209-geometric-misses.md (the remainder's share of the held-out error against the lens probe's allowance gives the same verdicts on every blind scene but the torus); a prediction only: where the lens probe kept more than its allowance on top of every confuser's probe, pose included (decision row beyond_confusers), the measurement settles it (docs/decisions/0213-geometric-allowances.md).",
    )
    maximum_edge_coherence: float = setting(
        0.8,
        "Edge orientation coherence (0 = all orientations, 1 = one) above which a directional blur is a blur along the only edges.",
    )
    surface_cells: int = setting(
        3, "Cells per axis of the grid over the object for the radius spread."
    )
    white_balance_reference_spread: float = setting(
        0.05,
        "Per-view white-balance change judged (RMS log gain of red and blue over green; 5 %, an auto white balance wandering some 600 K around daylight): identifiable when the agreement's test names a change this small over the fit's per-view colour noise.",
    )

    reference_blur_radius: float = setting(
        1.0,
        "Defocus judged by the identifiability check (pillbox radius, pixels; 1 px: the smallest whose disk reaches the neighbouring pixels): would a blur this size clear the probe's allowance over this fit's misfit?",
    )
    blur_estimate_factor: float = setting(
        2.3,
        "What the defocus probe removes over the identifiability check's estimate (the reference blur's change of the render against the fit's misfit), the largest measured: 1.0-2.3 on the blind check's ten 1 px synthetic defocus cases (docs/decisions/0209-geometric-misses.md), so 'not identifiable' is said only below the allowance even then.",
    )

    def __post_init__(self) -> None:
        check_range(self.reference_blur_radius, "reference_blur_radius", low=0.0)
        check_range(self.blur_estimate_factor, "blur_estimate_factor", low=0.0)
        check_range(self.white_balance_reference_spread, "white_balance_reference_spread", low=0.0)
        check_range(self.minimum_exposure_ratio, "minimum_exposure_ratio", low=1.0)
        check_range(self.corner_radius, "corner_radius", low=0.0, high=2.0)
        check_range(self.minimum_radius_spread, "minimum_radius_spread", low=0.0, high=2.0)
        check_range(self.reference_corner_shift, "reference_corner_shift", low=0.0, high=1.0)
        check_range(self.minimum_distinguishable_pixels, "minimum_distinguishable_pixels", low=0.0)
        check_range(self.maximum_edge_coherence, "maximum_edge_coherence", low=0.0, high=1.0)
        check_range(self.surface_cells, "surface_cells", low=1)


@dataclass
class MetadataConfig:
    """The capture-metadata check (recon.diagnose.metadata_check): recovered exposure against
    EXIF exposure."""

    permutations: int = setting(2000, "View permutations of the correlation's p-value.")
    alpha: float = setting(
        0.05, "The correlation's level (one-sided, positive): the conventional 5 %."
    )
    seed: int = setting(0, "Random seed of the permutations.")
    minimum_views: int = setting(
        3,
        "Held-out views with EXIF exposure needed for the check (a correlation across views needs at least 3); with fewer the run has no metadata evidence.",
    )
    equal_tolerance: float = setting(
        0.01,
        "When the known exposure is the same in every view (fixed exposure, or images already divided by their EXIF exposure): the median ratio error up to which the recovered exposure agrees (1 %, about an 8-bit photo's mid-tone step).",
    )

    def __post_init__(self) -> None:
        check_range(self.permutations, "permutations", low=1)
        check_range(self.minimum_views, "minimum_views", low=3)
        check_range(self.alpha, "alpha", low=0.0, high=1.0)
        check_range(self.equal_tolerance, "equal_tolerance", low=0.0, high=1.0)


@dataclass
class BackdropConfig:
    """The backdrop check (recon.diagnose.backdrop): a per-view camera gain (exposure, white
    balance) scales the whole frame, so where the photos share a static backdrop, its change
    from view to view is the camera's, read apart from the object's reflectance."""

    object_margin_pixels: int = setting(
        2,
        "Pixels around the object's mask (dilated) left out of the backdrop: the mask's edge and the object's blur.",
    )
    darkest: float = setting(
        0.01,
        "Backdrop pixels with a linear channel below this are left out (their log is noise and 8-bit steps).",
    )
    brightest: float = setting(
        0.97,
        "Backdrop pixels with a linear channel above this are left out (clipped: a gain does not scale them).",
    )
    static_tolerance: float = setting(
        0.08,
        "A backdrop pixel is static when its log colour, per-view gain removed, stays within this of its median over the views (median absolute deviation): the same surface under the same light in every frame. Chosen on the shared real capture at 96 px (0.04 left 137 of 9216 pixels); its veto or pass is the same from 0.05 to 0.12 on every real case, whether a vetoed gain is also 'not identifiable' is not (docs/decisions/0221-backdrop.md).",
    )
    minimum_pixels: int = setting(
        100,
        "Static backdrop pixels needed for a reading; with fewer (a moving camera, a transparent or clipped background) the check does not apply.",
    )
    minimum_views: int = setting(3, "Held-out views needed for a reading.")
    detectable_factor: float = setting(
        3.0,
        "The check applies only where the change the object's gains show (RMS over the views) is this many times the backdrop's reading noise (its top and bottom halves' difference): a change the backdrop could not see is no evidence either way.",
    )
    minimum_explained: float = setting(
        0.5,
        "The share of the object's gain change (1 - RMS(object - backdrop) / RMS(object), log gains over the views) the backdrop must show for the gain to be the camera's: at least half.",
    )

    def __post_init__(self) -> None:
        check_range(self.object_margin_pixels, "object_margin_pixels", low=0)
        check_range(self.darkest, "darkest", low=0.0, high=1.0)
        check_range(self.brightest, "brightest", low=0.0, high=1.0)
        check_range(self.static_tolerance, "static_tolerance", low=0.0)
        check_range(self.minimum_pixels, "minimum_pixels", low=1)
        check_range(self.minimum_views, "minimum_views", low=3)
        check_range(self.detectable_factor, "detectable_factor", low=0.0)
        check_range(self.minimum_explained, "minimum_explained", low=0.0, high=1.0)
        if self.darkest >= self.brightest:
            raise ConfigFieldError(
                "darkest", f"expected below brightest ({self.brightest}), got {self.darkest}"
            )


@dataclass
class LobeConfig:
    """The lobe evidence (recon.diagnose.lobe): the view-to-view residual against a highlight's
    lobe under the fitted light, on the training and held-out views, against placebo lights."""

    exponents: list[float] = setting(
        factory=lambda: [8.0, 16.0, 32.0, 64.0, 128.0],
        doc="Blinn-Phong exponents the lobe is tried at (the best counts, for the placebo lights as for the fitted one): roughness about 0.55 to 0.25.",
    )
    cells_per_axis: int = setting(
        12,
        "Cells per axis of the voxel grid over the object's surface points that get one offset each (what an albedo absorbs).",
    )
    placebo_lights: int = setting(
        200,
        "Directions of the Fibonacci sphere tried as placebo lights (those near the fitted light are left out).",
    )
    placebo_separation_degrees: float = setting(
        45.0,
        "Least angle between a placebo light and the fitted light: nearer ones share its highlights.",
    )
    minimum_pixels: int = setting(
        200, "Interior object pixels over all views below which no lobe evidence is measured."
    )
    enabled: bool = setting(True, "Measure the lobe evidence for the specular candidate.")
    maximum_pixels: int = setting(
        20000,
        "Interior object pixels (over all views) the lobe evidence uses at most, an even stride through them: its cost is pixels x placebo lights x exponents.",
    )
    blur_nuisance: bool = setting(
        True,
        "Project out, per view, the render's image Laplacian (a blur's first-order change, which follows the fitted light but not the half-vector) before the lobe is correlated (docs/decisions/0208-response-specular.md).",
    )
    relight: bool = setting(
        True,
        "Also test the lobe on the relight split under its known light (evidence 'relight_lobe'): no fitted light's error there (the Mitsuba bunny's highlight reads r = 0.14 against placebo lights at 0.03 there, 0.035 against 0.039 on the training and held-out views). Its pixels are weighted by the residual's spread along the sun's cosine (relight_spread_bins): unweighted, the Mitsuba spot's relight split read a lobe without any highlight (+0.074, +0.083; docs/decisions/0211-shadows-specular-mitsuba.md, 0216-relight-specular.md).",
    )
    relight_spread_bins: int = setting(
        8,
        "Bins of the relight sun's cosine (equal pixel counts) in each of which the relight residual's robust spread (1.4826 x median absolute value, the nuisances projected out) weights the relight lobe's pixels (1 / spread, for the sun and every placebo light): a fit's residual is larger where the sun lights the surface, so unweighted a lobe under the sun reads more than placebo lights' lobes in the dim part. 1: unweighted (docs/decisions/0216-relight-specular.md).",
    )

    def __post_init__(self) -> None:
        if not self.exponents or any(value <= 0 for value in self.exponents):
            raise ConfigFieldError(
                "exponents", f"expected positive exponents, got {self.exponents}"
            )
        for name in (
            "cells_per_axis",
            "placebo_lights",
            "minimum_pixels",
            "maximum_pixels",
            "relight_spread_bins",
        ):
            check_range(getattr(self, name), name, low=1)
        check_range(
            self.placebo_separation_degrees, "placebo_separation_degrees", low=0.0, high=180.0
        )


@dataclass
class CastShadowConfig:
    """The cast-shadow evidence (recon.diagnose.cast_shadow): the relight split's residual
    against the relight sun's shadow from the fitted mesh, against placebo directions."""

    placebo_lights: int = setting(
        200,
        "Directions of the Fibonacci sphere tried as placebo suns (those near the relight sun are left out).",
    )
    placebo_separation_degrees: float = setting(
        45.0,
        "Least angle between a placebo direction and the relight sun: nearer ones share its shadows.",
    )
    map_resolution: int = setting(
        128, "Texels a side of each direction's shadow map of the fitted mesh."
    )
    minimum_pixels: int = setting(
        200, "Interior relight pixels below which no cast-shadow evidence is measured."
    )
    maximum_pixels: int = setting(
        20000,
        "Interior relight pixels the evidence uses at most, an even stride through them: its cost is pixels x directions.",
    )
    enabled: bool = setting(True, "Measure the cast-shadow evidence for the shadows candidate.")
    silhouette_occluders: bool = setting(
        True,
        "Also predict the relight sun's shadows from the observed silhouettes' visual hull (thin parts a short fit drops: a spout, legs); each direction keeps the larger correlation of the two occluders, the placebo directions too (docs/decisions/0211-shadows-specular-mitsuba.md).",
    )
    silhouette_voxel_pixels: float = setting(
        1.0,
        "Voxel of the silhouette hull's carving grid, in the views' median pixel footprint at the object: finer voxels carve the masks' aliasing into the hull (at 48 px the teapot's relight shadows read r = 0.30 at one pixel, 0.21 at half a pixel).",
    )
    silhouette_margin: float = setting(
        1.5,
        "Half size of the silhouette hull's grid as a multiple of the fitted mesh's half extent (the hull must fit inside; an occupied border drops the hull).",
    )
    identifiable_shadowed: float = setting(
        0.02,
        "Share of the sun-facing relight pixels the fitted mesh or the silhouettes must shadow for the relight split to count as a test of cast shadows (it then voids the fingerprint's 'one light cannot tell' condition; below it the condition asks for a sun the object shadows itself).",
    )

    def __post_init__(self) -> None:
        check_range(self.silhouette_margin, "silhouette_margin", low=1.0)
        check_range(self.silhouette_voxel_pixels, "silhouette_voxel_pixels", low=0.01)
        check_range(self.identifiable_shadowed, "identifiable_shadowed", low=0.0, high=1.0)
        for name in ("placebo_lights", "map_resolution", "minimum_pixels", "maximum_pixels"):
            check_range(getattr(self, name), name, low=1)
        check_range(
            self.placebo_separation_degrees, "placebo_separation_degrees", low=0.0, high=180.0
        )


@dataclass
class BounceConfig:
    """The bounce evidence (recon.diagnose.bounce): the relight split's residual against the
    relight sun's one diffuse bounce off the fitted mesh, against placebo suns."""

    directions: int = setting(
        64,
        "Fibonacci directions over the sphere along which each point gathers sky light and bounced light (ray cast against the fitted mesh).",
    )
    cells: int = setting(
        40,
        "Cells a side of the grid over the triangles projected along each ray direction (speed only: each ray is tested against its cell's triangles).",
    )
    placebo_lights: int = setting(
        200,
        "Directions of the Fibonacci sphere tried as placebo suns (those near the relight sun are left out).",
    )
    placebo_separation_degrees: float = setting(
        45.0,
        "Least angle between a placebo sun and the relight sun: nearer ones light the same faces.",
    )
    visibility_floor: float = setting(
        0.05,
        "Least share of a point's unoccluded training irradiance its occluded irradiance is taken to be (the ratios divide by it; a point the mesh hides entirely is noise).",
    )
    minimum_pixels: int = setting(
        200, "Interior relight pixels below which no bounce evidence is measured."
    )
    maximum_pixels: int = setting(
        4000,
        "Interior relight pixels the evidence uses at most, an even stride through them: its cost is pixels x (directions + placebo suns).",
    )
    enabled: bool = setting(True, "Measure the bounce evidence for the interreflection candidate.")
    penumbra_pixels: float = setting(
        0.0,
        "How far, in pixels at the object, the relight sun's shadow edges may lie from where the fitted mesh puts them (a soft sun's penumbra, a misplaced occluder): the direct-light nuisance is also computed with the sun turned this many pixel footprints over the mesh's radius in four directions, each a free nuisance column, so a shadow edge is not read as bounced light. 0 (default): the point sun only; 1 silences the path-traced bob's shadows case (excess 0.025 -> -0.005) but names no further interreflection case (docs/decisions/0215-interreflection-blind.md).",
    )

    def __post_init__(self) -> None:
        for name in (
            "directions",
            "cells",
            "placebo_lights",
            "minimum_pixels",
            "maximum_pixels",
        ):
            check_range(getattr(self, name), name, low=1)
        check_range(
            self.placebo_separation_degrees, "placebo_separation_degrees", low=0.0, high=180.0
        )
        check_range(self.visibility_floor, "visibility_floor", low=1e-6, high=1.0)
        check_range(self.penumbra_pixels, "penumbra_pixels", low=0.0)


@dataclass
class FingerprintConfig:
    """The visibility fingerprint (recon.diagnose.fingerprint): the fitted albedo against the
    fitted mesh's self-shadowing under the fitted light, against placebo lights."""

    placebo_lights: int = setting(
        200,
        "Fibonacci directions the fitted light's dominant direction is turned to as placebo lights (those near it are left out).",
    )
    placebo_separation_degrees: float = setting(
        45.0,
        "Least angle between a placebo light's dominant direction and the fitted one: nearer ones share its shadows.",
    )

    def __post_init__(self) -> None:
        check_range(self.placebo_lights, "placebo_lights", low=1)
        check_range(
            self.placebo_separation_degrees, "placebo_separation_degrees", low=0.0, high=180.0
        )


@dataclass
class DiagnoseConfig:
    """The gap diagnosis (recon diagnose): which candidates, how each kind of evidence is
    measured, how far the refits go, and the decision's allowances."""

    refit: Literal["none", "top", "greedy"] = setting(
        "top",
        "How far: no refit, the top effect, or greedily each significant one (--refit overrides).",
    )
    candidates: list[str] = setting(
        factory=list,
        doc="Effects to consider (names from `recon effects`); empty: every effect the fit did not model (--effects overrides).",
    )
    absorption: bool = setting(
        True,
        "Run the absorption evidence (refits that let an effect take back what the fit absorbed).",
    )
    block_pixels: int = setting(
        4, "Side of the checkerboard blocks that split each held-out view into fit and test halves."
    )
    band_pixels: int = setting(
        3,
        "Pixels around the silhouette that count toward the gap (edge residuals of blur, distortion, pose).",
    )
    bootstrap_samples: int = setting(
        400,
        "Bootstrap resamples (over views, or pixel blocks for the fingerprint) of every interval.",
    )
    fingerprint_block_pixels: int = setting(
        8, "Side of the pixel blocks the visibility fingerprint's bootstrap resamples."
    )
    gauss_newton_iterations: int = setting(
        5, "Damped Gauss-Newton iterations of a probe (effect parameters only, scene frozen)."
    )
    absorption_steps: int = setting(
        24, "Steps of a frozen-geometry absorption refit (texture, light and the effect)."
    )
    geometry_steps: int = setting(
        15, "Steps of a geometry-moving absorption refit (effects that bend the geometry)."
    )
    geometry_resolution: int = setting(
        64, "Image side of the geometry-moving absorption refits (their cost is per triangle)."
    )
    absorption_texture_learning_rate: float = setting(
        0.03, "Texture step size of the frozen-geometry absorption refits."
    )
    absorption_light_learning_rate: float = setting(
        0.01, "Light step size of the frozen-geometry absorption refits."
    )
    absorption_smoothness_weight: float = setting(
        0.01, "Texture total-variation weight of the frozen-geometry absorption refits."
    )
    smallest_remaining_share: float = setting(
        0.05,
        "Least share of the error a given (conditioning) effect is taken to leave when deciding whether absorption refits are worth repeating on top of it.",
    )
    relight_iterations: int = setting(
        6, "Gauss-Newton iterations of the relight split's response probe."
    )
    relight_tile_pixels: int = setting(
        16,
        "Side of the image tiles the relight probe's bootstrap resamples (the exponent is one number for every view, and a relight split has few views).",
    )
    relight_shadowed_share: float = setting(
        0.1,
        "Pixels whose fitted surface loses more than this share of either light to the mesh itself are left out of the relight probe.",
    )
    regression_cells_per_side: int = setting(
        32,
        "Texture cells per side of the vignetting regression's cell gains (enough pixels per cell and view, a narrow range of radii per cell).",
    )
    regression_interior_margin: int = setting(
        4,
        "Pixels in from either silhouette that the vignetting regression leaves out (antialiasing, edge offsets, grazing shading).",
    )
    regression_minimum_rendered: float = setting(
        0.02,
        "Rendered values (linear, per channel) below which the vignetting regression leaves a pixel out (its log ratio is mostly noise).",
    )
    flat_field_half_window: int = setting(
        6, "Pixels each side of a point in the flat-field frames' local quadratic fits."
    )
    flat_field_maximum_clipped_share: float = setting(
        0.01,
        "Share of a flat-field frame's pixels at full scale above which the frame is refused (clipping flattens the falloff).",
    )
    refit_steps: int = setting(80, "Texture-stage steps of a how-far refit (warm start).")
    refit_position_learning_rate: float = setting(
        0.002,
        "Vertex step size of a how-far refit unless a geometry-bending effect is on (then the fit's own).",
    )
    max_greedy_effects: int = setting(3, "Most effects a greedy refit chain switches on.")
    confirming_share: float = setting(
        0.05,
        "Share of the gap above the floor a refit must close to confirm its effect (and continue a greedy chain).",
    )
    decision: DecisionConfig = setting(
        factory=DecisionConfig, doc="The significance decision's allowances."
    )
    specificity: SpecificityConfig = setting(
        factory=SpecificityConfig, doc="Specificity checks of the gain-like candidates."
    )
    geometric_specificity: GeometricSpecificityConfig = setting(
        factory=GeometricSpecificityConfig,
        doc="Specificity checks of the geometric and blur candidates.",
    )
    nulls: NullConfig = setting(
        factory=NullConfig, doc="Nulls from the run: placebo effects and split-half agreement."
    )
    identifiability: IdentifiabilityConfig = setting(
        factory=IdentifiabilityConfig,
        doc="Identifiability conditions on the capture (what would settle each effect).",
    )
    metadata: MetadataConfig = setting(
        factory=MetadataConfig, doc="Recovered exposure against the capture's EXIF exposure."
    )
    backdrop: BackdropConfig = setting(
        factory=BackdropConfig,
        doc="The camera's per-view gains read off a static backdrop, against the object's.",
    )
    lobe: LobeConfig = setting(
        factory=LobeConfig,
        doc="The lobe evidence: the view-to-view residual against a highlight under the fitted light.",
    )
    cast_shadow: CastShadowConfig = setting(
        factory=CastShadowConfig,
        doc="The cast-shadow evidence: the relight split's residual against the relight sun's shadow from the fitted mesh.",
    )
    fingerprint: FingerprintConfig = setting(
        factory=FingerprintConfig,
        doc="The visibility fingerprint: the fitted albedo against the fitted mesh's self-shadowing, beyond placebo lights.",
    )
    relight_compressive_only: bool = setting(
        True,
        "The relight probe credits only a compressive curve (exponent below 1 on the shading ratio, what a camera's response does to highlights); an expanding one (a highlight under the relight sun that the diffuse fit lacks) removes nothing (docs/decisions/0208-response-specular.md).",
    )
    colour_erode_pixels: int = setting(
        1,
        "Pixels the agreement's per-view colour gains leave out inside the silhouettes of both the photo and the render (recon.diagnose.agreement): a silhouette pixel's colour ratio is the coverage misfit's.",
    )
    colour_dark_fraction: float = setting(
        0.02,
        "The agreement's per-view colour gains leave out pixels darker than this share of the view's brightest (photo or render): their colour ratios are noise.",
    )
    colour_highlight_powers: list[int] = setting(
        factory=lambda: [1, 8],
        doc="Powers p of n.h whose per-view mean (how much of a highlight's lobe a view shows: a broad and a narrow lobe) the agreement removes from the views' colour gains with their brightness, so that a coloured highlight is not a white balance (recon.diagnose.agreement.view_covariates).",
    )
    exposure_highlight_powers: list[int] = setting(
        factory=lambda: [1, 4, 16, 64],
        doc="Powers of n.h of the highlight lobe that the exposure's per-view gains are read apart from (recon.diagnose.camera_gain): from a broad lobe to a narrow one.",
    )
    exposure_gain_iterations: int = setting(
        30, "Alternating least-squares steps of the exposure's highlight-free per-view gains."
    )
    bounce: BounceConfig = setting(
        factory=BounceConfig,
        doc="The bounce evidence: the relight split's residual against the relight sun's one diffuse bounce off the fitted mesh.",
    )
    relight_grazing_cosines: list[float] = setting(
        factory=lambda: [-0.1, 0.3],
        doc="The relight probe leaves out pixels whose fitted normal's cosine to the relight split's dominant light lies between these two: near that light's terminator an error of the fitted normal moves the predicted shading ratio most, and the noisy ratio reads as a compressive exponent on clean fits (docs/decisions/0212-response-curve-relight.md).",
    )
    relight_blur_nuisance: bool = setting(
        True,
        "The relight probe's exponent is fitted beside one blur strength per view (the relight render's Laplacian, a blur's first-order change): a defocus smooths the observed shading ratio, which otherwise reads as a compressive exponent (docs/decisions/0212-response-curve-relight.md).",
    )
    exposure_gain_estimator: str = setting(
        "highlight_free",
        "How the exposure's per-view gains are read (recon.diagnose.camera_gain): 'highlight_free' (least squares over the view's pixels beside a highlight lobe in n.h shared by the views) or 'robust_regions' (one gain per view plus one per region shared by the views, fitted robustly to the regions' gains, so that one view's misfit region does not move its gain; docs/decisions/0219-real-exposure.md).",
    )
    exposure_region_factors: list[str] = setting(
        factory=lambda: ["surface"],
        doc="The pixel-table factors whose joint cells are the regions of the 'robust_regions' exposure gains (recon.diagnose.pixel_table: surface, n_dot_h, n_dot_v, intensity, image_position, radius, camera_normal).",
    )
    exposure_region_tukey: float = setting(
        4.685,
        "Tukey biweight tuning constant, in robust standard deviations of the region gains' residuals, of the 'robust_regions' exposure gains: a (view, region) gain this far from the model has no weight.",
    )

    def __post_init__(self) -> None:
        for name in (
            "block_pixels",
            "fingerprint_block_pixels",
            "bootstrap_samples",
            "gauss_newton_iterations",
            "relight_iterations",
            "relight_tile_pixels",
            "regression_cells_per_side",
            "flat_field_half_window",
        ):
            check_range(getattr(self, name), name, low=1)
        check_range(self.band_pixels, "band_pixels", low=0)
        check_range(self.colour_erode_pixels, "colour_erode_pixels", low=0)
        check_range(self.colour_dark_fraction, "colour_dark_fraction", low=0.0, high=1.0)
        for power in self.colour_highlight_powers:
            check_range(power, "colour_highlight_powers", low=1)
        for power in self.exposure_highlight_powers:
            check_range(power, "exposure_highlight_powers", low=1)
        check_range(self.exposure_gain_iterations, "exposure_gain_iterations", low=1)
        if self.exposure_gain_estimator not in ("highlight_free", "robust_regions"):
            raise ConfigFieldError(
                "exposure_gain_estimator",
                f"expected highlight_free or robust_regions, got {self.exposure_gain_estimator!r}",
            )
        region_factors = {"surface", "n_dot_h", "n_dot_v", "intensity", "image_position"}
        region_factors |= {"radius", "camera_normal"}
        unknown_factors = sorted(set(self.exposure_region_factors) - region_factors)
        if unknown_factors:
            raise ConfigFieldError(
                "exposure_region_factors",
                f"unknown factors {unknown_factors}; known: {', '.join(sorted(region_factors))}",
            )
        check_range(self.exposure_region_tukey, "exposure_region_tukey", low=1e-3)
        if len(self.relight_grazing_cosines) != 2:
            raise ConfigFieldError(
                "relight_grazing_cosines",
                f"expected [low, high], got {self.relight_grazing_cosines}",
            )
        low, high = self.relight_grazing_cosines
        check_range(low, "relight_grazing_cosines", low=-1.0, high=1.0)
        check_range(high, "relight_grazing_cosines", low=low, high=1.0)
        check_range(self.regression_interior_margin, "regression_interior_margin", low=0)
        for name in (
            "relight_shadowed_share",
            "regression_minimum_rendered",
            "flat_field_maximum_clipped_share",
        ):
            check_range(getattr(self, name), name, low=0.0, high=1.0)
        for name in ("absorption_steps", "geometry_steps", "refit_steps", "max_greedy_effects"):
            check_range(getattr(self, name), name, low=1)
        check_range(self.geometry_resolution, "geometry_resolution", low=MINIMUM_VIEW_SIZE)
        check_range(self.confirming_share, "confirming_share", low=0.0, high=1.0)
        check_range(self.smallest_remaining_share, "smallest_remaining_share", low=1e-6, high=1.0)
        unknown = sorted(set(self.candidates) - set(EFFECT_NAMES))
        if unknown:
            raise ConfigFieldError(
                "candidates", f"unknown effects {unknown}; known: {', '.join(EFFECT_NAMES)}"
            )


@dataclass
class EvaluateConfig:
    """The evaluate stage's settings beyond the held-out images: how a `pbr` fit's material is
    compared with a synthetic world's true maps (recon/metrics/material.py)."""

    material_samples: int = setting(
        50_000,
        "Points sampled (by area) on the fitted surface to compare its roughness/metalness with the reference's true maps at the closest reference point.",
    )
    material_tolerance: float = setting(
        0.05,
        "A sample's roughness (metalness) counts as recovered when within this of the truth: metrics.json's material.*_within_tolerance.",
    )
    material_max_distance: float = setting(
        0.01,
        "Samples farther than this (in reference bounding-box diagonals) from the reference are left out of the material comparison (a geometry error, not a material one).",
    )
    material_seen_only: bool = setting(
        True,
        "Compare the material only where some training view saw the surface (unseen texels hold the regulariser's guess, not a measurement).",
    )
    material_depth_tolerance: float = setting(
        0.02,
        "A surface point counts as seen by a view when it is at most this fraction of its depth behind the nearest surface at its pixel.",
    )

    def __post_init__(self) -> None:
        check_range(self.material_samples, "material_samples", low=1)
        check_range(self.material_tolerance, "material_tolerance", low=0.0, high=1.0)
        check_range(self.material_max_distance, "material_max_distance", low=0.0)
        check_range(self.material_depth_tolerance, "material_depth_tolerance", low=0.0)


@dataclass
class RunConfig:
    """A whole run: a name, one seed threaded through every stage, the device, and sections."""

    name: str = setting(
        "run", "Run name: the folder under runs/ when --out is not given (a plain folder name)."
    )
    seed: int = setting(
        0,
        "The one seed threaded through every stage: the same config and seed give the same result on CPU.",
    )
    data: str | None = setting(
        None,
        "An existing dataset folder (NeRF-synthetic or LLFF) to fit instead of synthesising one.",
    )
    device: Literal["auto", "cpu", "cuda"] = setting(
        "auto", "Where to compute: auto picks cuda when present, else cpu."
    )
    deterministic: bool = setting(
        True,
        "Use torch's deterministic kernels, so the same config and seed give identical results "
        "with any thread count (CPU); false may be faster on CUDA but results then vary.",
    )
    stages: list[Literal["synth", "fit", "evaluate", "report"]] = setting(
        factory=lambda: ["synth", "fit", "evaluate", "report"],
        doc="Stages `recon run` runs, in order.",
    )
    scene: SceneConfig = setting(factory=SceneConfig, doc="The synthetic scene (data_synth).")
    capture: CaptureConfig = setting(
        factory=CaptureConfig, doc="The synthetic capture: cameras, splits, effects (data_synth)."
    )
    fit: FitConfig = setting(factory=FitConfig, doc="The reconstruction recipe.")
    dataset: DatasetConfig = setting(
        factory=DatasetConfig,
        doc="How a dataset folder is read: size cap, masks, held-out split, EXIF exposure, normalisation.",
    )
    diagnose: DiagnoseConfig = setting(
        factory=DiagnoseConfig,
        doc="The gap diagnosis (recon diagnose): evidence settings, refits, decision allowances.",
    )
    evaluate: EvaluateConfig = setting(
        factory=EvaluateConfig,
        doc="The evaluate stage: how a pbr fit's material is compared with a synthetic world's true maps.",
    )

    def __post_init__(self) -> None:
        if not self.name or any(character in self.name for character in "/\\:"):
            raise ConfigFieldError("name", f"expected a plain folder name, got {self.name!r}")

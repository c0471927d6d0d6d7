"""The run config schema: what a YAML config may say. Every section is strict (unknown keys are
errors with a suggestion) and validated where it is loaded; see README "Config reference".

Sections consumed by data_synth (scene, capture) are declared here so that a config is checked
whole before any stage runs; data_synth imports them (recon never imports data_synth).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from recon.config.checks import ConfigFieldError, check_range


@dataclass
class ShapeConfig:
    """The reference geometry: a built-in procedural shape or a mesh file (OBJ/PLY/GLB/OFF)."""

    procedural: str | None = "torus"
    mesh_path: str | None = None
    resolution: int = 64
    texture_path: str | None = None

    def __post_init__(self) -> None:
        if (self.procedural is None) == (self.mesh_path is None):
            raise ConfigFieldError("procedural", "give exactly one of 'procedural' and 'mesh_path'")
        check_range(self.resolution, "resolution", low=8, high=512)


@dataclass
class MaterialConfig:
    """Albedo: a procedural texture (checker, stripes, noise, patches), the mesh file's own
    texture ('file'), or a procedural vertex colour field ('vertex_noise')."""

    albedo: Literal["checker", "stripes", "noise", "patches", "file", "vertex_noise"] = "checker"
    texture_size: int = 256
    seed: int = 0
    # Used only where light transport renders specular reflection (the 'specular' effect).
    roughness: float = 0.3
    specular_level: float = 0.5

    def __post_init__(self) -> None:
        check_range(self.texture_size, "texture_size", low=4, high=8192)
        check_range(self.roughness, "roughness", low=0.01, high=1.0)
        check_range(self.specular_level, "specular_level", low=0.0, high=1.0)


@dataclass
class SunConfig:
    """A directional light: direction toward the light (world), irradiance per channel."""

    direction: list[float] = field(default_factory=lambda: [0.4, 0.8, 0.5])
    irradiance: list[float] = field(default_factory=lambda: [2.0, 2.0, 2.0])

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

    position: list[float] = field(default_factory=lambda: [1.5, 2.0, 1.5])
    intensity: list[float] = field(default_factory=lambda: [5.0, 5.0, 5.0])

    def __post_init__(self) -> None:
        _check_vector(self.position, "position")
        _check_vector(self.intensity, "intensity")
        check_range(self.intensity, "intensity", low=0.0)


@dataclass
class AreaLightConfig:
    """A one-sided rectangular emitter facing the origin from center (soft shadows in the path
    tracer; recon's renderer treats it as a point light with a cosine lobe at its centre)."""

    center: list[float] = field(default_factory=lambda: [1.0, 2.5, 1.0])
    size: list[float] = field(default_factory=lambda: [1.0, 1.0])
    radiance: list[float] = field(default_factory=lambda: [4.0, 4.0, 4.0])

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

    kind: Literal["none", "exr", "sky", "studio"] = "none"
    path: str | None = None
    strength: float = 1.0
    sun_elevation_deg: float = 45.0
    sun_azimuth_deg: float = 30.0
    sun_irradiance: float = 3.0
    resolution: list[int] = field(default_factory=lambda: [64, 128])

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

    ambient: list[float] = field(default_factory=lambda: [0.6, 0.6, 0.6])
    sky_gradient: float = 0.2
    suns: list[SunConfig] = field(default_factory=lambda: [SunConfig()])
    points: list[PointLightConfig] = field(default_factory=list)
    areas: list[AreaLightConfig] = field(default_factory=list)
    environment: EnvironmentConfig = field(default_factory=EnvironmentConfig)

    def __post_init__(self) -> None:
        _check_vector(self.ambient, "ambient")
        check_range(self.ambient, "ambient", low=0.0)
        check_range(self.sky_gradient, "sky_gradient", low=-1.0, high=1.0)


@dataclass
class SceneConfig:
    shape: ShapeConfig = field(default_factory=ShapeConfig)
    material: MaterialConfig = field(default_factory=MaterialConfig)
    lighting: LightingConfig = field(default_factory=LightingConfig)


@dataclass
class CameraRigConfig:
    """Where the captures are taken from."""

    rig: Literal["fibonacci", "orbit", "random", "hemisphere"] = "fibonacci"
    distance: float = 3.0
    fov_deg: float = 40.0
    resolution: list[int] = field(default_factory=lambda: [128, 128])
    jitter_deg: float = 0.0
    near: float = 0.1
    far: float = 100.0

    def __post_init__(self) -> None:
        check_range(self.distance, "distance", low=0.0, low_inclusive=False)
        check_range(self.fov_deg, "fov_deg", low=1.0, high=170.0)
        if len(self.resolution) != 2:
            raise ConfigFieldError("resolution", f"expected [height, width], got {self.resolution}")
        check_range(self.resolution, "resolution", low=4, high=8192)
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
    """One injected real-world effect and its strength parameters (names per effect; see
    README "Effects"). Per-view values are drawn from these with the run's seed."""

    name: Literal[EFFECT_NAMES] = "exposure"  # type: ignore[valid-type]
    parameters: dict[str, float] = field(default_factory=dict)


@dataclass
class RelightConfig:
    """An extra split of the test cameras rendered under another light (relight test)."""

    views: int = 0
    lighting: LightingConfig = field(default_factory=LightingConfig)

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

    views: int = 0
    # Linear radiance of the card (before exposure): mid-grey keeps the corners and a bright
    # exposure away from both ends of the 8-bit range.
    radiance: float = 0.5

    def __post_init__(self) -> None:
        check_range(self.views, "views", low=0, high=1000)
        check_range(self.radiance, "radiance", low=1e-3, high=1.0)


@dataclass
class CaptureConfig:
    """Views per split; the train/val/test cameras are drawn from one rig, disjoint."""

    cameras: CameraRigConfig = field(default_factory=CameraRigConfig)
    train_views: int = 16
    val_views: int = 2
    test_views: int = 4
    relight: RelightConfig = field(default_factory=RelightConfig)
    flat_field: FlatFieldConfig = field(default_factory=FlatFieldConfig)
    background: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    effects: list[EffectConfig] = field(default_factory=list)
    # own: recon's rasterizer; mitsuba: the path tracer; auto: mitsuba only when a
    # light-transport effect (specular, shadows, interreflection) is requested.
    backend: Literal["auto", "own", "mitsuba"] = "auto"
    mitsuba_spp: int = 64
    write_exr: bool = True
    write_depth_normals: bool = False
    contact_sheet: bool = True

    def __post_init__(self) -> None:
        check_range(self.train_views, "train_views", low=1, high=10000)
        check_range(self.val_views, "val_views", low=0, high=10000)
        check_range(self.test_views, "test_views", low=0, high=10000)
        check_range(self.mitsuba_spp, "mitsuba_spp", low=1, high=65536)
        _check_vector(self.background, "background")
        names = [effect.name for effect in self.effects]
        light_transport = [
            name for name in names if name in ("specular", "shadows", "interreflection")
        ]
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

    steps: int = 400
    views_per_step: int = 4
    # Coarse to fine: the rendering resolution grows through these (capped at the data's),
    # switching at equal fractions of the steps.
    resolutions: list[int] = field(default_factory=lambda: [64, 128, 256])
    learning_rate: float = 0.02
    albedo_learning_rate: float = 0.03
    light_learning_rate: float = 0.02
    large_steps_lambda: float = 20.0
    remesh_every: int = 50
    remesh_until: float = 0.8
    # Target edge length of the remesher, as a fraction of the initial shape's bounding-box
    # diagonal, shrinking geometrically from start to end over the remeshing period.
    edge_length_start: float = 0.04
    edge_length_end: float = 0.012
    mask_weight: float = 1.0
    image_loss: Literal["l1", "log_srgb_l1"] = "l1"
    directional_light: bool = True

    def __post_init__(self) -> None:
        check_range(self.steps, "steps", low=0)
        check_range(self.views_per_step, "views_per_step", low=1)
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
    target_faces: int = 20000

    def __post_init__(self) -> None:
        check_range(self.target_faces, "target_faces", low=4)


@dataclass
class TextureStageConfig:
    """Stage 2: UV texture (trilinear), lighting and vertex positions on a fixed topology."""

    steps: int = 200
    views_per_step: int = 4
    texture_size: int = 512
    learning_rate: float = 0.01
    texture_learning_rate: float = 0.03
    light_learning_rate: float = 0.01
    large_steps_lambda: float = 20.0
    smoothness_weight: float = 0.01
    mask_weight: float = 1.0
    # As fit.geometry.image_loss: 'log_srgb_l1' weighs dark regions as the sRGB metrics do.
    image_loss: Literal["l1", "log_srgb_l1"] = "l1"

    def __post_init__(self) -> None:
        check_range(self.steps, "steps", low=0)
        check_range(self.views_per_step, "views_per_step", low=1)
        check_range(self.texture_size, "texture_size", low=8, high=8192)
        for key in ("learning_rate", "texture_learning_rate", "light_learning_rate"):
            check_range(getattr(self, key), key, low=0.0)
        check_range(self.smoothness_weight, "smoothness_weight", low=0.0)


@dataclass
class FitLightConfig:
    """The fit's light model. frame 'world': the light is fixed in the scene (the default);
    'camera': it is fixed to the camera (OpenCV camera axes), as in turntable captures where the
    object turns under studio lights, so that in the object's frame the light turns with the
    view."""

    frame: Literal["world", "camera"] = "world"


@dataclass
class NormalizeConfig:
    """Recentring and rescaling of a dataset's cameras before the fit (the fit works in the
    normalised frame; meshes and lights are written in the dataset's own frame too).

    enabled: estimate the object's centre and size from the cameras and masks (a coarse carving
        around the cameras' common look-at point) and move it to the origin. null (auto): for
        datasets given with 'data' (photos, published poses), not for the synth stage's own
        (its scenes sit at the origin by construction).
    radius: half the longest side of the object's box in the normalised frame.
    grid: voxels per side of the coarse carving grid.
    image_size: longer side of the masks the coarse carving reads (downsampled).
    up: the scene's up axis for figures: 'auto' (the cameras' mean up), or 'x', 'y', 'z',
        '-x', '-y', '-z' in the dataset's frame.
    """

    enabled: bool | None = None
    radius: float = 1.0
    grid: int = 48
    image_size: int = 128
    up: Literal["auto", "x", "y", "z", "-x", "-y", "-z"] = "auto"

    def __post_init__(self) -> None:
        check_range(self.radius, "radius", low=0.0, low_inclusive=False)
        check_range(self.grid, "grid", low=8, high=256)
        check_range(self.image_size, "image_size", low=16, high=4096)


@dataclass
class DatasetConfig:
    """How a dataset folder (config key 'data', or the synth stage's dataset) is read.

    max_resolution: the longer image side after loading; larger photos are downsampled on load
        (antialiased, intrinsics scaled) with a printed message. None keeps the stored size.
    background_key: for photos without masks or alpha: a linear RGB background colour; pixels
        within background_tolerance of it (max channel difference) are background. None: a
        dataset without masks and alpha is an error.
    holdout_every: datasets without splits (LLFF, COLMAP, plain folders) hold out every N-th
        image as the test split.
    exposure: 'exif' divides every photo by its EXIF exposure (time x ISO / f-number^2)
        relative to the median, a known per-view gain; 'none' uses the pixels as they are.
    """

    max_resolution: int | None = 1024
    background_key: list[float] | None = None
    background_tolerance: float = 0.08
    holdout_every: int = 8
    exposure: Literal["none", "exif"] = "none"
    normalize: NormalizeConfig = field(default_factory=NormalizeConfig)

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

    init: Literal["visual_hull", "icosphere"] = "visual_hull"
    hull_resolution: int = 128
    geometry: GeometryStageConfig = field(default_factory=GeometryStageConfig)
    simplify: SimplifyConfig = field(default_factory=SimplifyConfig)
    texture: TextureStageConfig = field(default_factory=TextureStageConfig)
    checkpoint_every: int = 50
    effects: list[str] = field(default_factory=list)
    light: FitLightConfig = field(default_factory=FitLightConfig)

    def __post_init__(self) -> None:
        check_range(self.hull_resolution, "hull_resolution", low=8, high=512)
        check_range(self.checkpoint_every, "checkpoint_every", low=1)


@dataclass
class RunConfig:
    """A whole run: a name, one seed threaded through every stage, the device, and sections."""

    name: str = "run"
    seed: int = 0
    # An existing dataset folder (NeRF-synthetic or LLFF) to fit instead of synthesising one.
    data: str | None = None
    device: Literal["auto", "cpu", "cuda"] = "auto"
    stages: list[Literal["synth", "fit", "evaluate", "report"]] = field(
        default_factory=lambda: ["synth", "fit", "evaluate", "report"]
    )
    scene: SceneConfig = field(default_factory=SceneConfig)
    capture: CaptureConfig = field(default_factory=CaptureConfig)
    fit: FitConfig = field(default_factory=FitConfig)
    dataset: DatasetConfig = field(default_factory=DatasetConfig)

    def __post_init__(self) -> None:
        if not self.name or any(character in self.name for character in "/\\:"):
            raise ConfigFieldError("name", f"expected a plain folder name, got {self.name!r}")

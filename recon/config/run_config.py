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

    def __post_init__(self) -> None:
        check_range(self.texture_size, "texture_size", low=4, high=8192)


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


@dataclass
class LightingConfig:
    """SH environment (ambient radiance per channel + a sky/ground gradient) plus suns."""

    ambient: list[float] = field(default_factory=lambda: [0.6, 0.6, 0.6])
    sky_gradient: float = 0.2
    suns: list[SunConfig] = field(default_factory=lambda: [SunConfig()])

    def __post_init__(self) -> None:
        if len(self.ambient) != 3:
            raise ConfigFieldError("ambient", f"expected 3 values, got {len(self.ambient)}")
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


@dataclass
class CaptureConfig:
    """Views per split; the train/val/test cameras are drawn from one rig, disjoint."""

    cameras: CameraRigConfig = field(default_factory=CameraRigConfig)
    train_views: int = 16
    val_views: int = 2
    test_views: int = 4
    background: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    write_exr: bool = True
    write_depth_normals: bool = False
    contact_sheet: bool = True

    def __post_init__(self) -> None:
        check_range(self.train_views, "train_views", low=1, high=10000)
        check_range(self.val_views, "val_views", low=0, high=10000)
        check_range(self.test_views, "test_views", low=0, high=10000)
        if len(self.background) != 3:
            raise ConfigFieldError("background", f"expected 3 values, got {self.background}")


@dataclass
class RunConfig:
    """A whole run: a name, one seed threaded through every stage, the device, and sections."""

    name: str = "run"
    seed: int = 0
    device: Literal["auto", "cpu", "cuda"] = "auto"
    stages: list[Literal["synth"]] = field(default_factory=lambda: ["synth"])
    scene: SceneConfig = field(default_factory=SceneConfig)
    capture: CaptureConfig = field(default_factory=CaptureConfig)

    def __post_init__(self) -> None:
        if not self.name or any(character in self.name for character in "/\\:"):
            raise ConfigFieldError("name", f"expected a plain folder name, got {self.name!r}")

"""The second render backend: Mitsuba 3 path tracing of the same scene description.

recon's own Renderer (the default backend) shades Lambertian albedo under an SH environment and
directional lights with no visibility at all: no cast shadows, no interreflection (with
``capture.backend: own`` it shades the specular effect with its split-sum model,
data_synth/material.py).
The light-transport effects of the world (``data_synth/effects/light_transport.py``) need those,
so they render the same mesh, cameras and lighting with Mitsuba instead. Without any
light-transport effect the reference render is recon's own Renderer; on a convex, diffuse scene
lit directly the two agree (tests/data_synth/test_mitsuba_backend.py measures the PSNR).

Conventions found and verified by the tests (recon's side first):

- Cameras. recon: OpenCV axes (x right, y down, z forward), pixel centres at i + 0.5, row 0 at
  the top. Mitsuba's ``perspective`` sensor looks along its local +z with +y up and +x pointing
  LEFT in the image, so ``to_world = inverse(world_to_cam) @ diag(-1, -1, 1, 1)``. The film's
  sample position (0, 0) is the top-left corner of the image, as in recon. fov is taken along x
  from fx; a principal point off the centre becomes ``principal_point_offset_x/y`` =
  ((W / 2 - cx) / W, (H / 2 - cy) / H), in fractions of the film. Square pixels only (fx = fy,
  no skew): Mitsuba's pinhole has a single field of view.
- Environment. Mitsuba's ``envmap`` looks up a direction d (toward the environment, in its local
  frame, +y up) at u = atan2(d_x, -d_z) / (2 pi) (wrapped to [0, 1)), v = acos(d_y) / pi; the
  bitmap is interpolated bilinearly with rows at v = i / (h - 1) (row 0 is the +y pole, the last
  row the -y pole, unlike texel-centred maps) and columns at u = (j + 1/2) / w. The envmap gets
  ``to_world`` = (local x -> world z, y -> y, z -> world -x), so that column j looks along
  azimuth phi = 2 pi (j + 1/2) / w with direction (sin theta cos phi, cos theta,
  sin theta sin phi): data_synth.environment's convention. The SH radiance is evaluated at
  exactly those directions (recon's environment up to bilinear interpolation error), and an
  equirectangular map in that convention (texel centres at theta = pi (i + 1/2) / h) is
  resampled onto the pole-including rows.
- Texture coordinates. recon's uv (0, 0) is the top-left of the texture image with v growing
  downwards; Mitsuba's ``bitmap`` texture uses the same origin (its OBJ loader flips v on load for
  that reason), so uvs pass through unchanged; texel centres are at (j + 1/2) / w in both.
- Directional light. recon's ``irradiance`` is Mitsuba's ``directional`` ``irradiance`` (power
  per unit area normal to the light); Mitsuba's ``direction`` is the direction of travel, i.e.
  ``-direction_to_light``. A point light's intensity is Mitsuba's ``point`` ``intensity``; a
  point light with an emitter normal (recon's one-sided cosine lobe) becomes a tiny one-sided
  rectangle of radiance intensity / area.
- World lighting. Given data_synth.scene's WorldLighting (``.lighting``, ``.environment_map``,
  ``.area_lights``), Mitsuba renders what recon approximates: the full environment map (recon
  shades with its SH projection, which build_lighting adds to the SH coefficients, so that
  projection is subtracted and the rest of the SH, e.g. ambient and gradient, stays) and the
  true rectangular area lights (recon shades them as point lights at their centres, which are
  left out here).
- Output. ``hdrfilm`` with a box reconstruction filter of radius 1/2 averages the samples over
  each pixel's area, and with ``pixel_format='rgba'`` and hidden emitters the colour channels are
  the average of radiance over the pixel (0 where a sample misses the object), i.e. colour
  premultiplied by coverage over a black background, and alpha is the coverage: the same
  quantities as recon's antialiased RenderOutput.color / .alpha.

Shadows cannot be switched off in a path tracer (every light sample is a visibility test), so
``MitsubaOptions.shadows=False`` is refused: the shadow-free reference is recon's own Renderer.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Any

import numpy as np
import torch

from recon.camera.cameras import Cameras, rigid_inverse
from recon.errors import ReconError
from recon.mesh.mesh import Mesh, vertex_normals
from recon.render.shading import Lighting, sh_basis

PREFERRED_VARIANT = "llvm_ad_rgb"
FALLBACK_VARIANT = "scalar_rgb"
INTEGRATORS = ("path", "direct")
MATERIALS = ("diffuse", "specular", "roughplastic")
SAMPLERS = ("independent", "stratified", "multijitter", "orthogonal", "ldsampler")

# Mitsuba's camera: +x left, +y up, +z forward; OpenCV's: +x right, +y down, +z forward.
_OPENCV_TO_MITSUBA_CAMERA = np.diag([-1.0, -1.0, 1.0, 1.0])
# The envmap's local frame to world: Mitsuba's azimuth u = atan2(x, -z) / (2 pi) becomes
# data_synth.environment's phi = atan2(z, x) (local x -> world z, y -> y, z -> world -x).
ENVIRONMENT_TO_WORLD = np.array(
    [[0.0, 0.0, -1.0, 0.0], [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
)
# A point light with an emitter normal becomes a square of this edge (world units): small
# enough to act as a point, large enough for single-precision ray hits.
_POINT_EMITTER_SIZE = 1e-3
# Envmap rows for the smooth SH environment: bilinear interpolation of a band-2 function on a
# 64 x 128 grid is accurate to ~1e-3 relative, far below Monte Carlo noise.
_ENVIRONMENT_ROWS = 64
# A disk sun should span at least this many envmap rows across its diameter, so that its edge is
# resolved (the rows then grow up to _MAXIMUM_ENVIRONMENT_ROWS).
_SUN_ROWS_PER_DIAMETER = 8
_MAXIMUM_ENVIRONMENT_ROWS = 1024
# Samples traced at once by one render call (memory: a few hundred bytes per sample in flight).
_MAXIMUM_SAMPLES_PER_PASS = 2**22


@dataclass(frozen=True)
class DiskSun:
    """A distant light of finite angular size: a uniform disk added to the environment map.

    direction_to_light: world direction toward the sun's centre (normalised here).
    angular_diameter_deg: apparent diameter of the disk, in degrees (soft-shadow penumbra width).
    irradiance: RGB irradiance it gives a surface facing it (like DirectionalLight.irradiance).

    Being part of the environment it is never in the frame as geometry (hidden with the rest of
    the environment when hide_emitters is on) and costs nothing to intersect.
    """

    direction_to_light: tuple[float, float, float]
    angular_diameter_deg: float
    irradiance: tuple[float, float, float]


@dataclass(frozen=True)
class MitsubaOptions:
    """How Mitsuba renders the scene.

    spp: samples per pixel.
    max_depth: longest path in segments (Mitsuba's meaning): 2 = direct light only (camera ray
        plus one bounce toward the lights), larger adds diffuse interreflection, -1 unbounded.
    integrator: 'path' (default) or 'direct' (direct light only; then max_depth must be 2).
    material: 'diffuse' (Lambertian albedo, like recon), 'specular' (a GGX microfacet
        specular lobe with Schlick Fresnel over the diffuse albedo: Mitsuba's ``principled``,
        with ``metalness`` as its metallic: 1 is a GGX conductor whose F0 is the albedo) or
        'roughplastic' (Mitsuba's ``roughplastic``: a GGX dielectric coating with exact
        Fresnel over a diffuse base, whose diffuse part the coating's transmittance darkens).
    roughness: perceptual roughness r of the specular lobe (GGX alpha = r^2).
    specular_level: s in [0, 1]: normal-incidence reflectance 0.08 s (0.5 -> 4%, ior 1.5);
        roughplastic's interior ior is the one with that reflectance (s > 0).
    metalness: principled's metallic in [0, 1] ('specular' only).
    roughness_map: a spatially varying perceptual roughness [h, w] in [0.01, 1] on the mesh's
        UVs (bilinear, wrapped like the albedo), replacing roughness: principled's roughness
        texture ('specular' only; roughplastic takes a single alpha). None: roughness.
    albedo_scale: multiplies the albedo (clipped to 1): stronger interreflection.
    area_lights: extra one-sided rectangle emitters (soft shadows): objects with center [3],
        normal [3] (the emitting side), edge_u [3], edge_v [3] (full edge vectors) and
        radiance [3], e.g. data_synth.scene.AreaLight. They are geometry: a camera that has one
        in view sees an opaque black quad with alpha 1 (a DiskSun never is).
    suns: disk suns of finite angular size added to the environment (soft shadows).
    include_environment, include_directional: keep the lighting's environment (SH and map) and
        its directional lights (the shadows effect replaces the latter by its disk sun).
    hide_emitters: environment and emitters invisible to camera rays (background black, alpha 0).
    shadows: must stay True: Mitsuba traces visibility for every light sample and cannot leave it
        out. The shadow-free reference is recon's own Renderer.
    seed: base seed (view k, pass p renders with (seed * 65536 + k) * 256 + p).
    sampler: Mitsuba sampler plugin ('independent' by default).
    variant: Mitsuba variant, or None for pick_variant().
    """

    spp: int = 64
    max_depth: int = 2
    integrator: str = "path"
    material: str = "diffuse"
    roughness: float = 0.3
    specular_level: float = 0.5
    metalness: float = 0.0
    # Not compared: options with maps compare by their scalars (tensors have no single truth).
    roughness_map: torch.Tensor | None = field(default=None, compare=False)
    albedo_scale: float = 1.0
    area_lights: tuple[Any, ...] = ()
    suns: tuple[DiskSun, ...] = ()
    include_environment: bool = True
    include_directional: bool = True
    hide_emitters: bool = True
    shadows: bool = True
    seed: int = 0
    sampler: str = "independent"
    variant: str | None = None

    def validate(self) -> None:
        """Raise ReconError naming the option when a value is out of range."""
        if isinstance(self.spp, bool) or not isinstance(self.spp, int) or self.spp < 1:
            raise ReconError(f"mitsuba options: spp: expected an int >= 1, got {self.spp!r}")
        if (
            isinstance(self.max_depth, bool)
            or not isinstance(self.max_depth, int)
            or not (self.max_depth == -1 or self.max_depth >= 1)
        ):
            raise ReconError(
                f"mitsuba options: max_depth: expected -1 or an int >= 1 (2 = direct light only), "
                f"got {self.max_depth!r}"
            )
        _check_choice("integrator", self.integrator, INTEGRATORS)
        _check_choice("material", self.material, MATERIALS)
        _check_choice("sampler", self.sampler, SAMPLERS)
        if self.integrator == "direct" and self.max_depth != 2:
            raise ReconError(
                "mitsuba options: integrator 'direct' renders direct light only (max_depth 2); "
                f"got max_depth={self.max_depth}; use integrator 'path' for interreflection"
            )
        if not 0.01 <= float(self.roughness) <= 1.0:
            raise ReconError(
                f"mitsuba options: roughness: expected a value in [0.01, 1], got {self.roughness}"
            )
        if not 0.0 <= float(self.specular_level) <= 1.0:
            raise ReconError(
                "mitsuba options: specular_level: expected a value in [0, 1], "
                f"got {self.specular_level}"
            )
        if not 0.0 <= float(self.metalness) <= 1.0:
            raise ReconError(
                f"mitsuba options: metalness: expected a value in [0, 1], got {self.metalness}"
            )
        if self.roughness_map is not None:
            _check_roughness_map(self.roughness_map, self.material)
        if self.material == "roughplastic" and float(self.metalness) != 0.0:
            raise ReconError(
                "mitsuba options: metalness: material 'roughplastic' is a dielectric (metalness "
                f"0), got {self.metalness}; use material 'specular' for a conductor"
            )
        if self.material == "roughplastic" and not float(self.specular_level) > 0.0:
            raise ReconError(
                "mitsuba options: specular_level: material 'roughplastic' needs a coating "
                f"(specular_level > 0), got {self.specular_level}"
            )
        if not 0.0 < float(self.albedo_scale) <= 2.0:
            raise ReconError(
                f"mitsuba options: albedo_scale: expected a value in (0, 2], got {self.albedo_scale}"
            )
        if not self.shadows:
            raise ReconError(
                "mitsuba options: shadows=False is not possible: a path tracer tests visibility "
                "for every light sample. The shadow-free reference is recon's own Renderer "
                "(recon.render.renderer.Renderer), the default backend of data_synth"
            )
        for index, light in enumerate(self.area_lights):
            _rectangle_frame(light, f"mitsuba options: area_lights[{index}]")
        for index, sun in enumerate(self.suns):
            if not 0.1 <= float(sun.angular_diameter_deg) <= 90.0:
                raise ReconError(
                    f"mitsuba options: suns[{index}].angular_diameter_deg: expected a value in "
                    f"[0.1, 90], got {sun.angular_diameter_deg}"
                )
            if len(sun.irradiance) != 3 or min(sun.irradiance) < 0:
                raise ReconError(
                    f"mitsuba options: suns[{index}].irradiance: expected 3 values >= 0, "
                    f"got {sun.irradiance}"
                )
            if float(np.linalg.norm(sun.direction_to_light)) < 1e-8:
                raise ReconError(
                    f"mitsuba options: suns[{index}].direction_to_light: expected a nonzero vector"
                )


def _check_roughness_map(roughness_map: Any, material: str) -> None:
    """ReconError unless roughness_map is a finite [h, w] tensor in [0.01, 1] for 'specular'."""
    if not isinstance(roughness_map, torch.Tensor) or roughness_map.ndim != 2:
        shape = tuple(roughness_map.shape) if isinstance(roughness_map, torch.Tensor) else None
        raise ReconError(
            f"mitsuba options: roughness_map: expected a tensor [h, w], got "
            f"{shape or type(roughness_map).__name__}"
        )
    low, high = float(roughness_map.min()), float(roughness_map.max())
    if not (0.01 <= low and high <= 1.0):
        raise ReconError(
            f"mitsuba options: roughness_map: expected values in [0.01, 1], got [{low}, {high}]"
        )
    if material != "specular":
        raise ReconError(
            "mitsuba options: roughness_map: needs material 'specular' (principled's roughness "
            f"texture), got {material!r}"
            + ("; roughplastic takes a single alpha" if material == "roughplastic" else "")
        )


def _check_choice(key: str, value: object, choices: Sequence[str]) -> None:
    if value not in choices:
        raise ReconError(
            f"mitsuba options: {key}: expected one of {', '.join(choices)}, got {value!r}"
        )


# --------------------------------------------------------------------------------------------
# Variant
# --------------------------------------------------------------------------------------------


def _import_mitsuba() -> Any:
    try:
        import mitsuba
    except ImportError as error:
        raise ReconError(
            "the Mitsuba backend needs the 'mitsuba' package: pip install mitsuba (or "
            "pip install -e .[mitsuba]); its llvm variants also need LLVM at run time "
            f"(Debian/Ubuntu: apt-get install libllvm19). Import failed with: {error}"
        ) from error
    return mitsuba


def pick_variant() -> str:
    """Select and return the Mitsuba variant: 'llvm_ad_rgb', else 'scalar_rgb' with a warning.

    llvm_ad_rgb vectorises over pixels and threads; it needs a shared LLVM library (Debian's
    libllvm19). scalar_rgb always works but traces one ray at a time per thread (much slower).
    Raises ReconError when mitsuba is not installed.
    """
    mitsuba = _import_mitsuba()
    try:
        mitsuba.set_variant(PREFERRED_VARIANT)
        return PREFERRED_VARIANT
    except Exception as error:  # Mitsuba raises ImportError/AttributeError/RuntimeError here.
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
    try:
        mitsuba.set_variant(FALLBACK_VARIANT)
    except Exception as error:
        raise ReconError(
            f"mitsuba is installed but neither {PREFERRED_VARIANT} nor {FALLBACK_VARIANT} can be "
            f"selected ({error}); reinstall with pip install mitsuba"
        ) from error
    warnings.warn(
        f"Mitsuba variant {PREFERRED_VARIANT} is unavailable ({reason}); falling back to "
        f"{FALLBACK_VARIANT}, which is much slower. Install LLVM (Debian/Ubuntu: apt-get install "
        "libllvm19) to use the vectorised variant.",
        RuntimeWarning,
        stacklevel=2,
    )
    return FALLBACK_VARIANT


def _select_variant(variant: str | None) -> Any:
    """Set the requested (or picked) variant and return the mitsuba module."""
    mitsuba = _import_mitsuba()
    if variant is None:
        pick_variant()
    elif mitsuba.variant() != variant:
        try:
            mitsuba.set_variant(variant)
        except Exception as error:
            raise ReconError(
                f"mitsuba options: variant: cannot select {variant!r} ({error}); available: "
                f"{', '.join(mitsuba.variants())}"
            ) from error
    return mitsuba


# --------------------------------------------------------------------------------------------
# Scene conversion
# --------------------------------------------------------------------------------------------


def camera_to_world_mitsuba(world_to_cam: torch.Tensor) -> np.ndarray:
    """Mitsuba sensor to_world matrices [B, 4, 4] (float64) from OpenCV world_to_cam [B, 4, 4]."""
    cam_to_world = rigid_inverse(world_to_cam.detach().double().cpu()).numpy()
    return cam_to_world @ _OPENCV_TO_MITSUBA_CAMERA


def sensor_dict(cameras: Cameras, index: int, spp: int, sampler: str) -> dict:
    """The ``perspective`` sensor dictionary for camera ``index`` (raises for non-square pixels)."""
    mitsuba = _import_mitsuba()
    height, width = cameras.image_size
    intrinsics = cameras.intrinsics[index].detach().double().cpu()
    focal_x, focal_y = float(intrinsics[0, 0]), float(intrinsics[1, 1])
    center_x, center_y = float(intrinsics[0, 2]), float(intrinsics[1, 2])
    if abs(focal_x - focal_y) > 1e-4 * focal_x or abs(float(intrinsics[0, 1])) > 1e-6 * focal_x:
        raise ReconError(
            f"cameras.intrinsics[{index}]: the Mitsuba backend needs square pixels without skew "
            f"(fx = fy, skew 0); got fx={focal_x:.6g}, fy={focal_y:.6g}, "
            f"skew={float(intrinsics[0, 1]):.3g}"
        )
    fov_x_deg = math.degrees(2 * math.atan(0.5 * width / focal_x))
    to_world = camera_to_world_mitsuba(cameras.world_to_cam[index : index + 1])[0]
    return {
        "type": "perspective",
        "fov": fov_x_deg,
        "fov_axis": "x",
        # Mitsuba shifts the film sample position by these fractions of the film before it maps
        # it through the centred projection: shift by the centre's offset from the principal point.
        "principal_point_offset_x": (0.5 * width - center_x) / width,
        "principal_point_offset_y": (0.5 * height - center_y) / height,
        "near_clip": float(cameras.near),
        "far_clip": float(cameras.far),
        "to_world": mitsuba.ScalarTransform4f(to_world.tolist()),
        "film": {
            "type": "hdrfilm",
            "width": width,
            "height": height,
            "pixel_format": "rgba",
            "component_format": "float32",
            # Box of radius 1/2: every sample lands in its own pixel, an area average like
            # recon's antialiased coverage.
            "rfilter": {"type": "box"},
            "sample_border": False,
        },
        "sampler": {"type": sampler, "sample_count": spp},
    }


def environment_directions(rows: int, columns: int) -> np.ndarray:
    """World directions [rows, columns, 3] at the samples of the envmap bitmap (with
    ENVIRONMENT_TO_WORLD).

    Row i lies at polar angle theta = pi i / (rows - 1) from +y (both poles are rows), column j
    at azimuth phi = 2 pi (j + 1/2) / columns; direction (sin theta cos phi, cos theta,
    sin theta sin phi), as in data_synth.environment.
    """
    theta = np.pi * np.arange(rows) / (rows - 1)
    phi = 2 * np.pi * (np.arange(columns) + 0.5) / columns
    theta, phi = np.meshgrid(theta, phi, indexing="ij")
    return np.stack(
        [np.sin(theta) * np.cos(phi), np.cos(theta), np.sin(theta) * np.sin(phi)], axis=-1
    )


def environment_solid_angles(rows: int, columns: int) -> np.ndarray:
    """Solid angle [rows, columns] each envmap sample stands for (trapezoid rule in theta)."""
    theta = np.pi * np.arange(rows) / (rows - 1)
    weights = np.sin(theta) * (np.pi / (rows - 1)) * (2 * np.pi / columns)
    return np.repeat(weights[:, None], columns, axis=1)


def resample_equirectangular(image: np.ndarray, rows: int, columns: int) -> np.ndarray:
    """A texel-centred equirectangular map [h, w, C] (data_synth.environment) resampled to the
    envmap grid [rows, columns, C] (poles on rows), bilinear in (theta, phi), wrapping in phi.

    With rows = 2 h + 1 and columns = w every other row is an original texel row and the
    columns coincide, so nothing is blurred beyond Mitsuba's own bilinear lookup.
    """
    height, width = image.shape[:2]
    source_row = np.clip(np.arange(rows) / (rows - 1) * height - 0.5, 0.0, height - 1.0)
    source_column = (np.arange(columns) + 0.5) / columns * width - 0.5
    row_low = np.floor(source_row).astype(np.int64)
    row_high = np.minimum(row_low + 1, height - 1)
    row_weight = (source_row - row_low)[:, None, None]
    column_low = np.floor(source_column).astype(np.int64)
    column_weight = (source_column - column_low)[None, :, None]
    column_high = (column_low + 1) % width
    column_low = column_low % width
    top = (
        image[row_low][:, column_low] * (1 - column_weight)
        + image[row_low][:, column_high] * column_weight
    )
    bottom = (
        image[row_high][:, column_low] * (1 - column_weight)
        + image[row_high][:, column_high] * column_weight
    )
    return top * (1 - row_weight) + bottom * row_weight


def environment_bitmap(
    sh_coefficients: torch.Tensor | None,
    suns: Sequence[DiskSun] = (),
    environment_map: torch.Tensor | None = None,
    rows: int | None = None,
) -> np.ndarray:
    """The envmap image [rows, columns, 3] (float32 linear radiance): SH light + map + suns.

    sh_coefficients: [9, 3] radiance SH (recon's convention), or None.
    environment_map: [h, w, 3] equirectangular radiance (data_synth.environment), or None.
    rows: default 64, more for a small sun (8 rows per diameter, up to 1024); with a map
        2 h m + 1 rows and an odd multiple of its width as columns, so that its texel centres
        fall on envmap samples. Columns are 2 (rows - 1) otherwise.
    Negative SH radiance (a gradient steeper than the ambient allows) is clipped to 0 with a
    warning: an emitter cannot be negative, and recon's irradiance then differs.
    """
    if rows is None:
        rows = _ENVIRONMENT_ROWS
        for sun in suns:
            needed = _SUN_ROWS_PER_DIAMETER * 180.0 / float(sun.angular_diameter_deg)
            rows = max(rows, min(_MAXIMUM_ENVIRONMENT_ROWS, int(math.ceil(needed))))
        if environment_map is not None:
            # rows - 1 a multiple of 2 h puts a row on every texel centre theta = pi (i + 1/2) / h
            # (and one on every texel edge).
            spacing = 2 * environment_map.shape[0]
            rows = spacing * max(1, math.ceil((rows - 1) / spacing)) + 1
    columns = 2 * (rows - 1)
    if environment_map is not None:
        # An odd multiple of the map's width puts a column on every map texel centre; columns at
        # most twice as far apart as rows (the map's own 2:1 aspect) are enough.
        width = environment_map.shape[1]
        multiple = max(1, math.ceil((rows - 1) / width))
        columns = width * (multiple if multiple % 2 == 1 else multiple + 1)
    directions = environment_directions(rows, columns)
    image = np.zeros((rows, columns, 3), dtype=np.float64)
    if sh_coefficients is not None:
        if tuple(sh_coefficients.shape) != (9, 3):
            raise ReconError(
                "lighting.sh_coefficients: the Mitsuba backend needs shape [9, 3] (RGB), got "
                f"{tuple(sh_coefficients.shape)}"
            )
        basis = sh_basis(torch.from_numpy(directions)).numpy()
        image = basis @ sh_coefficients.detach().double().cpu().numpy()
        lowest = float(image.min())
        if lowest < -1e-5 * max(float(np.abs(image).max()), 1e-12):
            warnings.warn(
                f"SH environment has negative radiance (min {lowest:.4g}); clipped to 0 for "
                "Mitsuba, so its irradiance differs from recon's",
                RuntimeWarning,
                stacklevel=2,
            )
        image = np.clip(image, 0.0, None)
    if environment_map is not None:
        values = environment_map.detach().double().cpu().numpy()
        if values.ndim != 3 or values.shape[-1] != 3:
            raise ReconError(
                f"environment_map: expected an [h, w, 3] radiance map, got {values.shape}"
            )
        if not np.isfinite(values).all() or values.min() < 0:
            raise ReconError("environment_map: expected finite radiance >= 0")
        image = image + resample_equirectangular(values, rows, columns)
    solid_angles = environment_solid_angles(rows, columns)
    texel_angle = math.pi / (rows - 1)
    for sun in suns:
        axis = np.asarray(sun.direction_to_light, dtype=np.float64)
        axis = axis / np.linalg.norm(axis)
        cosine = directions @ axis
        angle = np.arccos(np.clip(cosine, -1.0, 1.0))
        radius = math.radians(float(sun.angular_diameter_deg)) / 2
        # Coverage ramps over one texel at the rim: the disk's area is kept while aliasing is not.
        coverage = np.clip((radius - angle) / texel_angle + 0.5, 0.0, 1.0)
        # Normalise on the grid Mitsuba integrates, so the irradiance facing the sun is exact.
        facing_irradiance = float((coverage * np.clip(cosine, 0.0, None) * solid_angles).sum())
        if facing_irradiance <= 0:
            raise ReconError(
                f"disk sun of {sun.angular_diameter_deg} degrees is too small for an envmap of "
                f"{rows} rows"
            )
        irradiance = np.asarray(sun.irradiance, dtype=np.float64)
        image = image + coverage[..., None] * irradiance / facing_irradiance
    return image.astype(np.float32)


def environment_dict(
    sh_coefficients: torch.Tensor | None,
    suns: Sequence[DiskSun] = (),
    environment_map: torch.Tensor | None = None,
) -> dict:
    """The ``envmap`` emitter dictionary of environment_bitmap(...) in world orientation."""
    mitsuba = _import_mitsuba()
    return {
        "type": "envmap",
        "bitmap": mitsuba.Bitmap(environment_bitmap(sh_coefficients, suns, environment_map)),
        "to_world": mitsuba.ScalarTransform4f(ENVIRONMENT_TO_WORLD.tolist()),
    }


def _split_uv_seams(mesh: Mesh) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Mitsuba keeps one uv per vertex: split vertices where a vertex has several uvs.

    Returns (source vertex per new vertex [V'], faces [F, 3] into the new vertices, uvs [V', 2]
    or None).
    """
    faces = mesh.faces.detach().cpu().numpy().astype(np.int64)
    if mesh.uvs is None or mesh.uv_faces is None:
        return np.arange(mesh.verts.shape[0]), faces, None
    uv_faces = mesh.uv_faces.detach().cpu().numpy().astype(np.int64)
    pairs = np.stack([faces.reshape(-1), uv_faces.reshape(-1)], axis=1)
    unique_pairs, inverse = np.unique(pairs, axis=0, return_inverse=True)
    uvs = mesh.uvs.detach().cpu().numpy().astype(np.float32)[unique_pairs[:, 1]]
    return unique_pairs[:, 0], inverse.reshape(faces.shape), uvs


def _albedo_texture(mesh: Mesh, albedo_scale: float) -> tuple[dict, np.ndarray | None]:
    """The albedo texture dictionary and, for vertex colours, the colours [V, 3] to attach."""
    mitsuba = _import_mitsuba()
    if mesh.texture is not None and mesh.uvs is not None:
        texture = mesh.texture.detach().float().cpu().numpy()
        if texture.ndim != 3 or texture.shape[-1] != 3:
            raise ReconError(
                f"mesh.texture: the Mitsuba backend needs [h, w, 3], got {texture.shape}"
            )
        texture = np.ascontiguousarray(np.clip(texture * albedo_scale, 0.0, 1.0), np.float32)
        bitmap = mitsuba.Bitmap(texture, pixel_format=mitsuba.Bitmap.PixelFormat.RGB)
        # raw: the values are linear albedo already (no sRGB decoding, no spectral upsampling);
        # wrap like recon's default 'wrap' boundary.
        return {
            "type": "bitmap",
            "bitmap": bitmap,
            "raw": True,
            "filter_type": "bilinear",
            "wrap_mode": "repeat",
        }, None
    if mesh.vertex_colors is not None:
        colors = mesh.vertex_colors.detach().double().cpu().numpy()
        if colors.ndim != 2 or colors.shape[-1] != 3:
            raise ReconError(
                f"mesh.vertex_colors: the Mitsuba backend needs [V, 3], got {colors.shape}"
            )
        colors = np.clip(colors * albedo_scale, 0.0, 1.0)
        return {"type": "mesh_attribute", "name": "vertex_color"}, colors
    return {"type": "rgb", "value": [min(1.0, 0.5 * albedo_scale)] * 3}, None


def plastic_ior(specular_level: float) -> float:
    """The interior index of refraction whose normal-incidence reflectance is 0.08 x level
    (F0 = ((n - 1) / (n + 1))^2; level 0.5 gives 1.5)."""
    root = math.sqrt(0.08 * float(specular_level))
    return (1 + root) / (1 - root)


def _roughness_texture(options: MitsubaOptions) -> float | dict:
    """principled's roughness: the scalar, or a raw (linear) bitmap of the roughness map on the
    mesh's UVs, filtered and wrapped as the albedo bitmap is."""
    if options.roughness_map is None:
        return float(options.roughness)
    mitsuba = _import_mitsuba()
    values = options.roughness_map.detach().float().cpu().numpy()[..., None]
    return {
        "type": "bitmap",
        "bitmap": mitsuba.Bitmap(np.ascontiguousarray(values, np.float32)),
        "raw": True,
        "filter_type": "bilinear",
        "wrap_mode": "repeat",
    }


def _bsdf_dict(albedo: dict, options: MitsubaOptions) -> dict:
    if options.material == "diffuse":
        inner = {"type": "diffuse", "reflectance": albedo}
    elif options.material == "roughplastic":
        inner = {
            "type": "roughplastic",
            "distribution": "ggx",
            "alpha": float(options.roughness) ** 2,
            "int_ior": plastic_ior(options.specular_level),
            "ext_ior": 1.0,
            "diffuse_reflectance": albedo,
            "nonlinear": False,
        }
    else:
        # principled with metallic 0: Burley's diffuse (Lambertian at normal incidence, within
        # ~5% of it up to 80 degrees) under a GGX lobe with Schlick Fresnel. Mitsuba's
        # roughplastic would darken the diffuse part by the coating's transmittance (-17% at
        # 60 degrees), moving the albedo as well as adding a highlight.
        inner = {
            "type": "principled",
            "base_color": albedo,
            "metallic": float(options.metalness),
            "roughness": _roughness_texture(options),
            "specular": float(options.specular_level),
        }
    # Two-sided: thin or open surfaces reflect on both sides, as recon shades every face.
    return {"type": "twosided", "bsdf": inner}


def mesh_to_mitsuba(mesh: Mesh, options: MitsubaOptions, name: str = "mesh") -> Any:
    """An in-memory ``mi.Mesh`` with recon's area-weighted vertex normals, uvs and albedo BSDF."""
    mitsuba = _import_mitsuba()
    import drjit

    source, faces, uvs = _split_uv_seams(mesh)
    verts = mesh.verts.detach().float().cpu()
    # recon shades with interpolated area-weighted vertex normals; Mitsuba would recompute
    # angle-weighted ones, so hand it recon's (computed before the seam split: smooth across).
    normals = vertex_normals(verts, mesh.faces.detach().cpu()).numpy()[source]
    positions = verts.numpy()[source]
    albedo, colors = _albedo_texture(mesh, float(options.albedo_scale))
    if options.roughness_map is not None and (mesh.uvs is None or mesh.uv_faces is None):
        raise ReconError(
            "mitsuba options: roughness_map: the mesh has no UVs to look the roughness map up"
        )
    if options.material == "roughplastic" and colors is not None:
        # roughplastic weighs its lobes by the albedo's mean, which a vertex attribute lacks.
        raise ReconError(
            "mitsuba options: material 'roughplastic' needs a textured mesh (uvs + texture), "
            "got vertex colours; use material 'specular' or a texture"
        )
    properties = mitsuba.Properties()
    properties["bsdf"] = mitsuba.load_dict(_bsdf_dict(albedo, options))
    result = mitsuba.Mesh(
        name,
        vertex_count=positions.shape[0],
        face_count=faces.shape[0],
        props=properties,
        has_vertex_normals=True,
        has_vertex_texcoords=uvs is not None,
    )
    parameters = mitsuba.traverse(result)
    parameters["vertex_positions"] = drjit.ravel(mitsuba.TensorXf(positions.astype(np.float32)))
    parameters["vertex_normals"] = drjit.ravel(mitsuba.TensorXf(normals.astype(np.float32)))
    parameters["faces"] = drjit.ravel(mitsuba.TensorXu(faces.astype(np.uint32)))
    if uvs is not None:
        parameters["vertex_texcoords"] = drjit.ravel(mitsuba.TensorXf(uvs))
    parameters.update()
    if colors is not None:
        # The variant's flat float storage (a JIT array, or drjit.scalar.ArrayXf in scalar_rgb).
        storage = type(parameters["vertex_positions"])
        result.add_attribute(
            "vertex_color", 3, storage(colors[source].astype(np.float32).reshape(-1))
        )
    return result


def _vector(value: Any, where: str) -> np.ndarray:
    """A finite float64 3-vector from a tensor or sequence, or ReconError naming where."""
    if isinstance(value, torch.Tensor):
        value = value.detach().double().cpu().numpy()
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        array = np.zeros(0)
    if array.shape != (3,) or not np.isfinite(array).all():
        raise ReconError(f"{where}: expected 3 finite values, got {value!r}")
    return array


def _rectangle_frame(light: Any, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(to_world [4, 4], radiance [3]) of a one-sided rectangle light.

    light: center, normal (emitting side), edge_u, edge_v (full edge vectors), radiance.
    Mitsuba's ``rectangle`` spans [-1, 1]^2 in its local xy plane and emits toward local +z, so
    to_world = [edge_u / 2, edge_v / 2, normal, center], with edge_v flipped if needed to keep
    the frame right-handed (a mirrored frame would flip the emitting side).
    """
    keys = ("center", "normal", "edge_u", "edge_v", "radiance")
    if not all(hasattr(light, key) for key in keys):
        raise ReconError(
            f"{where}: expected an area light with center, normal, edge_u, edge_v and radiance "
            f"(data_synth.scene.AreaLight), got {type(light).__name__}"
        )
    center, normal, edge_u, edge_v, radiance = (
        _vector(getattr(light, key), f"{where}.{key}") for key in keys
    )
    normal_length = np.linalg.norm(normal)
    cross = np.cross(edge_u, edge_v)
    if normal_length < 1e-12 or np.linalg.norm(cross) < 1e-12:
        raise ReconError(f"{where}: expected a nonzero normal and non-parallel nonzero edges")
    if (radiance < 0).any():
        raise ReconError(f"{where}.radiance: expected values >= 0, got {radiance.tolist()}")
    normal = normal / normal_length
    if float(cross @ normal) < 0:
        edge_v = -edge_v
    to_world = np.eye(4)
    to_world[:3, 0] = edge_u / 2
    to_world[:3, 1] = edge_v / 2
    to_world[:3, 2] = normal
    to_world[:3, 3] = center
    return to_world, radiance


def _rectangle_dict(to_world: np.ndarray, radiance: np.ndarray) -> dict:
    mitsuba = _import_mitsuba()
    return {
        "type": "rectangle",
        "to_world": mitsuba.ScalarTransform4f(to_world.tolist()),
        # Black: the light itself reflects nothing back into the scene.
        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}},
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": radiance.tolist()}},
    }


def _point_light_dict(light: Any, index: int) -> dict:
    """Mitsuba emitter for recon's PointLight: ``point`` when isotropic, else a tiny one-sided
    square of radiance intensity / area (intensity * max(0, cos) toward its normal)."""
    where = f"lighting.points[{index}]"
    position = _vector(light.position, f"{where}.position")
    intensity = _vector(light.intensity, f"{where}.intensity")
    if (intensity < 0).any():
        raise ReconError(f"{where}.intensity: expected values >= 0, got {intensity.tolist()}")
    if light.emitter_normal is None:
        return {
            "type": "point",
            "position": position.tolist(),
            "intensity": {"type": "rgb", "value": intensity.tolist()},
        }
    normal = _vector(light.emitter_normal, f"{where}.emitter_normal")
    helper = np.array([0.0, 1.0, 0.0]) if abs(normal[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    axis_u = np.cross(helper, normal)
    axis_u /= np.linalg.norm(axis_u)
    axis_v = np.cross(normal / np.linalg.norm(normal), axis_u)
    square = SimpleNamespace(
        center=position,
        normal=normal,
        edge_u=axis_u * _POINT_EMITTER_SIZE,
        edge_v=axis_v * _POINT_EMITTER_SIZE,
        radiance=intensity / _POINT_EMITTER_SIZE**2,
    )
    return _rectangle_dict(*_rectangle_frame(square, where))


def _is_area_light_stand_in(point: Any, area_lights: Sequence[Any]) -> bool:
    """Whether a point light is recon's stand-in for one of the true area lights (build_lighting
    adds one at each area light's centre, with its normal): Mitsuba renders the area light."""
    if point.emitter_normal is None:
        return False
    position = _vector(point.position, "point light position")
    for area in area_lights:
        center = _vector(area.center, "area light center")
        if np.linalg.norm(position - center) <= 1e-6 * max(1.0, float(np.linalg.norm(center))):
            return True
    return False


def scene_dict(
    meshes: Sequence[Mesh], cameras: Cameras, lighting: Any, options: MitsubaOptions
) -> dict:
    """The full Mitsuba scene dictionary: meshes, one sensor per camera, emitters, integrator.

    lighting: recon's Lighting, or data_synth.scene's WorldLighting (see render_mitsuba).
    Selects options.variant (or pick_variant()) first: Mitsuba objects belong to one variant.
    """
    options.validate()
    _select_variant(options.variant)
    base, environment_map, world_area_lights = _unpack_lighting(lighting)
    integrator: dict = {"type": options.integrator, "hide_emitters": options.hide_emitters}
    if options.integrator == "path":
        integrator["max_depth"] = options.max_depth
    scene: dict = {"type": "scene", "integrator": integrator}
    for index, mesh in enumerate(meshes):
        scene[f"mesh_{index}"] = mesh_to_mitsuba(mesh, options, name=f"mesh_{index}")
    for index in range(len(cameras)):
        scene[f"sensor_{index}"] = sensor_dict(cameras, index, options.spp, options.sampler)
    sh = base.sh_coefficients.detach().double().cpu() if options.include_environment else None
    if not options.include_environment:
        environment_map = None
    if sh is not None and environment_map is not None:
        from data_synth.environment import project_to_sh

        # recon shades the map through its SH projection, included in the coefficients.
        sh = sh - project_to_sh(environment_map.detach().float().cpu()).double()
    if sh is not None and not bool((sh.abs() > 1e-6 * max(1.0, float(sh.abs().max()))).any()):
        sh = None
    if sh is not None or environment_map is not None or options.suns:
        scene["environment"] = environment_dict(sh, options.suns, environment_map)
    if options.include_directional:
        for index, light in enumerate(base.directional):
            where = f"lighting.directional[{index}]"
            direction = _vector(light.direction_to_light, f"{where}.direction_to_light")
            irradiance = _vector(light.irradiance, f"{where}.irradiance")
            if np.linalg.norm(direction) < 1e-12 or (irradiance < 0).any():
                raise ReconError(f"{where}: expected a nonzero direction and irradiance >= 0")
            scene[f"directional_{index}"] = {
                "type": "directional",
                "direction": (-direction / np.linalg.norm(direction)).tolist(),
                "irradiance": {"type": "rgb", "value": irradiance.tolist()},
            }
    for index, point in enumerate(getattr(base, "points", [])):
        if not _is_area_light_stand_in(point, world_area_lights):
            scene[f"point_light_{index}"] = _point_light_dict(point, index)
    area_lights = [*world_area_lights, *options.area_lights]
    for index, light in enumerate(area_lights):
        scene[f"area_light_{index}"] = _rectangle_dict(
            *_rectangle_frame(light, f"area_lights[{index}]")
        )
    return scene


def _unpack_lighting(lighting: Any) -> tuple[Lighting, torch.Tensor | None, list]:
    """(recon Lighting, environment map or None, true area lights) of a Lighting or a
    WorldLighting (duck-typed: .lighting, .environment_map, .area_lights)."""
    if isinstance(lighting, Lighting):
        return lighting, None, []
    base = getattr(lighting, "lighting", None)
    if not isinstance(base, Lighting):
        raise ReconError(
            "lighting: expected recon's Lighting or data_synth.scene.WorldLighting, got "
            f"{type(lighting).__name__}"
        )
    return (
        base,
        getattr(lighting, "environment_map", None),
        list(getattr(lighting, "area_lights", []) or []),
    )


# --------------------------------------------------------------------------------------------
# Render
# --------------------------------------------------------------------------------------------


def render_mitsuba(
    mesh: Mesh | Sequence[Mesh],
    cameras: Cameras,
    lighting: Any,
    options: MitsubaOptions | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Path-trace mesh (or several meshes) from every camera with Mitsuba.

    mesh: one Mesh or a sequence (e.g. an object and a ground plane); albedo from its texture
        (+ uvs), else its vertex colours, else 0.5, as in recon's Renderer.
    cameras: B cameras (square pixels, no skew).
    lighting: recon's Lighting (SH environment [9, 3], directional and point lights), or
        data_synth.scene's WorldLighting, whose full environment map and true area lights
        Mitsuba renders in place of recon's approximations (see the module docstring).
    Returns (images [B, H, W, 3] float32 linear radiance premultiplied by coverage over a black
    background, alpha [B, H, W, 1] float32 coverage), on cameras' device; with
    hide_emitters=False the environment shows behind the object instead and alpha is 1 there.
    View k uses seed (options.seed * 65536 + k) * 256 + pass. Not differentiable.
    """
    options = MitsubaOptions() if options is None else options
    options.validate()
    meshes = [mesh] if isinstance(mesh, Mesh) else list(mesh)
    if not meshes:
        raise ReconError("render_mitsuba: expected at least one mesh")
    for index, item in enumerate(meshes):
        if not isinstance(item, Mesh) or item.faces.shape[0] == 0:
            raise ReconError(
                f"render_mitsuba: mesh {index}: expected a Mesh with faces, got {item!r:.80}"
            )
    mitsuba = _select_variant(options.variant)
    height, width = cameras.image_size
    batch = len(cameras)
    if batch == 0:
        empty = torch.zeros(0, height, width, 3, device=cameras.device)
        return empty, empty[..., :1]
    scene = mitsuba.load_dict(scene_dict(meshes, cameras, lighting, options))
    sensors = scene.sensors()
    # The JIT variants trace every sample of a pass at once (hundreds of bytes each): split the
    # samples into passes of at most _MAXIMUM_SAMPLES_PER_PASS and average them (the box filter
    # normalises each pass by its own weight, so equal-spp passes average exactly).
    per_pass = max(1, min(options.spp, _MAXIMUM_SAMPLES_PER_PASS // (height * width)))
    pass_count = math.ceil(options.spp / per_pass)
    pass_spp = [
        options.spp // pass_count + (1 if k < options.spp % pass_count else 0)
        for k in range(pass_count)
    ]
    images = np.zeros((batch, height, width, 4), dtype=np.float64)
    for index in range(batch):
        for pass_index, samples in enumerate(pass_spp):
            # Distinct seeds per view and pass; the same options and seed give the same images.
            seed = ((int(options.seed) * 65536 + index) * 256 + pass_index) % (2**32)
            rendered = mitsuba.render(scene, sensor=sensors[index], seed=seed, spp=samples)
            pixels = np.asarray(rendered, dtype=np.float64).reshape(height, width, 4)
            images[index] += pixels * (samples / options.spp)
    result = torch.from_numpy(images.astype(np.float32)).to(cameras.device)
    return result[..., :3], result[..., 3:4]

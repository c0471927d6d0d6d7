#!/usr/bin/env python
"""Benchmark recon's differentiable renderer (forward + backward) and compare it with Mitsuba 3.

Prints one JSON document on stdout (progress goes to stderr) and writes it to --out atomically.

Sections (--sections, default all of them):
  grid    procedural textured spheres with exactly 1k / 10k / 100k / 1M faces x resolution
          {128, 256, 512, 1024}^2 x {1, 8} views: median forward and backward ms and peak RSS.
  spot    the target scene: spot subdivided once (23,424 faces), 512x512, one view, full render
          forward + backward w.r.t. vertex positions, (a) with a prebuilt mip pyramid (texture
          fixed) and (b) rebuilding the pyramid every step (texture optimised too). Target < 100 ms.
  peer    Mitsuba 3 on the same spot scene and camera (prb and direct_projective with sppi=0,
          16 spp, llvm_ad_rgb), and the ratio mitsuba_ms / recon_ms.
  memory  peak RSS of recon's fwd + bwd at 512x512 with 8 views of the 1M-face sphere (< 8 GB).

Every measurement runs in a fresh worker process (this module with --worker), so each peak RSS
belongs to one configuration and a configuration that exceeds --timeout-per-config or runs out of
memory is recorded as {"skipped": reason}.

Examples:
  recon-bench render --quick                    # 1k/10k faces, 128/256 px, 1 view
  recon-bench render --spot-only --out spot.json
  recon-bench render --configs 100k:512:8,1M:512:1 --runs 3
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
import traceback

from benchmarks import common

MODULE = "benchmarks.render"
SHARED_MESHES = common.REPO_ROOT.parent / "shared" / "meshes"
SPOT_OBJ = "spot_triangulated.obj"
SPOT_TEXTURE = "spot_texture.png"

GRID_FACES = ("1k", "10k", "100k", "1M")
GRID_RESOLUTIONS = (128, 256, 512, 1024)
GRID_VIEWS = (1, 8)
QUICK_FACES = ("1k", "10k")
QUICK_RESOLUTIONS = (128, 256)
QUICK_VIEWS = (1,)
SECTIONS = ("grid", "spot", "peer", "memory")

SPOT_TARGET_MS = 100.0
MEMORY_TARGET_MB = 8192.0
MEMORY_CHECK = {"faces": "1M", "resolution": 512, "views": 8}
PROCEDURAL_TEXTURE_SIZE = 1024
# Camera of the grid scenes (unit sphere) and of spot (its bounding box is about 1.7 units).
ORBIT_DISTANCE = 3.0
FOV_X_DEG = 40.0
SPOT_EYE = (1.8, 1.1, -2.2)
SPOT_LOOK_AT = (0.0, 0.05, 0.15)


# ----------------------------------------------------------------------------------------------
# Scenes (benchmark inputs only: no rendering logic lives here)


def parse_face_count(label: str) -> int:
    """'1k' -> 1000, '1M' -> 1000000, '2500' -> 2500."""
    text = str(label).strip()
    scale = {"k": 1_000, "K": 1_000, "m": 1_000_000, "M": 1_000_000}.get(text[-1:], 1)
    number = float(text[:-1]) if scale != 1 else float(text)
    return int(round(number * scale))


def sphere_grid(face_count: int) -> tuple[int, int]:
    """(bands, columns) of a latitude-longitude sphere with exactly face_count faces: one
    triangle fan per pole and bands - 2 rows of quads, 2 * columns * (bands - 1) faces in all,
    with cells as close to square at the equator as the divisors allow (columns ~ 2 bands)."""
    half = face_count // 2
    if face_count < 12 or face_count % 2:
        raise SystemExit(f"sphere face count must be even and >= 12, got {face_count}")
    best = None
    for rings in range(1, half // 3 + 1):
        if half % rings:
            continue
        bands, columns = rings + 1, half // rings
        score = abs(math.log(columns / (2.0 * bands)))
        if best is None or score < best[0]:
            best = (score, bands, columns)
    return best[1], best[2]


def latlong_sphere(face_count: int):
    """Unit sphere (y up) with exactly face_count faces, equirectangular UVs on their own index
    buffer (positions shared across the seam, UVs duplicated at u = 0 and u = 1; v = 0 at the
    north pole = top of the texture). Returns numpy (verts, faces, uvs, uv_faces)."""
    import numpy as np

    bands, columns = sphere_grid(face_count)
    theta = np.pi * np.arange(1, bands) / bands  # polar angle of each ring
    phi = 2 * np.pi * np.arange(columns) / columns
    sin_theta = np.sin(theta)[:, None]
    ring_points = np.stack(
        [
            sin_theta * np.sin(phi)[None],
            np.broadcast_to(np.cos(theta)[:, None], (bands - 1, columns)),
            sin_theta * np.cos(phi)[None],
        ],
        axis=-1,
    ).reshape(-1, 3)
    north, south = len(ring_points), len(ring_points) + 1
    verts = np.concatenate([ring_points, [[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]]).astype(np.float32)
    ring = np.arange((bands - 1) * columns).reshape(bands - 1, columns)
    ring_next = np.roll(ring, -1, axis=1)

    # UVs: (bands - 1) rings of columns + 1 (seam duplicated), then one pole UV per column.
    u = np.arange(columns + 1) / columns
    ring_uvs = np.stack(
        np.broadcast_arrays(u[None], (np.arange(1, bands) / bands)[:, None]), axis=-1
    ).reshape(-1, 2)
    pole_u = (np.arange(columns) + 0.5) / columns
    north_uvs = np.stack([pole_u, np.zeros(columns)], axis=-1)
    south_uvs = np.stack([pole_u, np.ones(columns)], axis=-1)
    uvs = np.concatenate([ring_uvs, north_uvs, south_uvs]).astype(np.float32)
    uv_ring = np.arange((bands - 1) * (columns + 1)).reshape(bands - 1, columns + 1)
    uv_north = len(ring_uvs) + np.arange(columns)
    uv_south = uv_north + columns

    # Counter-clockwise seen from outside (checked below).
    top = np.stack([np.full(columns, north), ring[0], ring_next[0]], axis=-1)
    top_uv = np.stack([uv_north, uv_ring[0, :-1], uv_ring[0, 1:]], axis=-1)
    bottom = np.stack([np.full(columns, south), ring_next[-1], ring[-1]], axis=-1)
    bottom_uv = np.stack([uv_south, uv_ring[-1, 1:], uv_ring[-1, :-1]], axis=-1)
    a, b = ring[:-1], ring_next[:-1]
    c, d = ring_next[1:], ring[1:]
    a_uv, b_uv = uv_ring[:-1, :-1], uv_ring[:-1, 1:]
    c_uv, d_uv = uv_ring[1:, 1:], uv_ring[1:, :-1]
    quads = np.concatenate(
        [np.stack([a, d, c], -1).reshape(-1, 3), np.stack([a, c, b], -1).reshape(-1, 3)]
    )
    quads_uv = np.concatenate(
        [
            np.stack([a_uv, d_uv, c_uv], -1).reshape(-1, 3),
            np.stack([a_uv, c_uv, b_uv], -1).reshape(-1, 3),
        ]
    )
    faces = np.concatenate([top, quads, bottom]).astype(np.int64)
    uv_faces = np.concatenate([top_uv, quads_uv, bottom_uv]).astype(np.int64)
    corners = verts[faces].astype(np.float64)
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    if float((normal * corners.mean(axis=1)).sum()) < 0:  # whole mesh inside out: flip all
        faces, uv_faces = faces[:, ::-1].copy(), uv_faces[:, ::-1].copy()
    assert faces.shape[0] == face_count, (faces.shape, face_count)
    return verts, faces, uvs, uv_faces


def procedural_texture(size: int = PROCEDURAL_TEXTURE_SIZE):
    """[size, size, 3] float32 linear albedo: a checkerboard over a smooth colour gradient."""
    import torch

    coordinates = (torch.arange(size, dtype=torch.float32) + 0.5) / size
    v, u = torch.meshgrid(coordinates, coordinates, indexing="ij")
    checker = ((torch.floor(u * 16) + torch.floor(v * 8)) % 2)[..., None]
    gradient = torch.stack([0.3 + 0.5 * u, 0.3 + 0.4 * v, 0.8 - 0.5 * u], dim=-1)
    return (gradient * (0.35 + 0.65 * checker)).contiguous()


def midpoint_subdivide(points, faces):
    """One 1-to-4 midpoint subdivision (numpy). New points (edge midpoints, one per undirected
    edge) follow the old ones; the 4 children of face f are rows 4f..4f+3, corner order kept, so
    positions and a UV index buffer subdivided separately stay in step face by face."""
    import numpy as np

    face_count = faces.shape[0]
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    unique_edges, inverse = np.unique(np.sort(edges, axis=1), axis=0, return_inverse=True)
    midpoints = 0.5 * (points[unique_edges[:, 0]] + points[unique_edges[:, 1]])
    new_points = np.concatenate([points, midpoints.astype(points.dtype)])
    mid = len(points) + inverse.reshape(3, face_count).T  # (v0v1, v1v2, v2v0) per face
    a, b, c = faces.T
    ab, bc, ca = mid.T
    children = np.stack(
        [
            np.stack([a, ab, ca], -1),
            np.stack([ab, b, bc], -1),
            np.stack([ca, bc, c], -1),
            np.stack([ab, bc, ca], -1),
        ],
        axis=1,
    )
    return new_points, children.reshape(-1, 3)


def load_spot(subdivisions: int = 1):
    """spot (recon Mesh on the CPU, its real texture), midpoint-subdivided; None when absent."""
    import torch

    obj, texture = SHARED_MESHES / SPOT_OBJ, SHARED_MESHES / SPOT_TEXTURE
    if not (obj.is_file() and texture.is_file()):
        return None
    from recon.io.meshes import load_mesh
    from recon.mesh.mesh import Mesh

    mesh = load_mesh(obj, texture_path=texture)
    verts, faces = mesh.verts.numpy(), mesh.faces.numpy()
    uvs, uv_faces = mesh.uvs.numpy(), mesh.uv_faces.numpy()
    for _ in range(subdivisions):
        verts, faces = midpoint_subdivide(verts, faces)
        uvs, uv_faces = midpoint_subdivide(uvs, uv_faces)
    return Mesh(
        verts=torch.from_numpy(verts),
        faces=torch.from_numpy(faces),
        uvs=torch.from_numpy(uvs),
        uv_faces=torch.from_numpy(uv_faces),
        texture=mesh.texture,
    )


def spot_cameras(resolution: int, device: str):
    import torch

    from recon.camera.cameras import Cameras, intrinsics_from_fov, look_at

    eye = torch.tensor([SPOT_EYE], dtype=torch.float32)
    target = torch.tensor([SPOT_LOOK_AT], dtype=torch.float32)
    distance = float((eye - target).norm())
    return Cameras(
        world_to_cam=look_at(eye, target).to(device),
        intrinsics=intrinsics_from_fov(FOV_X_DEG, (resolution, resolution))[None].to(device),
        image_size=(resolution, resolution),
        near=0.05 * distance,
        far=10.0 * distance,
    )


def build_scene(job: dict):
    """(mesh, cameras, description) for a worker job, on the job's device."""
    import torch

    from recon.camera.cameras import orbit_cameras
    from recon.mesh.mesh import Mesh

    device, resolution, views = job["device"], job["resolution"], job["views"]
    if job["scene"] == "spot":
        mesh = load_spot()
        if mesh is None:
            raise FileNotFoundError(f"spot is absent from {SHARED_MESHES}")
        cameras = spot_cameras(resolution, device)
        if views != 1:
            raise ValueError("the spot scene has one view")
        description = {"mesh": f"spot subdivided once ({SPOT_OBJ} + {SPOT_TEXTURE})"}
    else:
        verts, faces, uvs, uv_faces = latlong_sphere(job["faces"])
        mesh = Mesh(
            verts=torch.from_numpy(verts),
            faces=torch.from_numpy(faces),
            uvs=torch.from_numpy(uvs),
            uv_faces=torch.from_numpy(uv_faces),
            texture=procedural_texture(),
        )
        cameras = orbit_cameras(
            views,
            (resolution, resolution),
            distance=ORBIT_DISTANCE,
            fov_x_deg=FOV_X_DEG,
            device=device,
        )
        bands, columns = sphere_grid(job["faces"])
        description = {
            "mesh": f"latitude-longitude unit sphere, {bands} bands x {columns} columns, "
            f"procedural {PROCEDURAL_TEXTURE_SIZE}^2 texture"
        }
    mesh = mesh.to(device)
    description.update(
        faces=int(mesh.faces.shape[0]),
        vertices=int(mesh.verts.shape[0]),
        texture_size=list(mesh.texture.shape[:2]),
    )
    return mesh, cameras, description


# ----------------------------------------------------------------------------------------------
# Workers (run in a fresh process each)


def run_count(requested: int, minimum: int, warmup_s: float, budget_s: float) -> int:
    """Timed runs: the requested count, fewer when the warm-up step says they would not fit in
    budget_s (but never fewer than minimum)."""
    if warmup_s <= 0:
        return requested
    fitting = int(budget_s / warmup_s)
    return max(min(requested, fitting), min(minimum, requested), 1)


def recon_worker(job: dict) -> dict:
    """Time recon's full render (rasterize, interpolate, texture, shade, antialias) forward and
    backward (MSE against a random target, gradient w.r.t. vertex positions)."""
    import torch

    from recon.mesh.mesh import Mesh
    from recon.render.antialias import build_topology
    from recon.render.renderer import Renderer
    from recon.render.shading import Lighting
    from recon.render.texture import build_mip_pyramid

    started = time.perf_counter()
    threads = common.configure_threads(job.get("threads"))
    device = job["device"]
    mesh, cameras, description = build_scene(job)
    mip = job.get("mip", "prebuilt")
    optimise_texture = mip == "rebuild"
    verts = mesh.verts.clone().requires_grad_(True)
    texture = mesh.texture.clone().requires_grad_(optimise_texture)
    mesh = Mesh(
        verts=verts, faces=mesh.faces, uvs=mesh.uvs, uv_faces=mesh.uv_faces, texture=texture
    )
    topology = build_topology(mesh.faces, mesh.verts.shape[0])
    pyramid = None if optimise_texture else build_mip_pyramid(texture.detach())
    lighting = Lighting.constant(1.0, device=device)
    renderer = Renderer()
    height, width = cameras.image_size
    generator = torch.Generator().manual_seed(0)
    target = torch.rand(len(cameras), height, width, 3, generator=generator).to(device)
    if device.startswith("cuda"):
        torch.cuda.reset_peak_memory_stats()
    rss_before = common.current_rss_mb()
    peak_before = common.peak_rss_mb()

    covered = []

    def step() -> tuple[float, float]:
        common.synchronize(device)
        t0 = time.perf_counter()
        output = renderer.render(
            mesh,
            cameras,
            lighting,
            background=job.get("background", 0.0),
            topology=topology,
            mip_pyramid=pyramid,
        )
        loss = torch.nn.functional.mse_loss(output.color, target)
        common.synchronize(device)
        t1 = time.perf_counter()
        loss.backward()
        common.synchronize(device)
        t2 = time.perf_counter()
        if not covered:
            covered.append(int(output.fragments.covered_index.shape[0]))
            covered.append(
                bool(torch.isfinite(verts.grad).all()) and float(verts.grad.abs().sum()) > 0
            )
        verts.grad = None
        texture.grad = None
        return (t1 - t0) * 1e3, (t2 - t1) * 1e3

    label = job.get("label", "")
    warmup_ms = [step() for _ in range(job.get("warmup", 1))]
    warmup_s = sum(f + b for f, b in warmup_ms) / 1e3 / max(len(warmup_ms), 1)
    elapsed = time.perf_counter() - started
    budget = max(0.7 * job["timeout_s"] - elapsed, 0.0)
    runs = run_count(job["runs"], job.get("min_runs", 1), warmup_s, budget)
    common.log(f"{label}: warm-up {warmup_s * 1e3:.0f} ms/step, timing {runs} runs")
    meter = common.CpuMeter()
    load = common.load_average()
    meter.start()
    timings = [step() for _ in range(runs)]
    cores_used = meter.cores_used()
    forward = [round(f, 3) for f, _ in timings]
    backward = [round(b, 3) for _, b in timings]
    total = [round(f + b, 3) for f, b in timings]
    result = {
        **description,
        "resolution": job["resolution"],
        "views": job["views"],
        "device": device,
        "torch_threads": threads,
        "texture_filter": renderer.texture_filter,
        "mip_pyramid": "prebuilt once (texture fixed)"
        if pyramid is not None
        else "rebuilt every step (texture requires grad)",
        "covered_pixels": covered[0],
        "gradient_ok": covered[1],
        "warmup_runs": len(warmup_ms),
        "runs": runs,
        "forward_ms": common.median(forward),
        "backward_ms": common.median(backward),
        "total_ms": common.median(total),
        "total_ms_min": min(total),
        "forward_ms_all": forward,
        "backward_ms_all": backward,
        "cpu_cores_used": cores_used,
        "load_average_before": load,
        "rss_before_render_mb": None if rss_before is None else round(rss_before, 1),
        "peak_rss_before_render_mb": round(peak_before, 1),
        "peak_rss_mb": round(common.peak_rss_mb(), 1),
    }
    if device.startswith("cuda"):
        result["cuda_max_memory_allocated_mb"] = round(torch.cuda.max_memory_allocated() / 2**20, 1)
    return result


def mitsuba_camera(cameras) -> tuple[dict, dict]:
    """A Mitsuba perspective sensor dict for recon's (single) camera, and notes on the mapping.

    recon: OpenCV camera axes (x right, y down, z forward), world_to_cam + pixel intrinsics.
    Mitsuba: camera-to-world `to_world` whose local axes are x LEFT, y up, z forward (what
    ScalarTransform4f.look_at builds), so to_world = cam_to_world_opengl @ diag(-1, 1, -1, 1)
    (= cam_to_world_opencv @ diag(-1, -1, 1, 1)). fov is the full horizontal angle
    2 atan(W / (2 fx)) with fov_axis 'x'; Mitsuba assumes square pixels and a centred principal
    point here, which recon's camera must match.
    """
    import mitsuba as mi
    import numpy as np

    height, width = cameras.image_size
    intrinsics = cameras.intrinsics[0].detach().cpu().double().numpy()
    fx, fy, cx, cy = intrinsics[0, 0], intrinsics[1, 1], intrinsics[0, 2], intrinsics[1, 2]
    if abs(fx - fy) > 1e-4 * fx or abs(cx - width / 2) > 1e-3 or abs(cy - height / 2) > 1e-3:
        raise ValueError("Mitsuba sensor mapping needs square pixels and a centred principal point")
    cam_to_world_gl = cameras.cam_to_world_opengl()[0].detach().cpu().double().numpy()
    to_world = cam_to_world_gl @ np.diag([-1.0, 1.0, -1.0, 1.0])
    fov_x = math.degrees(2 * math.atan(width / (2 * fx)))
    sensor = {
        "type": "perspective",
        "fov": fov_x,
        "fov_axis": "x",
        "near_clip": float(cameras.near),
        "far_clip": float(cameras.far),
        "to_world": mi.ScalarTransform4f(to_world.tolist()),
        "film": {
            "type": "hdrfilm",
            "width": width,
            "height": height,
            "pixel_format": "rgb",
            "rfilter": {"type": "box"},
        },
    }
    notes = {
        "fov_x_deg": round(fov_x, 6),
        "to_world": "cam_to_world_opengl @ diag(-1, 1, -1, 1): Mitsuba's camera x axis points "
        "left (OpenCV: right, y down; OpenGL: y up, looks down -z); Mitsuba looks down +z",
        "pixels": "Mitsuba integrates over each pixel's area (box filter, spp samples); recon "
        "samples pixel centres and antialiases silhouette edges analytically",
    }
    return sensor, notes


def mitsuba_mesh_arrays(mesh):
    """Mitsuba meshes have one UV per vertex: split recon's (position, uv) index pairs."""
    import numpy as np

    faces = mesh.faces.numpy()
    uv_faces = mesh.uv_faces.numpy()
    pairs = np.stack([faces.reshape(-1), uv_faces.reshape(-1)], axis=-1)
    unique_pairs, inverse = np.unique(pairs, axis=0, return_inverse=True)
    positions = mesh.verts.numpy()[unique_pairs[:, 0]].astype(np.float32)
    uvs = mesh.uvs.numpy()[unique_pairs[:, 1]].astype(np.float32)
    return positions, inverse.reshape(-1, 3).astype(np.uint32), uvs


def mitsuba_worker(job: dict) -> dict:
    """Time Mitsuba's forward + backward (w.r.t. vertex positions) on the spot scene."""
    import drjit as dr
    import mitsuba as mi
    import numpy as np
    import torch

    started = time.perf_counter()
    mi.set_variant(job["variant"])
    threads = job.get("threads") or os.cpu_count() or 1
    dr.set_thread_count(threads)
    mesh = load_spot()
    if mesh is None:
        raise FileNotFoundError(f"spot is absent from {SHARED_MESHES}")
    resolution = job["resolution"]
    cameras = spot_cameras(resolution, "cpu")
    sensor, camera_notes = mitsuba_camera(cameras)
    sensor["sampler"] = {"type": "independent", "sample_count": job["spp"]}
    positions, faces, uvs = mitsuba_mesh_arrays(mesh)

    def make_mesh():
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(
            {
                "type": "diffuse",
                "reflectance": {
                    "type": "bitmap",
                    "bitmap": mi.Bitmap(mesh.texture.numpy()),  # the same linear texture
                    "raw": True,
                    "filter_type": "bilinear",
                    "wrap_mode": "repeat",
                },
            }
        )
        shape = mi.Mesh(
            "spot",
            vertex_count=len(positions),
            face_count=len(faces),
            props=props,
            has_vertex_normals=True,
            has_vertex_texcoords=True,
        )
        shape_params = mi.traverse(shape)
        shape_params["vertex_positions"] = mi.Float(positions.reshape(-1))
        shape_params["faces"] = mi.UInt32(faces.reshape(-1))
        shape_params["vertex_texcoords"] = mi.Float(uvs.reshape(-1))
        shape_params.update()  # recomputes the (smooth) vertex normals
        return shape

    integrator = {"type": job["integrator"]}
    if job["integrator"] == "direct_projective":
        integrator["sppi"] = 0
    else:
        integrator["max_depth"] = job["max_depth"]
    emitter = {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": integrator,
            "sensor": sensor,
            "spot": make_mesh(),
            "env": emitter,
        }
    )
    params = mi.traverse(scene)
    key = "spot.vertex_positions"
    initial = np.array(params[key])
    generator = torch.Generator().manual_seed(0)
    target_array = torch.rand(resolution, resolution, 3, generator=generator).numpy()
    target = mi.TensorXf(target_array)
    gradient_ok = []

    def step(seed: int) -> tuple[float, float]:
        t0 = time.perf_counter()
        params[key] = mi.Float(initial)
        dr.enable_grad(params[key])
        params.update()  # differentiable vertex normals and the acceleration structure
        image = mi.render(scene, params, spp=job["spp"], seed=seed)
        loss = dr.mean(dr.square(image - target), axis=None)
        dr.eval(loss)
        dr.sync_thread()
        t1 = time.perf_counter()
        dr.backward(loss)
        gradient = dr.grad(params[key])
        dr.eval(gradient)
        dr.sync_thread()
        t2 = time.perf_counter()
        if not gradient_ok:
            values = np.array(gradient)
            gradient_ok.append(bool(np.isfinite(values).all() and np.abs(values).sum() > 0))
        return (t1 - t0) * 1e3, (t2 - t1) * 1e3

    label = job.get("label", "")
    warmup = [step(seed) for seed in range(job["warmup"])]
    common.log(
        f"{label}: warm-up (JIT compilation) "
        + ", ".join(f"{(f + b) / 1e3:.2f} s" for f, b in warmup)
    )
    meter = common.CpuMeter()
    load = common.load_average()
    meter.start()
    timings = [step(1000 + run) for run in range(job["runs"])]
    cores_used = meter.cores_used()
    forward = [round(f, 3) for f, _ in timings]
    backward = [round(b, 3) for _, b in timings]
    total = [round(f + b, 3) for f, b in timings]
    result = {
        "integrator": integrator,
        "variant": job["variant"],
        "spp": job["spp"],
        "resolution": resolution,
        "faces": int(len(faces)),
        "mitsuba_vertices": int(len(positions)),
        "drjit_threads": threads,
        "warmup_runs": len(warmup),
        "warmup_ms": [round(f + b, 1) for f, b in warmup],
        "runs": len(timings),
        "forward_ms": common.median(forward),
        "backward_ms": common.median(backward),
        "total_ms": common.median(total),
        "total_ms_min": min(total),
        "forward_ms_all": forward,
        "backward_ms_all": backward,
        "cpu_cores_used": cores_used,
        "load_average_before": load,
        "gradient_ok": gradient_ok[0] if gradient_ok else None,
        "peak_rss_mb": round(common.peak_rss_mb(), 1),
        "camera": camera_notes,
        "worker_setup_and_run_s": round(time.perf_counter() - started, 2),
    }
    if job.get("camera_check"):
        result["camera_check"] = camera_check(mi, make_mesh, sensor, emitter, mesh, cameras)
    return result


def camera_check(mi, make_mesh, sensor, emitter, mesh, cameras) -> dict:
    """Silhouette agreement between Mitsuba (alpha of an rgba film) and recon (alpha), which
    confirms the camera conversion: a mirrored or shifted camera gives a low IoU."""
    import numpy as np
    import torch

    from recon.render.renderer import Renderer
    from recon.render.shading import Lighting

    check_sensor = dict(sensor)
    check_sensor["film"] = dict(sensor["film"], pixel_format="rgba")
    check_sensor["sampler"] = {"type": "independent", "sample_count": 64}
    scene = mi.load_dict(
        {
            "type": "scene",
            "integrator": {"type": "direct"},
            "sensor": check_sensor,
            "spot": make_mesh(),
            "env": emitter,
        }
    )
    mitsuba_image = np.array(mi.render(scene))
    with torch.no_grad():
        output = Renderer().render(mesh, cameras, Lighting.constant(1.0), background=1.0)
    recon_alpha = output.alpha[0, ..., 0].numpy()
    recon_color = output.color[0].numpy()
    mitsuba_alpha = mitsuba_image[..., 3]
    inside_m, inside_r = mitsuba_alpha > 0.5, recon_alpha > 0.5
    union = np.logical_or(inside_m, inside_r).sum()
    both = np.logical_and(inside_m, inside_r)
    return {
        "silhouette_iou": round(float(np.logical_and(inside_m, inside_r).sum() / max(union, 1)), 4),
        "alpha_mean_abs_diff": round(float(np.abs(mitsuba_alpha - recon_alpha).mean()), 4),
        "color_mean_abs_diff_inside": round(
            float(np.abs(mitsuba_image[..., :3][both] - recon_color[both]).mean()), 4
        ),
        "note": "Mitsuba 'direct' (64 spp) vs recon; colours differ by Mitsuba's self-shadowing "
        "of the environment light (recon's SH shading has no visibility)",
    }


def worker_main(job: dict) -> None:
    common.limit_address_space(job.get("memory_limit_mb"))
    try:
        result = mitsuba_worker(job) if job["kind"] == "mitsuba" else recon_worker(job)
    except FileNotFoundError as error:
        result = {"skipped": str(error)}
    except Exception as error:  # recorded in the report rather than ending the whole run
        first_line = (str(error).splitlines() or [""])[0][:300]
        if common.is_out_of_memory(error):
            result = {"skipped": f"out of memory: {first_line}"}
        else:
            traceback.print_exc()
            result = {"skipped": f"error: {type(error).__name__}: {first_line}"}
    common.emit_worker_result(result)


# ----------------------------------------------------------------------------------------------
# Orchestration


def parse_config(text: str) -> tuple[str, int, int]:
    """'1k:512:8' -> ('1k', 512, 8)."""
    parts = text.strip().split(":")
    if len(parts) != 3:
        raise SystemExit(
            f"--configs: expected FACES:RESOLUTION:VIEWS such as 1k:512:8, got {text!r}"
        )
    return parts[0], int(parts[1]), int(parts[2])


def grid_configs(args) -> list[tuple[str, int, int]]:
    if args.configs:
        return [parse_config(item) for item in args.configs.split(",") if item.strip()]
    if args.quick:
        return [(f, r, v) for f in QUICK_FACES for r in QUICK_RESOLUTIONS for v in QUICK_VIEWS]
    return [(f, r, v) for f in GRID_FACES for r in GRID_RESOLUTIONS for v in GRID_VIEWS]


def default_memory_limit_mb() -> float | None:
    available = common.available_memory_mb()
    return None if available is None else round(0.75 * available)


def recon_job(args, device: str, **fields) -> dict:
    job = {
        "kind": "recon",
        "device": device,
        "runs": args.runs,
        "warmup": 1,
        "timeout_s": args.timeout_per_config,
        "memory_limit_mb": None if device.startswith("cuda") else args.memory_limit_mb,
        "threads": args.threads,
    }
    job.update(fields)
    return job


def run_grid(args, device: str) -> list[dict]:
    results, failed = [], []
    for label, resolution, views in grid_configs(args):
        face_count = parse_face_count(label)
        entry = {
            "faces_label": label,
            "faces": face_count,
            "resolution": resolution,
            "views": views,
        }
        # A configuration at least as large as one that already failed would fail too.
        larger_than = next(
            (f for f in failed if face_count >= f[0] and resolution >= f[1] and views >= f[2]), None
        )
        if larger_than is not None:
            entry["skipped"] = (
                f"not run: {larger_than[3]} faces at {larger_than[1]}^2 x {larger_than[2]} views "
                "was already skipped"
            )
            common.log(f"grid {label} {resolution}^2 x{views}: {entry['skipped']}")
            results.append(entry)
            continue
        tag = f"grid {label} {resolution}^2 x{views}"
        common.log(f"{tag}: starting")
        result = common.run_worker(
            MODULE,
            recon_job(
                args,
                device,
                scene="sphere",
                faces=face_count,
                resolution=resolution,
                views=views,
                label=tag,
            ),
            args.timeout_per_config,
        )
        entry.update(result)
        if "skipped" in result:
            failed.append((face_count, resolution, views, label))
            common.log(f"{tag}: skipped ({result['skipped']})")
        else:
            common.log(
                f"{tag}: forward {result['forward_ms']:.1f} ms, backward "
                f"{result['backward_ms']:.1f} ms, peak RSS {result['peak_rss_mb']:.0f} MB, "
                f"{result['cpu_cores_used']} cores busy"
            )
        results.append(entry)
    return results


def run_spot(args, device: str) -> dict:
    if not (SHARED_MESHES / SPOT_OBJ).is_file() or not (SHARED_MESHES / SPOT_TEXTURE).is_file():
        return {"skipped": f"spot is absent ({SHARED_MESHES / SPOT_OBJ} / {SPOT_TEXTURE})"}
    section = {
        "scene": "spot subdivided once (midpoint, positions and UV index buffer separately), "
        f"{args.spot_resolution}^2, 1 view, constant white environment, background 1, full "
        "render (rasterize, interpolate, trilinear texture, SH shading, antialias) forward + "
        "MSE loss against a random target, backward to the vertex positions",
        "target_ms": SPOT_TARGET_MS,
    }
    for key, mip in (("prebuilt_mip", "prebuilt"), ("rebuild_mip", "rebuild")):
        tag = f"spot {key}"
        common.log(f"{tag}: starting")
        result = common.run_worker(
            MODULE,
            recon_job(
                args,
                device,
                scene="spot",
                resolution=args.spot_resolution,
                views=1,
                mip=mip,
                runs=args.spot_runs,
                min_runs=min(10, args.spot_runs),
                warmup=2,
                background=1.0,
                label=tag,
            ),
            args.timeout_per_config,
        )
        if "total_ms" in result:
            result["meets_target"] = result["total_ms"] < SPOT_TARGET_MS
            common.log(
                f"{tag}: forward {result['forward_ms']:.1f} + backward "
                f"{result['backward_ms']:.1f} = {result['total_ms']:.1f} ms (median of "
                f"{result['runs']}, {result['cpu_cores_used']} cores busy)"
            )
        section[key] = result
    return section


def run_peer(args, device: str, spot: dict | None) -> dict | str:
    version = common.mitsuba_version()
    if version == "not installed":
        return "not installed"
    if not (SHARED_MESHES / SPOT_OBJ).is_file():
        return {"skipped": f"spot is absent from {SHARED_MESHES}", "version": version}
    section = {
        "version": version,
        "variant": args.mitsuba_variant,
        "spp": args.mitsuba_spp,
        "scene": "the same subdivided spot, camera, texture (linear, bilinear, repeat) and "
        "constant environment (radiance 1, visible as the background), diffuse BSDF, "
        "smooth vertex normals recomputed from the positions every step; forward includes "
        "params.update() (normals + BVH rebuild), as in an optimisation step",
        "ratio": "mitsuba total_ms / recon total_ms (forward + backward medians)",
    }
    for name in ("prb", "direct_projective"):
        tag = f"mitsuba {name}"
        common.log(f"{tag}: starting")
        result = common.run_worker(
            MODULE,
            {
                "kind": "mitsuba",
                "integrator": name,
                "variant": args.mitsuba_variant,
                "spp": args.mitsuba_spp,
                "max_depth": args.mitsuba_max_depth,
                "resolution": args.spot_resolution,
                "runs": args.mitsuba_runs,
                "warmup": 2,
                "camera_check": name == "prb",
                "threads": args.threads,
                "label": tag,
            },
            args.timeout_per_config * 3,
        )
        if "total_ms" in result and isinstance(spot, dict):
            ratios = {}
            for key in ("prebuilt_mip", "rebuild_mip"):
                recon_ms = spot.get(key, {}).get("total_ms")
                if recon_ms:
                    ratios[key] = round(result["total_ms"] / recon_ms, 3)
            result["ratio_to_recon"] = ratios
        if "total_ms" in result:
            common.log(
                f"{tag}: forward {result['forward_ms']:.1f} + backward "
                f"{result['backward_ms']:.1f} = {result['total_ms']:.1f} ms; ratios "
                f"{result.get('ratio_to_recon')}"
            )
        else:
            common.log(f"{tag}: {result}")
        section[name] = result
    return section


def run_memory_check(args, device: str, grid: list[dict]) -> dict:
    face_count = parse_face_count(MEMORY_CHECK["faces"])
    reused = next(
        (
            entry
            for entry in grid
            if entry.get("faces") == face_count
            and entry.get("resolution") == MEMORY_CHECK["resolution"]
            and entry.get("views") == MEMORY_CHECK["views"]
            and "peak_rss_mb" in entry
        ),
        None,
    )
    if reused is not None:
        result, source = reused, "grid entry"
    else:
        tag = "memory check 1M 512^2 x8"
        common.log(f"{tag}: starting")
        result = common.run_worker(
            MODULE,
            recon_job(
                args,
                device,
                scene="sphere",
                faces=face_count,
                resolution=MEMORY_CHECK["resolution"],
                views=MEMORY_CHECK["views"],
                runs=1,
                warmup=1,
                label=tag,
                timeout_s=args.memory_timeout,
            ),
            args.memory_timeout,
        )
        source = "own worker (1 warm-up + 1 timed fwd+bwd)"
    section = {
        "faces": face_count,
        "resolution": MEMORY_CHECK["resolution"],
        "views": MEMORY_CHECK["views"],
        "target_mb": MEMORY_TARGET_MB,
        "source": source,
    }
    if "peak_rss_mb" in result:
        section.update(
            peak_rss_mb=result["peak_rss_mb"],
            rss_before_render_mb=result.get("rss_before_render_mb"),
            meets_target=result["peak_rss_mb"] < MEMORY_TARGET_MB,
            forward_ms=result.get("forward_ms"),
            backward_ms=result.get("backward_ms"),
        )
        if "cuda_max_memory_allocated_mb" in result:
            section["cuda_max_memory_allocated_mb"] = result["cuda_max_memory_allocated_mb"]
        common.log(f"memory check: peak RSS {result['peak_rss_mb']:.0f} MB")
    else:
        section["skipped"] = result.get("skipped")
    return section


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto")
    parser.add_argument("--runs", type=int, default=5, help="timed runs per grid config (median)")
    parser.add_argument(
        "--quick",
        action="store_true",
        help="grid subset 1k/10k faces x 128/256 px x 1 view (grid section only)",
    )
    parser.add_argument(
        "--configs", help="grid configs FACES:RES:VIEWS[,...], e.g. 1k:64:1,1M:512:8"
    )
    parser.add_argument("--sections", help=f"comma-separated subset of {','.join(SECTIONS)}")
    parser.add_argument("--spot-only", action="store_true", help="only the spot and peer sections")
    parser.add_argument("--no-peer", action="store_true", help="skip the Mitsuba peer")
    parser.add_argument(
        "--timeout-per-config",
        type=float,
        default=120.0,
        help="seconds before a config's worker is killed and recorded as skipped",
    )
    parser.add_argument(
        "--memory-timeout",
        type=float,
        default=600.0,
        help="seconds allowed to the memory check's worker when the grid did not cover it",
    )
    parser.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch / Dr.Jit threads per worker (default os.cpu_count())",
    )
    parser.add_argument(
        "--memory-limit-mb",
        type=float,
        default=default_memory_limit_mb(),
        help="address-space cap of each CPU worker (default 75%% of MemAvailable)",
    )
    parser.add_argument("--spot-resolution", type=int, default=512)
    parser.add_argument("--spot-runs", type=int, default=20, help="timed spot runs (>= 10)")
    parser.add_argument("--mitsuba-variant", default="llvm_ad_rgb")
    parser.add_argument("--mitsuba-spp", type=int, default=16)
    parser.add_argument("--mitsuba-runs", type=int, default=7)
    parser.add_argument(
        "--mitsuba-max-depth",
        type=int,
        default=2,
        help="prb max_depth (2 = direct light only, like recon's shading)",
    )
    parser.add_argument("--out", help="also write the JSON here (atomically)")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.runs < 1 or args.spot_runs < 1 or args.mitsuba_runs < 1:
        parser.error("run counts must be >= 1")
    return args


def selected_sections(args) -> list[str]:
    if args.sections:
        sections = [item.strip() for item in args.sections.split(",") if item.strip()]
        unknown = sorted(set(sections) - set(SECTIONS))
        if unknown:
            raise SystemExit(f"--sections: unknown {unknown}; expected a subset of {SECTIONS}")
    elif args.spot_only:
        sections = ["spot", "peer"]
    elif args.quick or args.configs:
        sections = ["grid"]
    else:
        sections = list(SECTIONS)
    if args.no_peer:
        sections = [name for name in sections if name != "peer"]
    return sections


def main(argv: list[str] | None = None) -> dict | None:
    args = parse_args(argv)
    if args.worker:
        worker_main(json.loads(args.worker))
        return None
    common.configure_threads()
    device = common.resolve_device(args.device)
    sections = selected_sections(args)
    started = time.perf_counter()
    report: dict = {
        "benchmark": "recon render forward + backward",
        "environment": common.environment(device),
        "settings": {
            "sections": sections,
            "runs": args.runs,
            "threads": args.threads or os.cpu_count(),
            "spot_runs": args.spot_runs,
            "timeout_per_config_s": args.timeout_per_config,
            "memory_limit_mb": args.memory_limit_mb,
            "timing": "median ms over the timed runs after warm-up; forward = render + MSE loss, "
            "backward = loss.backward() to the vertex positions",
            "contention": "cpu_cores_used = CPU seconds / wall seconds of the worker over its "
            "timed runs (about torch_threads when it had the cores to itself; lower means other "
            "processes competed and the times are inflated); load_average_before is os.getloadavg()",
            "memory": "peak_rss_mb = ru_maxrss of a fresh worker process per config (includes "
            "the interpreter, torch and the scene); rss_before_render_mb is its RSS just before "
            "the first render",
        },
    }
    grid: list[dict] = []
    if "grid" in sections:
        grid = run_grid(args, device)
        report["grid"] = grid
    spot = None
    if "spot" in sections:
        spot = run_spot(args, device)
        report["spot"] = spot
    if "peer" in sections:
        report["mitsuba"] = run_peer(args, device, spot)
    elif not args.no_peer and common.mitsuba_version() == "not installed":
        report["mitsuba"] = "not installed"
    if "memory" in sections:
        report["memory_check"] = run_memory_check(args, device, grid)
    report["environment"]["load_average_at_end"] = common.load_average()
    report["wall_s"] = round(time.perf_counter() - started, 1)
    text = json.dumps(report, indent=2)
    print(text, flush=True)
    if args.out:
        common.write_json_atomic(args.out, report)
    return report


if __name__ == "__main__":
    main()

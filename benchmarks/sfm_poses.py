"""Plain-folder SfM poses against the published ones: ../shared/captures/ethiopian_head.

Copies every --every-th photo of the capture (with its mask, without poses) into a plain folder
under --out, lets recon estimate its poses by structure from motion (recon.io.sfm: pycolmap,
SIFT on the masked object, exhaustive matching, incremental mapper, one SIMPLE_RADIAL camera),
and compares them with the published LLFF poses of the same photos: after a similarity
alignment of the camera centres (Umeyama), each camera's rotation error in degrees and centre
error (in the published units and as a share of the orbit's radius), and the focal lengths.
Then (unless --no-fit) it fits both folders, the SfM one and an LLFF copy of the same photos
with the published poses (only the photos SfM registered), with configs/real_capture.yaml (plus --set overrides, the same for
both) and reports the held-out masked PSNR of each and their difference. Prints one JSON object;
--json also writes it. Run from the repository root:

    recon-bench sfm-poses [--every 2] [--out runs/bench_sfm] [--set key=value ...] [--no-fit]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from dataclasses import replace
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

from benchmarks import common
from recon.io.run_folder import RunPaths

REPO_ROOT = Path(__file__).resolve().parents[1]
DEFAULT_DATA = REPO_ROOT.parent / "shared" / "captures" / "ethiopian_head"


def umeyama(source: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(scale, rotation [3, 3], translation [3]) minimising |target - (s R source + t)|^2 over
    points [N, 3] (Umeyama 1991)."""
    source_mean, target_mean = source.mean(0), target.mean(0)
    source_centred, target_centred = source - source_mean, target - target_mean
    covariance = target_centred.T @ source_centred / len(source)
    left, singular, right = np.linalg.svd(covariance)
    sign = np.eye(3)
    if np.linalg.det(left) * np.linalg.det(right) < 0:
        sign[2, 2] = -1.0
    rotation = left @ sign @ right
    variance = (source_centred**2).sum() / len(source)
    scale = float(np.trace(np.diag(singular) @ sign) / variance)
    translation = target_mean - scale * rotation @ source_mean
    return scale, rotation, translation


def pose_errors(published, estimated) -> dict:
    """Rotation and centre errors of estimated cameras against published ones (same order),
    after aligning the estimated centres to the published ones by a similarity."""
    published_w2c = published.world_to_cam.double().numpy()
    estimated_w2c = estimated.world_to_cam.double().numpy()

    def centres(world_to_cam: np.ndarray) -> np.ndarray:
        rotation, translation = world_to_cam[:, :3, :3], world_to_cam[:, :3, 3]
        return -np.einsum("nji,nj->ni", rotation, translation)

    truth, guess = centres(published_w2c), centres(estimated_w2c)
    scale, rotation, translation = umeyama(guess, truth)
    aligned = scale * guess @ rotation.T + translation
    centre_error = np.linalg.norm(aligned - truth, axis=1)
    radius = float(np.linalg.norm(truth - truth.mean(0), axis=1).mean())
    # World-to-camera rotation in the published world: R_sfm R_align^T.
    relative = published_w2c[:, :3, :3] @ (estimated_w2c[:, :3, :3] @ rotation.T).transpose(0, 2, 1)
    cosine = np.clip((np.trace(relative, axis1=1, axis2=2) - 1) / 2, -1.0, 1.0)
    angle = np.degrees(np.arccos(cosine))
    return {
        "cameras": len(truth),
        "rotation_error_deg": {
            "median": round(float(np.median(angle)), 3),
            "max": round(float(angle.max()), 3),
        },
        "centre_error": {
            "median": round(float(np.median(centre_error)), 4),
            "max": round(float(centre_error.max()), 4),
            "median_share_of_orbit_radius": round(float(np.median(centre_error)) / radius, 4),
        },
        "orbit_radius": round(radius, 4),
        "alignment_scale": round(scale, 4),
        "focal_px": {
            "published": round(float(published.intrinsics[0, 0, 0]), 2),
            "estimated": round(float(estimated.intrinsics[0, 0, 0]), 2),
        },
    }


def copy_photos(source: Path, folder: Path, names: list[str]) -> None:
    """folder/images and folder/masks with the named photos of source and their masks."""
    masks = {Path(name).stem: name for name in os.listdir(source / "masks")}
    (folder / "images").mkdir(parents=True, exist_ok=True)
    (folder / "masks").mkdir(exist_ok=True)
    for name in names:
        mask = masks[Path(name).stem]
        shutil.copy(source / "images" / name, folder / "images" / name)
        shutil.copy(source / "masks" / mask, folder / "masks" / mask)


def published_copy(source: Path, folder: Path, stems: list[str]) -> None:
    """An LLFF folder with the photos of these stems, their masks and their published poses."""
    table = np.load(source / "poses_bounds.npy")
    every = sorted(path.name for path in (source / "images").iterdir())
    rows = [index for index, name in enumerate(every) if Path(name).stem in set(stems)]
    copy_photos(source, folder, [every[index] for index in rows])
    np.save(folder / "poses_bounds.npy", table[rows])


def fit(data: Path, run: Path, overrides: list[str], threads: int) -> dict:
    """recon fit configs/real_capture.yaml --data data --out run (fit, evaluate, report)."""
    environment = dict(os.environ)
    for key in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        environment[key] = str(threads)
    command = [sys.executable, "-m", "recon.cli", "fit", "configs/real_capture.yaml"]
    command += ["--data", str(data), "--out", str(run), "--force", "--device", "cpu"]
    for override in overrides:
        command += ["--set", override]
    started = time.perf_counter()
    completed = subprocess.run(
        command, cwd=REPO_ROOT, env=environment, capture_output=True, text=True
    )
    seconds = time.perf_counter() - started
    if completed.returncode != 0:
        return {"error": completed.stderr[-1500:], "returncode": completed.returncode}
    metrics = json.loads(RunPaths(run).metrics.read_text())
    return {
        "psnr_masked": round(metrics["image"]["psnr_masked"], 3),
        "psnr": round(metrics["image"]["psnr"], 3),
        "test_views": metrics["views"],
        "faces": metrics["mesh"]["faces"],
        "genus": metrics["mesh"]["genus"],
        "seconds": round(seconds, 1),
        "load_average": common.load_average(),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", default=str(DEFAULT_DATA))
    parser.add_argument("--out", default="runs/bench_sfm")
    parser.add_argument("--every", type=int, default=2, help="use every N-th photo")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--set", action="append", default=[], help="fit override key=value")
    parser.add_argument("--no-fit", action="store_true", help="poses only")
    parser.add_argument("--json", help="also write the result here")
    arguments = parser.parse_args(argv)
    source, out = Path(arguments.data), Path(arguments.out)
    if not (source / "poses_bounds.npy").exists():
        print(json.dumps({"error": f"{source}: no poses_bounds.npy (is ../shared present?)"}))
        return 2
    common.configure_threads(arguments.threads)
    from recon.config.run_config import DatasetConfig
    from recon.io.datasets import read_captures, read_llff

    if out.exists():
        shutil.rmtree(out)
    every = sorted(path.name for path in (source / "images").iterdir())
    names = every[:: arguments.every]
    plain, llff = out / "photos", out / "published"
    copy_photos(source, plain, names)
    result: dict = {
        "date": datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "data": str(source),
        "photos": len(names),
        "every": arguments.every,
        "resolution": "as stored (384 x 384)",
        "load_average_start": common.load_average(),
    }
    started = time.perf_counter()
    # Every registered photo: the test split (the first one) and the training split.
    options = DatasetConfig(holdout_every=10**6, max_resolution=None)
    held_out = read_captures(plain, "test", options)
    training = read_captures(plain, "train", options)
    estimated = replace(
        training,
        cameras=replace(
            training.cameras,
            world_to_cam=torch.cat([held_out.cameras.world_to_cam, training.cameras.world_to_cam]),
            intrinsics=torch.cat([held_out.cameras.intrinsics, training.cameras.intrinsics]),
        ),
        names=held_out.names + training.names,
    )
    result["sfm_seconds"] = round(time.perf_counter() - started, 1)
    result["registered"] = len(estimated.names)
    published = read_llff(source)
    index = {name: position for position, name in enumerate(published.names)}
    chosen = [index[name] for name in estimated.names]
    result["poses"] = pose_errors(published.cameras[torch.tensor(chosen)], estimated.cameras)
    result["load_average_after_sfm"] = common.load_average()
    if not arguments.no_fit:
        # The published poses of the photos SfM registered: both fits see the same photos.
        published_copy(source, llff, estimated.names)
        held_out = {
            "published": read_captures(llff, "test", DatasetConfig(max_resolution=64)).names,
            "sfm": read_captures(plain, "test", DatasetConfig(max_resolution=64)).names,
        }
        result["held_out_views"] = held_out
        result["overrides"] = arguments.set
        result["fit_published"] = fit(llff, out / "run_published", arguments.set, arguments.threads)
        result["fit_sfm"] = fit(plain, out / "run_sfm", arguments.set, arguments.threads)
        first, second = result["fit_published"], result["fit_sfm"]
        if "psnr_masked" in first and "psnr_masked" in second:
            result["psnr_masked_difference_sfm_minus_published"] = round(
                second["psnr_masked"] - first["psnr_masked"], 3
            )
    text = json.dumps(result, indent=2)
    print(text)
    if arguments.json:
        common.write_json_atomic(arguments.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Collect the evidence of one blind case: synthesise (or derive) its data, fit without effects,
diagnose without reading the truth. Scoring comes later (benchmarks.blind.score), with
thresholds calibrated on other scenes: the evidence is collected once and re-decided.

Layout under the benchmark folder OUT:
    OUT/configs/WORLD_SCENE.yaml            the case config without its seed (synthetic worlds)
    OUT/cases/WORLD/SCENE/LABEL_seedN/      the run folder (dataset/, fit, diagnosis.json)
        bench_case.json                     config hash, fit and diagnosis seconds
    OUT/real_datasets/LABEL_seedN/          derived real-photo datasets (LLFF)
    OUT/truth/WORLD__SCENE__LABEL_seedN.json   the withheld truth (never inside a run folder)
A case whose bench_case.json matches its config hash and refit mode is not run again.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import torch
import yaml

from benchmarks.blind.cases import SHARED, BlindCase, case_config
from recon.config import config_hash, dump_resolved, load_config, to_dict
from recon.config.run_config import RunConfig
from recon.errors import ReconError
from recon.io.atomic import atomic_write_json, atomic_write_text
from recon.io.run_folder import RunPaths, open_run_folder, prepare_run_folder


@dataclass
class RealOptions:
    """How the real-photo world is made: the capture folder, the size the photos are read at,
    which views are kept, and the fit config (configs/real_capture.yaml's settings scaled)."""

    source: Path = SHARED / "captures" / "ethiopian_head"
    config: Path = Path(__file__).resolve().parents[2] / "configs" / "bench" / "blind_real.yaml"
    max_resolution: int = 96
    view_every: int = 2


def truth_path(out: Path, case: BlindCase) -> Path:
    return out / "truth" / (case.folder_name.replace("/", "__") + ".json")


def _stored(
    record_path: Path,
    digest: str,
    refit: str,
    paths: RunPaths,
    config: RunConfig,
    device,
    candidates: list[str] | None = None,
    ignore: tuple[str, ...] = (),
    rediagnose: bool = False,
) -> dict | None:
    """The case's stored record when its fit was made under the same config (digest): as it is
    when its diagnosis ran with the same refit mode, else (or with rediagnose: the diagnosis
    code changed) diagnosed again on the same fit."""
    if not record_path.exists():
        return None
    record = json.loads(record_path.read_text())
    if not paths.fitted_mesh.exists():
        if rediagnose:
            raise ReconError(f"--rediagnose: no stored fit in {paths.root}")
        return None
    if record.get("config_hash") != digest:
        difference = fit_config_difference(paths.resolved_config, config, ignore)
        if difference is not None:
            if rediagnose:
                # --rediagnose never fits: a stored fit that no longer matches is an error to
                # see (e.g. a mesh path that moved with the checkout), not a silent refit.
                raise ReconError(
                    f"--rediagnose: the stored fit in {paths.root} was made under another "
                    f"config ({difference}); run without --rediagnose to fit it again"
                )
            return None
        # Fields added to the schema since, all at their defaults: the same fit. The record
        # takes the new hash so the next run finds it at once.
        record["config_hash"] = digest
    same = record.get("refit") == refit and record.get("candidates") == candidates
    if same and paths.diagnosis.exists() and not rediagnose:
        return record
    record["diagnose_seconds"] = round(_diagnose(paths, config, device, refit, candidates), 2)
    record["refit"], record["candidates"] = refit, candidates
    atomic_write_json(record_path, record)
    return record


def fit_config_difference(
    stored_path: Path, config: RunConfig, ignore: tuple[str, ...] = ()
) -> str | None:
    """How a fit made under the resolved config at stored_path differs from the fit config
    would make (the first differing key, with both values), or None when it is the same fit.

    The config hash changes whenever the schema gains a field (e.g. a new fit option), which
    would refit every stored case although nothing it reads changed. A fit is the same when every
    key the stored config holds has the same value now (the diagnose section aside) and every key
    it lacks is at the schema's default: a field added with a default keeps the old behaviour.
    ignore: top-level keys left out besides diagnose (the real world's `data`, a path under the
    benchmark folder that changes when the folder is copied; its content is the case's own).
    """
    if not stored_path.exists():
        return f"{stored_path} not found"
    stored = yaml.safe_load(stored_path.read_text()) or {}
    current, defaults = to_dict(config), to_dict(RunConfig())
    for key in ("diagnose", *ignore):
        stored.pop(key, None)
        current.pop(key, None)
    # A Lambertian fit never reads the pbr material's settings: a changed pbr default (e.g. the
    # environment's size) is the same Lambertian fit.
    stored_fit, current_fit = stored.get("fit", {}), current.get("fit", {})
    if stored_fit.get("material", "lambert") == current_fit.get("material") == "lambert":
        stored_fit.pop("pbr", None)
        current_fit.pop("pbr", None)
    return _difference(stored, current, defaults, "")


def same_fit_config(stored_path: Path, config: RunConfig, ignore: tuple[str, ...] = ()) -> bool:
    """Whether the stored fit is the fit config would make (fit_config_difference is None)."""
    return fit_config_difference(stored_path, config, ignore) is None


def _difference(stored, current, defaults, path: str) -> str | None:
    """The first key where stored and current differ (current's keys absent from stored must
    equal defaults), recursively; None when they agree."""
    if not (isinstance(stored, dict) and isinstance(current, dict)):
        return None if stored == current else f"{path}: stored {stored!r}, now {current!r}"
    for key, value in current.items():
        where = f"{path}.{key}" if path else key
        default = defaults.get(key) if isinstance(defaults, dict) else None
        if key not in stored:
            if value != default:
                return f"{where}: absent from the stored config, now {value!r}"
            continue
        found = _difference(stored[key], value, default, where)
        if found:
            return found
    extra = sorted(set(stored) - set(current))
    return f"{path}.{extra[0]}: stored, no longer in the schema" if extra else None


def located(record: dict, case: BlindCase, out: Path) -> dict:
    """record with its paths where the case lives now, under out: a benchmark folder copied
    elsewhere keeps the old paths in its records, and scoring must read this folder's
    diagnosis (a copy of b48v8 once scored b48v8's)."""
    record = {
        **record,
        "run_folder": str(out / "cases" / case.folder_name),
        "truth_file": str(truth_path(out, case)),
    }
    if "dataset" in record:
        record["dataset"] = str(out / "real_datasets" / f"{case.label}_seed{case.seed}")
    return record


def finished_case(case: BlindCase, out: Path) -> dict | None:
    """The stored record of a case collected earlier (whatever its config), or None."""
    record_path = out / "cases" / case.folder_name / "bench_case.json"
    if not record_path.exists() or not RunPaths(record_path.parent).diagnosis.exists():
        return None
    return located(json.loads(record_path.read_text()), case, out)


def _diagnose(
    paths: RunPaths,
    config: RunConfig,
    device: torch.device,
    refit: str,
    candidates: list[str] | None = None,
) -> float:
    """Diagnose a fitted case (candidates: the effects considered, None = all); its seconds."""
    from recon.stages.diagnose import run_diagnosis

    started = time.perf_counter()
    run_diagnosis(paths, config, device, refit=refit, candidates=candidates)
    return time.perf_counter() - started


def _complete_calibration_splits(folder: Path, config: RunConfig, truth: Path) -> None:
    """A stored case made before the config asked for calibration frames takes them now: the
    fit never reads them, so its fit stays the new config's, and the frames are the ones a
    fresh synth writes (data_synth.calibration_splits)."""
    from data_synth.calibration_splits import CALIBRATION_SPLITS, add_calibration_split

    paths = open_run_folder(folder)
    if not paths.resolved_config.exists() or not paths.dataset.is_dir():
        return
    for split in CALIBRATION_SPLITS:
        views = getattr(config.capture, split).views
        if views and not paths.dataset_layout.split_file(split).is_file():
            add_calibration_split(folder, split, views, truth)


def collect_synthetic(
    case: BlindCase,
    base: dict,
    out: Path,
    device: torch.device,
    refit: str,
    candidates: list[str] | None = None,
    rediagnose: bool = False,
) -> dict:
    """Synth (effects withheld) -> fit -> diagnose one case of the own or Mitsuba world."""
    from recon.pipeline import run_stages

    folder = out / "cases" / case.folder_name
    config_file = out / "configs" / f"{case.world}_{case.scene}.yaml"
    config_file.parent.mkdir(parents=True, exist_ok=True)
    config_dict = case_config(base, case)
    text = yaml.safe_dump({**config_dict, "seed": 0})
    if not config_file.exists() or config_file.read_text() != text:
        atomic_write_text(config_file, text)
    config = load_config(config_file, RunConfig, overrides=[f"seed={case.seed}"])
    digest = config_hash(config, exclude=("diagnose",))
    record_path = folder / "bench_case.json"
    if record_path.exists():
        _complete_calibration_splits(folder, config, truth_path(out, case))
        stored = _stored(
            record_path,
            digest,
            refit,
            open_run_folder(folder),
            config,
            device,
            candidates,
            rediagnose=rediagnose,
        )
        if stored is not None:
            return located(stored, case, out)
    if rediagnose:
        raise ReconError(f"--rediagnose: no stored case in {folder}")
    truth = truth_path(out, case)
    paths = prepare_run_folder(folder, force=True)
    dump_resolved(config, paths.resolved_config)
    options = {"withhold_effects": list(case.withheld), "truth_out": truth} if case.withheld else {}
    started = time.perf_counter()
    run_stages(config, paths, device, ["synth", "fit"], {"synth": options})
    fit_seconds = time.perf_counter() - started
    if not case.withheld:
        atomic_write_json(truth, {"withheld": [], "realised": {}})
    diagnose_seconds = _diagnose(paths, config, device, refit, candidates)
    record = {
        "case": case.to_json(),
        "config_hash": digest,
        "refit": refit,
        "candidates": candidates,
        "run_folder": str(folder),
        "truth_file": str(truth),
        "fit_seconds": round(fit_seconds, 2),
        "diagnose_seconds": round(diagnose_seconds, 2),
    }
    atomic_write_json(record_path, record)
    return record


def collect_real(
    case: BlindCase,
    options: RealOptions,
    out: Path,
    device: torch.device,
    refit: str,
    candidates: list[str] | None = None,
    rediagnose: bool = False,
) -> dict:
    """Derive the photos with the case's effects injected -> fit (LLFF, the real-capture
    settings) -> diagnose."""
    from benchmarks.blind.real import derive_real_dataset
    from recon.pipeline import run_stages

    folder = out / "cases" / case.folder_name
    dataset = out / "real_datasets" / f"{case.label}_seed{case.seed}"
    config = load_config(
        options.config,
        RunConfig,
        overrides=[
            f"data={dataset}",
            f"seed={case.seed}",
            f"dataset.max_resolution={options.max_resolution}",
        ],
    )
    digest = config_hash(config, exclude=("diagnose",))
    record_path = folder / "bench_case.json"
    if dataset.is_dir() and record_path.exists():
        stored = _stored(
            record_path,
            digest,
            refit,
            open_run_folder(folder, dataset),
            config,
            device,
            candidates,
            ignore=("data",),
            rediagnose=rediagnose,
        )
        if stored is not None:
            return located(stored, case, out)
    if rediagnose:
        raise ReconError(f"--rediagnose: no stored case in {folder}")
    truth = truth_path(out, case)
    derive_real_dataset(
        options.source,
        dataset,
        truth,
        list(case.withheld),
        case.seed,
        options.max_resolution,
        options.view_every,
        config.dataset.holdout_every,
    )
    started_paths = prepare_run_folder(folder, force=True)
    paths = RunPaths(started_paths.root, dataset)
    dump_resolved(config, paths.resolved_config)
    started = time.perf_counter()
    run_stages(config, paths, device, ["fit"], {})
    fit_seconds = time.perf_counter() - started
    diagnose_seconds = _diagnose(
        open_run_folder(folder, dataset), config, device, refit, candidates
    )
    record = {
        "case": case.to_json(),
        "config_hash": digest,
        "refit": refit,
        "candidates": candidates,
        "run_folder": str(folder),
        "dataset": str(dataset),
        "truth_file": str(truth),
        "fit_seconds": round(fit_seconds, 2),
        "diagnose_seconds": round(diagnose_seconds, 2),
    }
    atomic_write_json(record_path, record)
    return record

"""The report's figures (matplotlib) and its Markdown and HTML text, the diagnosis's tables and
one-line parameter summaries. The report stage (recon/stages/report.py) gathers what the run
folder holds and writes report.html / report.md."""

from __future__ import annotations

import html
import math
from pathlib import Path

import matplotlib
import matplotlib.pyplot as plt
import torch

from recon.camera import Cameras, intrinsics_from_fov, look_at
from recon.io.atomic import atomic_path
from recon.io.images import save_contact_sheet
from recon.mesh.mesh import Mesh
from recon.metrics.evaluate import ERROR_PANEL_MAXIMUM
from recon.optimize.material_stage import PbrTextureResult
from recon.render.renderer import Renderer
from recon.render.shading import Lighting

matplotlib.use("Agg")


def _save_figure(figure, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as temporary:
        figure.savefig(temporary, dpi=110, bbox_inches="tight", format="png")
    plt.close(figure)


def loss_figure(records: list[dict], path: Path) -> None:
    """Loss and training PSNR per step, both stages, one curve each."""
    figure, (loss_axis, psnr_axis) = plt.subplots(1, 2, figsize=(10, 3.5))
    offset = 0
    for stage in ("geometry", "texture"):
        stage_records = [record for record in records if record["stage"] == stage]
        if not stage_records:
            continue
        steps = [offset + record["step"] for record in stage_records]
        loss_axis.plot(steps, [record["loss"] for record in stage_records], label=stage)
        psnr_axis.plot(steps, [record["psnr_linear"] for record in stage_records], label=stage)
        offset = steps[-1] + 1
    loss_axis.set_yscale("log")
    loss_axis.set_xlabel("step")
    loss_axis.set_ylabel("loss")
    loss_axis.legend()
    psnr_axis.set_xlabel("step")
    psnr_axis.set_ylabel("training PSNR, linear (dB)")
    psnr_axis.legend()
    _save_figure(figure, path)


def framing_cameras(
    mesh: Mesh,
    count: int,
    size: int,
    up: list[float] | None = None,
    elevation_deg: float = 20.0,
    fov_x_deg: float = 40.0,
) -> Cameras:
    """count cameras on a ring around the mesh's bounding-box centre, about `up` (default +y),
    far enough that the bounding sphere fills about 80 % of the frame: the object is in view
    wherever the dataset put it and whichever way is up."""
    verts = mesh.verts.detach().cpu().float()
    centre = (verts.amax(0) + verts.amin(0)) / 2
    radius = max(float((verts - centre).norm(dim=-1).max()), 1e-6)
    distance = radius / math.sin(math.radians(fov_x_deg) / 2) / 0.8
    up_vector = torch.nn.functional.normalize(torch.tensor(up or [0.0, 1.0, 0.0]).float(), dim=0)
    helper = (
        torch.tensor([1.0, 0.0, 0.0])
        if abs(float(up_vector[0])) < 0.9
        else torch.tensor([0.0, 0.0, 1.0])
    )
    first = torch.nn.functional.normalize(torch.linalg.cross(up_vector, helper, dim=0), dim=0)
    second = torch.linalg.cross(first, up_vector, dim=0)
    azimuth = torch.arange(count, dtype=torch.float32) * (2 * math.pi / count)
    elevation = math.radians(elevation_deg)
    directions = (
        math.cos(elevation)
        * (torch.cos(azimuth)[:, None] * second + torch.sin(azimuth)[:, None] * first)
        + math.sin(elevation) * up_vector
    )
    eyes = centre + distance * directions
    world_to_cam = look_at(eyes, centre.expand_as(eyes), up=tuple(up_vector.tolist()))
    intrinsics = intrinsics_from_fov(fov_x_deg, (size, size))
    return Cameras(world_to_cam, intrinsics, (size, size), near=0.05 * distance, far=3 * distance)


def turntable(
    mesh: Mesh,
    lighting: Lighting,
    path: Path,
    device: torch.device,
    up: list[float] | None = None,
    pbr: PbrTextureResult | None = None,
) -> None:
    """Eight views around the fitted mesh in one sheet, framed by its bounds about `up`: with
    the Lambertian model under lighting, or, for a `pbr` fit (pbr given: its mesh, material maps
    and environment), with the material the fit found, as the held-out renders are."""
    cameras = framing_cameras(mesh, 8, 192, up).to(device)
    with torch.no_grad():
        if pbr is None:
            output = Renderer().render(mesh.to(device), cameras, lighting, background=1.0)
        else:
            output = pbr.render(Renderer(), cameras, background=1.0)
    save_contact_sheet(list(output.color.cpu()), path, columns=4)


# Held-out figures show each panel at least this many pixels wide, however small the photos.
HELD_OUT_PANEL_PIXELS = 320


def held_out_figure(panel_path: Path, path: Path) -> None:
    """A held-out view (evaluate's target | render | error PNG [H, 3W, 3]) as a figure: the
    three panels titled, about HELD_OUT_PANEL_PIXELS wide each at least, and the error panel
    with its colour bar (|sRGB error|, magma, 0 .. ERROR_PANEL_MAXIMUM)."""
    from PIL import Image

    with Image.open(panel_path) as image:
        pixels = image.convert("RGB")
        width, height = pixels.size
        panel_width = width // 3
        panels = [
            pixels.crop((k * panel_width, 0, (k + 1) * panel_width, height)) for k in range(3)
        ]
    dpi = 110
    panel_inches = max(panel_width, HELD_OUT_PANEL_PIXELS) / dpi
    figure, axes = plt.subplots(
        1, 3, figsize=(3 * panel_inches + 1.0, panel_inches * height / panel_width + 0.5)
    )
    for axis, panel, title in zip(axes, panels, ("photo", "render", "error"), strict=True):
        axis.imshow(panel, interpolation="nearest")
        axis.set_title(title)
        axis.set_axis_off()
    # The error panel is already colour-mapped: a colour bar with the same map and range.
    scale = matplotlib.cm.ScalarMappable(
        norm=matplotlib.colors.Normalize(0.0, ERROR_PANEL_MAXIMUM), cmap="magma"
    )
    bar = figure.colorbar(scale, ax=axes[2], fraction=0.046, pad=0.04)
    bar.set_label("|sRGB error| (mean over channels)")
    _save_figure(figure, path)


def geometry_error_figure(
    mesh: Mesh,
    reference: Mesh,
    path: Path,
    device: torch.device,
    up: list[float] | None = None,
) -> None:
    """The fitted mesh coloured by its distance to the reference (viridis, 0 .. 1 % diagonal),
    four views framed by its bounds about `up`."""
    from recon.metrics.geometry import per_vertex_error

    error = per_vertex_error(mesh, reference).cpu()
    scale = 0.01
    colors = matplotlib.colormaps["viridis"]((error / scale).clamp(0, 1).numpy())[:, :3]
    colored = Mesh(mesh.verts, mesh.faces, vertex_colors=torch.tensor(colors, dtype=torch.float32))
    cameras = framing_cameras(mesh, 4, 200, up).to(device)
    with torch.no_grad():
        output = Renderer().render(
            colored.to(device), cameras, Lighting.constant(device=device), background=1.0
        )
    save_contact_sheet(list(output.color.cpu()), path, columns=4)


def _metric_rows(metrics: dict) -> list[tuple[str, str]]:
    rows = []
    for group in ("image", "geometry", "material", "mesh"):
        for key, value in metrics.get(group, {}).items():
            if isinstance(value, float):
                text = f"{value:.4g}"
            else:
                text = str(value)
            rows.append((f"{group}.{key}", text))
    for stage, seconds in metrics.get("stage_seconds", {}).items():
        rows.append((f"seconds.{stage}", f"{seconds:.1f}"))
    return rows


def render_report(
    name: str, metrics: dict, diagnosis: dict | None, figures: list[tuple[str, str]]
) -> tuple[str, str]:
    """The report as (Markdown, HTML) text: the metrics table (metrics.json's record), the
    diagnosis's verdict and tables when there is one, then each (title, relative link) figure."""
    rows = _metric_rows(metrics)
    diagnosis_markdown: list[str] = []
    if diagnosis is not None and "candidates" not in diagnosis:
        # Written before the typed records: its evidence re-decided into the current form.
        from recon.diagnose.decision import redecide

        diagnosis = redecide(diagnosis).to_json()
    if diagnosis is not None:
        rows.append(("diagnosis.verdict", diagnosis["verdict"]))
        diagnosis_markdown = ["", "## Gap diagnosis", "", f"Verdict: {diagnosis['verdict']}", ""]
        diagnosis_markdown += _markdown_table(*_ranking_table(diagnosis))
        if recovered_parameters(diagnosis):
            diagnosis_markdown += [""] + _markdown_table(*_parameter_table(diagnosis))
        if diagnosis.get("refits"):
            diagnosis_markdown += [""] + _markdown_table(*_refit_table(diagnosis))
    markdown = [f"# recon report: {name}", "", "| metric | value |", "|---|---|"]
    markdown += [f"| {key} | {value} |" for key, value in rows]
    markdown += diagnosis_markdown
    for title, link in figures:
        markdown += ["", f"## {title}", "", f"![{title}]({link})"]
    table = "".join(
        f"<tr><td>{html.escape(key)}</td><td>{html.escape(value)}</td></tr>" for key, value in rows
    )
    body = "".join(
        f"<h2>{html.escape(title)}</h2><img src='{html.escape(link)}' style='max-width:100%'>"
        for title, link in figures
    )
    if diagnosis_markdown:
        diagnosis_tables = [_ranking_table(diagnosis)]
        if recovered_parameters(diagnosis):
            diagnosis_tables.append(_parameter_table(diagnosis))
        if diagnosis.get("refits"):
            diagnosis_tables.append(_refit_table(diagnosis))
        body = (
            "<h2>Gap diagnosis</h2>"
            f"<p>Verdict: {html.escape(diagnosis['verdict'])}</p>"
            + "".join(_html_table(*table) for table in diagnosis_tables)
            + body
        )
    page = (
        "<!doctype html><html><head><meta charset='utf-8'>"
        f"<title>recon report: {html.escape(name)}</title>"
        "<style>body{font-family:sans-serif;max-width:1100px;margin:auto}"
        "td{padding:2px 12px;border-bottom:1px solid #ddd}</style></head><body>"
        f"<h1>recon report: {html.escape(name)}</h1><table>{table}</table>{body}"
        "</body></html>"
    )
    return "\n".join(markdown) + "\n", page


def _ranking_table(diagnosis: dict) -> tuple[list[str], list[list[str]]]:
    """The diagnosis' candidates, best first, as (header, rows) of text cells: the deciding
    evidence, the probe's held-out reduction and interval, the absorption and relight
    reductions, and why it is or is not significant."""
    from recon.diagnose.records import Candidate

    header = [
        "candidate",
        "evidence",
        "held-out reduction",
        "interval",
        "absorption",
        "relight",
        "significant",
        "why",
    ]
    rows = []
    for record in diagnosis["candidates"]:
        candidate = Candidate.from_json(record)
        probe = candidate.evidence_of("probe")
        reduction, interval = "", ""
        if probe is not None:
            low, high = probe.interval
            reduction, interval = f"{probe.details['reduction']:.3f}", f"[{low:.3f}, {high:.3f}]"
        absorption = candidate.evidence_of("absorption")
        absorption_cell = "" if absorption is None else f"{absorption.details['reduction']:.3f}"
        if absorption is not None and absorption.void:
            # Measured alone, voided on top of the conditioning effect (it does not decide).
            absorption_cell += f" (void beside {absorption.details.get('discounted_by')})"
        relight = candidate.evidence_of("relight")
        rows.append(
            [
                candidate.name,
                candidate.decided_by,
                reduction,
                interval,
                absorption_cell,
                "" if relight is None else f"{relight.details['reduction']:.3f}",
                "yes"
                if candidate.significant
                else candidate.status.replace("_", " ")
                if candidate.status in ("vetoed", "not_identifiable")
                else "",
                candidate.why,
            ]
        )
    return header, rows


# Strings longer than this in a parameter set are explanations ("model", "radius_unit"), kept
# in diagnosis.json but left out of the one-line summaries.
_SHORT_TEXT = 24


def summarise_parameters(parameters: dict) -> str:
    """One line for an effect's recovered parameters: numbers to three significant digits, a
    list of numbers (per view) as its range and count, short strings as they are; explanations
    and nested lists are left to diagnosis.json."""
    parts = []
    for key, value in parameters.items():
        if isinstance(value, bool) or value is None:
            continue
        if isinstance(value, int | float):
            parts.append(f"{key} {value:.3g}")
        elif (
            isinstance(value, list)
            and value
            and all(isinstance(item, int | float) and not isinstance(item, bool) for item in value)
        ):
            parts.append(f"{key} {min(value):.3g}..{max(value):.3g} ({len(value)})")
        elif isinstance(value, str) and len(value) <= _SHORT_TEXT:
            parts.append(f"{key} {value}")
    return ", ".join(parts)


def recovered_parameters(
    diagnosis: dict, significant_only: bool = True
) -> list[tuple[str, str, dict]]:
    """(effect, source, parameters) per ranked effect (the significant ones only, by default):
    from the first refit that switched it on ("refit": fitted with the scene on the training
    views) when there is one, else from the deciding evidence (its name: held-out views, scene
    frozen). The blind benchmark scores the same choice (recon.sweep.scoring)."""
    from_refits: dict = {}
    for refit in reversed(diagnosis.get("refits", [])):
        from_refits.update(refit.get("parameters", {}))
    recovered = []
    for item in diagnosis["candidates"]:
        if significant_only and not item["significant"]:
            continue
        if item["name"] in from_refits:
            recovered.append((item["name"], "refit", from_refits[item["name"]]))
        else:
            recovered.append((item["name"], item.get("decided_by", ""), item.get("parameters", {})))
    return recovered


def _parameter_table(diagnosis: dict) -> tuple[list[str], list[list[str]]]:
    """The significant effects' recovered parameters as (header, rows) of text cells."""
    rows = [
        [effect, source, summarise_parameters(parameters)]
        for effect, source, parameters in recovered_parameters(diagnosis)
    ]
    return ["effect", "from", "recovered parameters"], rows


def _refit_table(diagnosis: dict) -> tuple[list[str], list[list[str]]]:
    """The refits (how far the gap shrinks) as (header, rows) of text cells."""
    header = [
        "refit with",
        "RMSE before",
        "RMSE after",
        "floor RMSE",
        "gap above floor closed",
        "relight split closed",
    ]
    rows = [
        [
            " + ".join(refit["effects"]),
            f"{refit['before_rmse']:.4f}",
            f"{refit['after_rmse']:.4f}",
            f"{refit['floor'] ** 0.5:.4f}",
            f"{100 * refit['closed_fraction']:.0f} %",
            f"{100 * refit['relight_closed_fraction']:.0f} %"
            if "relight_closed_fraction" in refit
            else "",
        ]
        for refit in diagnosis["refits"]
    ]
    return header, rows


def _markdown_table(header: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(row) + " |" for row in rows]


def _html_table(header: list[str], rows: list[list[str]]) -> str:
    head = "".join(f"<th>{html.escape(cell)}</th>" for cell in header)
    body = "".join(
        "<tr>" + "".join(f"<td>{html.escape(cell)}</td>" for cell in row) + "</tr>" for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"

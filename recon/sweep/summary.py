"""summary.html: the results table and plots (each metric vs each swept parameter; a confusion
matrix of withheld truth vs diagnosed effect for diagnosis sweeps), PNGs inlined so the page is
one self-contained file."""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from recon.io.atomic import atomic_write_text  # noqa: E402
from recon.sweep.results import columns, format_cell, row  # noqa: E402


def _png(figure) -> str:
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=100, bbox_inches="tight")
    plt.close(figure)
    return base64.b64encode(buffer.getvalue()).decode()


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def metric_plot(records: list[dict], metric: str, parameter: str) -> str | None:
    """metric vs parameter: every trial as a dot, the mean per value as a line (numeric
    parameters) or per category; None when nothing numeric to plot."""
    points = [
        (record["parameters"].get(parameter), record["metrics"].get(metric))
        for record in records
        if record["status"] == "ok"
    ]
    points = [(x, y) for x, y in points if _is_number(y) or isinstance(y, bool)]
    if not points:
        return None
    numeric = all(_is_number(x) for x, _ in points)
    labels = sorted({x for x, _ in points}) if numeric else sorted({str(x) for x, _ in points})
    position = {label: index for index, label in enumerate(labels)}
    figure, axes = plt.subplots(figsize=(4.5, 3.2))
    xs = [x if numeric else position[str(x)] for x, _ in points]
    ys = [float(y) for _, y in points]
    axes.scatter(xs, ys, s=18, alpha=0.7, label="trials")
    means = []
    for label in labels:
        values = [float(y) for x, y in points if (x if numeric else str(x)) == label]
        means.append(sum(values) / len(values))
    axes.plot(labels if numeric else range(len(labels)), means, color="C1", label="mean")
    if not numeric:
        axes.set_xticks(range(len(labels)), labels, rotation=30, ha="right")
    axes.set_xlabel(parameter)
    axes.set_ylabel(metric)
    axes.legend(fontsize=7)
    return _png(figure)


def confusion_plot(records: list[dict]) -> str | None:
    """Rows: the withheld truth ('none' for clean cases); columns: the diagnosis's top effect."""
    pairs = [
        ("+".join(record["diagnosis"]["truth"]) or "none", record["diagnosis"]["predicted_top"])
        for record in records
        if record["status"] == "ok" and "diagnosis" in record
    ]
    if not pairs:
        return None
    truths = sorted({truth for truth, _ in pairs})
    predictions = sorted({prediction for _, prediction in pairs} | {"none"})
    counts = [[0] * len(predictions) for _ in truths]
    for truth, prediction in pairs:
        counts[truths.index(truth)][predictions.index(prediction)] += 1
    figure, axes = plt.subplots(figsize=(1.2 + 0.55 * len(predictions), 1.0 + 0.45 * len(truths)))
    axes.imshow(counts, cmap="Blues")
    for row_index, line in enumerate(counts):
        for column_index, count in enumerate(line):
            if count:
                axes.text(column_index, row_index, str(count), ha="center", va="center")
    axes.set_xticks(range(len(predictions)), predictions, rotation=40, ha="right")
    axes.set_yticks(range(len(truths)), truths)
    axes.set_xlabel("diagnosed (top significant)")
    axes.set_ylabel("withheld")
    return _png(figure)


def write_summary(out: Path, title: str, records: list[dict], metrics: list[str]) -> Path:
    """Write out/summary.html; returns its path."""
    parts = [
        "<!doctype html><html><head><meta charset='utf-8'>",
        f"<title>{html.escape(title)}</title>",
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;"
        "font-size:12px}td,th{border:1px solid #ccc;padding:2px 6px}"
        "img{margin:6px;vertical-align:top}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
    ]
    failed = [record for record in records if record["status"] != "ok"]
    parts.append(f"<p>{len(records)} trials, {len(failed)} failed.</p>")
    confusion = confusion_plot(records)
    if confusion:
        parts.append("<h2>Confusion matrix</h2>")
        parts.append(f"<img alt='confusion matrix' src='data:image/png;base64,{confusion}'>")
    swept = [
        key
        for key in dict.fromkeys(key for record in records for key in record["parameters"])
        if len({str(record["parameters"].get(key)) for record in records}) > 1
    ]
    if len(swept) > 1 and "seed" in swept:
        # Seeds are repeats, not a setting: their spread shows in the other plots' dots.
        swept.remove("seed")
    if swept:
        parts.append("<h2>Metrics vs parameters</h2>")
    for metric in metrics:
        for parameter in swept:
            image = metric_plot(records, metric, parameter)
            if image:
                alt = html.escape(f"{metric} vs {parameter}")
                parts.append(f"<img alt='{alt}' src='data:image/png;base64,{image}'>")
    names = columns(records, metrics)
    parts.append("<h2>Trials</h2><table><tr>")
    parts += [f"<th>{html.escape(name)}</th>" for name in names]
    parts.append("</tr>")
    for record in records:
        values = row(record, metrics)
        cells = "".join(f"<td>{html.escape(format_cell(values.get(n)))}</td>" for n in names)
        parts.append(f"<tr>{cells}</tr>")
    parts.append("</table></body></html>")
    path = out / "summary.html"
    atomic_write_text(path, "\n".join(parts) + "\n")
    return path

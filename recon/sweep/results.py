"""The sweep's tables, rewritten atomically after every trial: results.jsonl (one record per
finished trial), results.csv (one row per trial: parameters, metrics, status) and results.md."""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

from recon.io.atomic import atomic_write_text


def plain(value):
    """JSON-safe: NaN and infinity become None (they are not JSON)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {key: plain(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain(item) for item in value]
    return value


def columns(records: list[dict], metrics: list[str]) -> list[str]:
    parameters = []
    for record in records:
        for key in record["parameters"]:
            if key not in parameters:
                parameters.append(key)
    return ["trial_id", "status", *parameters, *metrics, "seconds", "error"]


def row(record: dict, metrics: list[str]) -> dict:
    values = {"trial_id": record["trial_id"], "status": record["status"]}
    values.update(record["parameters"])
    values.update({name: record["metrics"].get(name) for name in metrics})
    values["seconds"] = record.get("seconds")
    values["error"] = record.get("error") or ""
    return values


def format_cell(value) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, (list, dict)):
        return json.dumps(value)
    return str(value)


def write_results(out: Path, records: list[dict], metrics: list[str]) -> None:
    """results.jsonl, results.csv and results.md for the finished records (in trial order)."""
    lines = [json.dumps(plain(record), sort_keys=True) for record in records]
    atomic_write_text(out / "results.jsonl", "".join(line + "\n" for line in lines))
    names = columns(records, metrics)
    table = [row(record, metrics) for record in records]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=names, lineterminator="\n")
    writer.writeheader()
    for values in table:
        writer.writerow({key: format_cell(values.get(key)) for key in names})
    atomic_write_text(out / "results.csv", buffer.getvalue())
    failed = sum(record["status"] != "ok" for record in records)
    markdown = [
        f"# Sweep results ({len(records)} trials, {failed} failed)",
        "",
        "| " + " | ".join(names) + " |",
        "|" + "---|" * len(names),
    ]
    for values in table:
        cells = [format_cell(values.get(key)).replace("|", "\\|") for key in names]
        markdown.append("| " + " | ".join(cells) + " |")
    atomic_write_text(out / "results.md", "\n".join(markdown) + "\n")


def read_records(path: Path) -> list[dict]:
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text().splitlines() if line.strip()]

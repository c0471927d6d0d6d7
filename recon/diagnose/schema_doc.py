"""docs/diagnosis/schema.md, generated from the typed records (recon.diagnose.records).

    python -m recon.diagnose.schema_doc > docs/diagnosis/schema.md

A test (tests/diagnose/test_schema_doc.py) fails when the file is stale.
"""

from __future__ import annotations

import dataclasses
import sys
import typing

from recon.diagnose import records
from recon.diagnose.decision import DECISION_TABLE

REGENERATE_COMMAND = "python -m recon.diagnose.schema_doc > docs/diagnosis/schema.md"
RECORDS = (records.Diagnosis, records.Candidate, records.Evidence)


def _type_name(annotation) -> str:
    """A readable type: the annotation's text as written (the module uses postponed ones)."""
    return str(annotation).replace("typing.", "")


def _table(record: type) -> list[str]:
    hints = typing.get_type_hints(record, vars(records))
    lines = ["| field | type | meaning |", "|---|---|---|"]
    for item in dataclasses.fields(record):
        annotation = record.__annotations__.get(item.name, hints.get(item.name))
        doc = item.metadata.get("doc", "").replace("|", "\\|")
        lines.append(f"| `{item.name}` | `{_type_name(annotation)}` | {doc} |")
    return lines


def schema_markdown() -> str:
    """The whole schema page."""
    lines = [
        "# diagnosis.json",
        "",
        "Written by `recon diagnose` into the run folder (`RUN/diagnosis.json`): a `Diagnosis`",
        f"(schema_version {records.SCHEMA_VERSION}) with its `Candidate`s and their `Evidence`.",
        "The method behind each field is in [method.md](method.md). Generated from",
        f"`recon/diagnose/records.py` by `{REGENERATE_COMMAND}`; a test fails when it is stale.",
        "`recon.diagnose.decision.redecide(diagnosis_json, diagnose_config)` re-decides a stored",
        "diagnosis from its evidence.",
    ]
    for record in RECORDS:
        summary = (record.__doc__ or "").strip().splitlines()[0]
        lines += ["", f"## {record.__name__}", "", summary, ""]
        lines += _table(record)
    lines += [
        "",
        "## Evidence kinds",
        "",
        "The decision table (`recon/diagnose/decision.py`), in the order it is consulted:",
        "",
        "| kind | role | ranks as held-out or direct evidence |",
        "|---|---|---|",
    ]
    lines += [
        f"| `{rule.kind}` | {rule.role} | {'yes' if rule.measured else 'no'} |"
        for rule in DECISION_TABLE
    ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.stdout.write(schema_markdown())

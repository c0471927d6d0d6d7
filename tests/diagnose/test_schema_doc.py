"""docs/diagnosis/schema.md is generated from the typed records and must be current."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from recon.diagnose.records import Candidate, Diagnosis, Evidence
from recon.diagnose.schema_doc import REGENERATE_COMMAND, schema_markdown

SCHEMA_MD = Path(__file__).resolve().parents[2] / "docs" / "diagnosis" / "schema.md"


def test_every_record_field_has_a_doc():
    for record in (Diagnosis, Candidate, Evidence):
        undocumented = [f.name for f in dataclasses.fields(record) if not f.metadata.get("doc")]
        assert not undocumented, f"{record.__name__}: fields without a doc: {undocumented}"


def test_schema_md_is_current():
    actual = SCHEMA_MD.read_text(encoding="utf-8") if SCHEMA_MD.exists() else ""
    assert actual == schema_markdown(), f"{SCHEMA_MD} is stale; regenerate: {REGENERATE_COMMAND}"


def test_every_field_appears_in_the_page():
    text = schema_markdown()
    for record in (Diagnosis, Candidate, Evidence):
        assert f"## {record.__name__}" in text
        for field in dataclasses.fields(record):
            assert f"| `{field.name}` |" in text

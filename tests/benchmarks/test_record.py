"""Benchmark records (docs/bench/*.json): provenance, and the pages generated from them."""

from __future__ import annotations

import json
import re
import sys
import types

import pytest

from benchmarks import cli, record

PAGE_COMMAND = "PYTHONPATH=$PWD python -m benchmarks.cli docs"


def test_benchmarks_page_and_readme_summary_are_what_the_records_make():
    """docs/benchmarks.md and the README's summary are generated: edit a record (or measure
    with `recon-bench NAME --record`), then run `recon-bench docs`."""
    records = record.read_records()
    page = record.render_page(records, cli.BENCHMARKS)
    assert record.PAGE.read_text(encoding="utf-8") == page, f"stale: run {PAGE_COMMAND}"
    readme = record.README.read_text(encoding="utf-8")
    assert record.render_readme(readme, records) == readme, f"stale: run {PAGE_COMMAND}"


def test_every_record_names_commit_date_machine_and_config_hash():
    records = record.read_records()
    assert {"fit", "render", "diagnose"} <= {item["name"] for item in records}
    for item in records:
        provenance = item["provenance"]
        missing = [key for key in record.PROVENANCE_FIELDS if not provenance.get(key)]
        missing += [key for key in record.MACHINE_FIELDS if not provenance["machine"].get(key)]
        assert not missing, f"docs/bench/{item['name']}.json lacks {missing}"
        if provenance.get("recorded_before_provenance"):
            assert provenance.get("note"), f"{item['name']}: say where the figures came from"
        else:
            assert re.fullmatch(r"[0-9a-f]{12}", provenance["config_hash"])
            assert provenance["commit"] != "unknown"
        assert item["summary"] or item["notes"], f"{item['name']}: an empty section"


def test_the_fit_summary_reproduces_the_recorded_table():
    fit = next(item for item in record.read_records() if item["name"] == "fit")
    from benchmarks.fit import markdown

    assert markdown(fit["result"]) == fit["summary"]
    assert "| spot | 64 s | 32.43 dB | 0.988 | 7.0e-4 | 0.996 | 0.984 | 11,940 |" in fit["summary"]


@pytest.fixture
def docs_in(tmp_path, monkeypatch):
    """RECORDS, PAGE and README in tmp_path (the repository's are never written by tests)."""
    (tmp_path / "bench").mkdir()
    readme = tmp_path / "README.md"
    readme.write_text(f"# x\n\n{record.README_START}\n{record.README_END}\n")
    monkeypatch.setattr(record, "RECORDS", tmp_path / "bench")
    monkeypatch.setattr(record, "PAGE", tmp_path / "benchmarks.md")
    monkeypatch.setattr(record, "README", readme)
    return tmp_path


def test_record_writes_provenance_and_regenerates_the_pages(docs_in, monkeypatch, capsys):
    toy = types.ModuleType("toy_bench")
    toy.TITLE = "Toy"
    toy.main = lambda argv: print(json.dumps({"seconds": 1.5, "views": int(argv[0])})) or 0
    monkeypatch.setitem(sys.modules, "toy_bench", toy)
    monkeypatch.setitem(cli.BENCHMARKS, "toy", ("toy_bench", "a toy"))
    assert cli.main(["toy", "3", "--record"]) == 0
    assert json.loads(capsys.readouterr().out)["views"] == 3  # still printed
    written = json.loads((docs_in / "bench" / "toy.json").read_text())
    provenance = written["provenance"]
    assert written["result"] == {"seconds": 1.5, "views": 3}
    assert written["command"] == "recon-bench toy 3" and written["title"] == "Toy"
    assert re.fullmatch(r"[0-9a-f]{12}", provenance["config_hash"])
    assert provenance["machine"]["cores"] and provenance["machine"]["torch"]
    assert "| seconds | 1.5 |" in written["summary"]
    page = (docs_in / "benchmarks.md").read_text()
    assert "## Toy" in page and f"config hash `{provenance['config_hash']}`" in page
    assert "no `fit` record" in (docs_in / "README.md").read_text()
    # Measured again: the notes written for the first record are kept, and say so.
    written["notes"] = "Hand-written remark."
    (docs_in / "bench" / "toy.json").write_text(json.dumps(written))
    assert cli.main(["toy", "4", "--record"]) == 0
    again = json.loads((docs_in / "bench" / "toy.json").read_text())
    assert again["result"]["views"] == 4 and again["notes"] == "Hand-written remark."
    assert again["notes_from"].startswith("the record of ")
    # The same arguments and recipes give the same config hash; other arguments another.
    assert record.config_hash("toy", ["3"]) == provenance["config_hash"]
    assert record.config_hash("toy", ["4"]) != provenance["config_hash"]


def test_a_benchmark_that_prints_no_json_is_not_recorded(docs_in, monkeypatch, capsys):
    toy = types.ModuleType("quiet_bench")
    toy.main = lambda argv: 0
    monkeypatch.setitem(sys.modules, "quiet_bench", toy)
    monkeypatch.setitem(cli.BENCHMARKS, "quiet", ("quiet_bench", "prints nothing"))
    assert cli.main(["quiet", "--record"]) == 2
    assert "printed no JSON result to record" in capsys.readouterr().err
    assert not (docs_in / "bench" / "quiet.json").exists()

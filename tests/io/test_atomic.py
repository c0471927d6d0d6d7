"""remove_stale_temporaries deletes exactly what a killed atomic write leaves behind."""

from __future__ import annotations

import tempfile

from recon.io.atomic import atomic_write_text, remove_stale_temporaries


def test_only_atomic_writer_leftovers_are_removed(tmp_path):
    (tmp_path / "split").mkdir()
    handle, stale = tempfile.mkstemp(dir=tmp_path / "split", prefix=".r_0.", suffix=".tmp.png")
    handle_json, stale_json = tempfile.mkstemp(dir=tmp_path, prefix=".env.", suffix=".tmp.json")
    kept = [
        tmp_path / ".recon-run",
        tmp_path / ".notes.tmp",  # a user's hidden file: not the writer's 8-character pattern
        tmp_path / "r_0.tmp.png",  # not hidden
        tmp_path / "split" / "r_0.png",
    ]
    for path in kept:
        path.write_text("keep")
    atomic_write_text(tmp_path / "done.txt", "complete")
    removed = remove_stale_temporaries(tmp_path)
    assert sorted(str(path) for path in removed) == sorted([stale, stale_json])
    assert all(path.read_text() == "keep" for path in kept)
    assert (tmp_path / "done.txt").read_text() == "complete"
    assert remove_stale_temporaries(tmp_path) == []

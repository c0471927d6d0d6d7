"""Retired config keys: a run folder written by an earlier recon still loads."""

from __future__ import annotations

from pathlib import Path

import pytest

from recon.config import load_config
from recon.config.retired import RETIRED_KEYS, retired_reason
from recon.config.run_config import RunConfig
from recon.errors import ConfigError

RETIRED = "diagnose.decision.visibility_share_minimum"


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "config.resolved.yaml"
    path.write_text(text)
    return path


def test_a_retired_key_is_skipped_with_a_warning_naming_its_replacement(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _write(
        tmp_path,
        "diagnose:\n  decision:\n    visibility_share_minimum: 0.2\n    fingerprint_alpha: 0.02\n",
    )
    config = load_config(path, RunConfig)
    assert config.diagnose.decision.fingerprint_alpha == 0.02  # its neighbours still load
    warning = capsys.readouterr().err
    assert warning.startswith("recon: warning: ")
    assert "config.resolved.yaml:3" in warning
    assert RETIRED in warning and "fingerprint_minimum" in warning


def test_a_misspelt_key_beside_it_is_still_an_error(tmp_path: Path) -> None:
    path = _write(tmp_path, "diagnose:\n  decision:\n    visibility_share_minimun: 0.2\n")
    with pytest.raises(ConfigError, match="visibility_share_minimun: unknown key"):
        load_config(path, RunConfig)


def test_every_retired_key_is_really_gone_from_the_schema() -> None:
    # A key still in the schema must load as itself, never be skipped as retired.
    from recon.config.reference import config_keys

    current = {item.key for item in config_keys(RunConfig)}
    assert RETIRED_KEYS and not set(RETIRED_KEYS) & current
    assert retired_reason(("diagnose", "decision", "fingerprint_minimum")) is None

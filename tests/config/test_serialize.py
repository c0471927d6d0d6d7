"""recon.config.serialize: a config hash can leave top-level sections out."""

from __future__ import annotations

from dataclasses import replace

from recon.config import config_hash
from recon.config.run_config import DecisionConfig, DiagnoseConfig, RunConfig


def test_a_hash_without_the_diagnose_section_ignores_diagnose_settings():
    config = RunConfig()
    other = replace(config, diagnose=DiagnoseConfig(decision=DecisionConfig(minimum_share=0.05)))
    assert config_hash(config) != config_hash(other)
    assert config_hash(config, exclude=("diagnose",)) == config_hash(other, exclude=("diagnose",))
    # Any other section still counts.
    moved = replace(config, seed=1)
    assert config_hash(config, exclude=("diagnose",)) != config_hash(moved, exclude=("diagnose",))

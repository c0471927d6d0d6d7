"""Tests for recon.config.run_config: the diagnosis checks' sections (issue 20)."""

from __future__ import annotations

import pytest

from recon.config import ConfigError, from_dict
from recon.config.run_config import DiagnoseConfig, RunConfig
from recon.config.serialize import to_dict


def test_the_checks_sections_round_trip_through_the_resolved_config():
    config = from_dict(
        {
            "diagnose": {
                "specificity": {"alpha": 0.05, "angle_bins": 4},
                "nulls": {"placebo_draws": 7},
                "identifiability": {"corner_radius": 0.8},
                "metadata": {"permutations": 100},
            }
        },
        RunConfig,
    )
    diagnose = config.diagnose
    assert diagnose.specificity.alpha == 0.05 and diagnose.specificity.angle_bins == 4
    assert diagnose.nulls.placebo_draws == 7 and diagnose.identifiability.corner_radius == 0.8
    again = from_dict(to_dict(config), RunConfig)
    assert again.diagnose == diagnose
    # Defaults are the checks' former module constants.
    defaults = DiagnoseConfig()
    assert defaults.nulls.quantile == 0.95 and defaults.metadata.alpha == 0.05
    assert defaults.identifiability.minimum_exposure_ratio == pytest.approx(2 ** (1 / 3))


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ({"specificity": {"alpha": 1.5}}, "diagnose.specificity.alpha"),
        ({"nulls": {"placebo_draws": 0}}, "diagnose.nulls.placebo_draws"),
        ({"metadata": {"permutations": 0}}, "diagnose.metadata.permutations"),
    ],
)
def test_out_of_range_check_settings_name_their_key(section, message):
    with pytest.raises(ConfigError, match=message):
        from_dict({"diagnose": section}, RunConfig)


@pytest.mark.parametrize(
    ("section", "message"),
    [
        (
            {"exposure_gain_estimator": "median"},
            "diagnose.exposure_gain_estimator.*highlight_free or robust_regions.*'median'",
        ),
        ({"exposure_region_factors": ["texel"]}, "diagnose.exposure_region_factors.*texel"),
        ({"exposure_region_tukey": 0.0}, "diagnose.exposure_region_tukey"),
    ],
)
def test_bad_exposure_gain_settings_name_their_key(section, message):
    with pytest.raises(ConfigError, match=message):
        from_dict({"diagnose": section}, RunConfig)
    # The default estimator is the one the blind check was scored with (decision 0219).
    assert DiagnoseConfig().exposure_gain_estimator == "highlight_free"

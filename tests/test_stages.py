"""recon.stages.find_stage: recon's own stages from the table, other packages' by entry point."""

from __future__ import annotations

import pytest

from recon.errors import ReconError
from recon.stages import STAGES, find_stage


@pytest.mark.parametrize("name", sorted(STAGES))
def test_own_stages_resolve_from_the_table(name):
    stage = find_stage(name)
    assert callable(stage) and stage.__name__ == STAGES[name].split(":")[1]


def test_the_synth_stage_comes_from_data_synth_by_entry_point():
    assert find_stage("synth").__module__ == "data_synth.stage"


def test_an_unknown_stage_names_the_known_ones():
    with pytest.raises(ReconError, match=r"stage 'fitt': not installed \(known: .*fit.*synth"):
        find_stage("fitt")

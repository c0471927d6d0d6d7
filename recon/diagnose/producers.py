"""Evidence producers beyond the built-in ones: where a new kind of check plugs in.

A producer is ``producer(inputs: EvidenceInputs, candidates: list[Candidate], settings:
DiagnoseConfig) -> list[Evidence]``. ``diagnose_run`` calls every producer in ``PRODUCERS``
after the built-in evidence (probes, fingerprint, relight, flat field, absorption, conditional
probes) and before the final decision; each returned Evidence is added to the candidate it names
(a base-model mismatch candidate is created when first named). The decision table
(recon.diagnose.decision) says what each kind does: 'specificity' vetoes (and can name a
mismatch through details['instead']), 'null' raises the bar, 'identifiability' qualifies,
'metadata' vetoes a candidate the capture's record contradicts. Adding a producer is appending it here; no other module changes.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from recon.config.run_config import DiagnoseConfig
from recon.diagnose.data import DiagnosisData, FittedModel, render_diagnosis_data
from recon.diagnose.records import Candidate, Evidence
from recon.diagnose.which import EffectProbe
from recon.io.datasets import CaptureSet


@dataclass
class EvidenceInputs:
    """What a producer may look at (objects only; no run-folder paths).

    data: the held-out views against the fitted model (DiagnosisData, renders on the CPU).
    probe: the EffectProbe of those views (cached render; probe.render(modules) renders the
        model with extra effect modules, probe.heldout_errors the probes' per-view errors).
    heldout, training: the held-out and training captures (CaptureSet.metadata holds EXIF
        where the dataset has it).
    model: the fitted model (material, light, the fit's own effects).
    relight: the relight split against the model under its own light, or None.
    training_data: the training views against the fitted model when an earlier step rendered
        them (training_views() renders them otherwise, once).
    """

    data: DiagnosisData
    probe: EffectProbe
    heldout: CaptureSet
    training: CaptureSet
    model: FittedModel
    relight: DiagnosisData | None = None
    training_data: DiagnosisData | None = None

    def training_views(self, band_pixels: int) -> DiagnosisData:
        """The training views against the fitted model (rendered on first use)."""
        if self.training_data is None:
            device = self.model.mesh.verts.device
            self.training_data = render_diagnosis_data(
                self.training, self.model, device, band_pixels
            )
        return self.training_data


EvidenceProducer = Callable[[EvidenceInputs, list[Candidate], DiagnoseConfig], list[Evidence]]

# The extra producers, called in order (the specificity, null, identifiability and metadata
# checks register here).
PRODUCERS: list[EvidenceProducer] = []


def _register_checks() -> None:
    """Issue 20's checks (recon.diagnose.checks), imported late: they read EvidenceInputs."""
    from recon.diagnose.bounce import bounce_producer
    from recon.diagnose.cast_shadow import cast_shadow_producer
    from recon.diagnose.checks import CHECK_PRODUCERS
    from recon.diagnose.edge_width import edge_blur_producer, edge_producer
    from recon.diagnose.geometric_checks import GEOMETRIC_PRODUCERS
    from recon.diagnose.lobe import lobe_producer

    # The lobe first: the specificity checks see specular's verdict with it.
    PRODUCERS.append(lobe_producer)
    PRODUCERS.append(cast_shadow_producer)
    PRODUCERS.append(bounce_producer)
    PRODUCERS.extend(CHECK_PRODUCERS)
    # The edges before the geometric checks: a blur they rule out is vetoed, and the probes
    # measured on top of it are restored alone (geometric_checks.restore_unconditioned).
    PRODUCERS.append(edge_producer)
    PRODUCERS.append(edge_blur_producer)
    PRODUCERS.extend(GEOMETRIC_PRODUCERS)


_register_checks()


def gather(
    producers: list[EvidenceProducer],
    inputs: EvidenceInputs,
    candidates: list[Candidate],
    settings: DiagnoseConfig,
) -> list[Candidate]:
    """Every producer's Evidence added to its candidate (mismatch candidates created); returns
    the candidates (the same list, extended)."""
    by_name = {candidate.name: candidate for candidate in candidates}
    for producer in producers:
        for evidence in producer(inputs, candidates, settings):
            if evidence.candidate not in by_name:
                by_name[evidence.candidate] = Candidate(evidence.candidate)
                candidates.append(by_name[evidence.candidate])
            by_name[evidence.candidate].add(evidence)
    return candidates

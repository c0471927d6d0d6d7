"""What the gap diagnosis needs to know about an effect, as data beside the effect.

Each model effect (recon.effects) carries one ``DiagnosisFacts`` as its class attribute
``diagnosis``: which family it belongs to (a camera effect can be vetoed by a specificity check
that finds the base model's mismatch instead), which kinds of evidence apply to it, how its
absorption evidence is measured, where its probe starts, what it is most often confused with,
and what capture makes it identifiable. The diagnosis (recon.diagnose) reads these facts and
names no effect itself.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Family = Literal["camera", "light_transport"]
AbsorptionMode = Literal["none", "frozen", "geometry", "closed_form"]


@dataclass(frozen=True)
class DiagnosisFacts:
    """One effect's diagnosis facts.

    family: 'camera' (the camera or sensor changes the image) or 'light_transport' (the scene's
        light does something the base model's shading leaves out).
    evidence: the evidence kinds besides the probe that apply (recon.diagnose.decision's rows):
        'absorption', 'relight', 'flat_field', 'line_target', 'line_target_levels',
        'fingerprint'.
    absorption: how its absorption evidence is measured: 'frozen' (texture, light and the
        effect refitted on the frozen geometry), 'geometry' (a refit that moves the vertices:
        the effect bends the geometry the fit absorbed it into), 'closed_form' (a regression
        of texel gains and the effect), 'none'.
    probe_start: (parameter, value) a probe starts from instead of the identity, for a
        parameter whose image changes to second order at zero (None: the identity).
    probe_frozen: parameters the probe keeps at zero (their image looks like other effects').
    fingerprint_side: which side of the visibility fingerprint's slope names it: 'blocked'
        (light missing entirely: at or above the shadow share) or 'bounced' (partly filled back).
    radial_falloff: its parameters describe a falloff over the image radius, measured only as
        far as the object's pixels reach (the diagnosis records that radius beside them).
    relight_exponent: a refit holds its exponent at the relight split's estimate (under one
        light the albedo absorbs a curve, so a refit cannot pin it).
    confusable: effects and base-model mismatches whose signature resembles this one's (the
        specificity checks test against them).
    identifiable_when: the capture that makes it identifiable (said when the data cannot).
    modelled_by: fit materials (config fit.material) that model it already: with one of them
        it is part of the model, not a candidate.
    gain_signature: the camera scales the image by a gain that its signature is (one per view,
        a curve of intensity, a falloff over the radius; recon.diagnose.specificity): a
        candidate whose signature removes no held-out error did not remove its error through
        it, whatever the light, and fails specificity. (Light-transport effects carry gain
        signatures too, but their evidence is their fingerprint: False.)
    distinct_from_confusers: its image change is none of its confusers' in any strength (a
        per-view rigid turn of the camera is no radial warp and no blur), so a real one removes
        held-out error on top of each confuser's probe; a probe whose reduction one confuser's
        probe removes as well (the least lower bound on top of one, row beyond_confusers, not
        above 0) removed the fit's own misfit that any warp removes, and is vetoed. (The two
        blurs are not: a short motion blur is nearly a small defocus.)
    """

    family: Family
    evidence: tuple[str, ...] = ()
    absorption: AbsorptionMode = "none"
    probe_start: tuple[str, float] | None = None
    probe_frozen: tuple[str, ...] = ()
    fingerprint_side: Literal["blocked", "bounced", ""] = ""
    radial_falloff: bool = False
    relight_exponent: bool = False
    confusable: tuple[str, ...] = ()
    identifiable_when: str = ""
    modelled_by: tuple[str, ...] = ()
    gain_signature: bool = False
    distinct_from_confusers: bool = False

"""The significance decision's thresholds, and where they come from.

Every fit leaves some structured misfit (a slightly wrong silhouette, a texture a little too
soft), and a flexible effect module explains part of it even on data that holds no effect at
all: a per-view pose refinement or a blur always "helps" a little on held-out views. Each
probe's held-out reduction is therefore compared with what that probe reaches on clean data,
its null allowance, not with zero.

The allowances were measured with ``recon-bench calibrate`` on clean calibration
datasets (the benchmark config at 128², default scene and spot, seeds 103-105: fits that the
blind benchmark's scored cases never use) as twice the largest reduction seen, floored at
MINIMUM_SHARE; the script prints the table below from fresh fits (the benchmark fits: 128³
hull, Large Steps lambda 10, 300 texture steps; largest clean reductions: defocus 0.078,
motion 0.070, pose 0.054, lens 0.028, response curve 0.009, all others below 0.005;
absorption: lens 0.022 (its 15-step refits; 0.034 at 30 steps), specular 0.001, vignetting
0.0005 (regression); relight 0.015). The
blur and pose probes pick up the fits' edge misfit (silhouettes, the torus' checker edges).
The visibility fingerprint's largest clean share was 0.010.
"""

from __future__ import annotations

# Below this, a held-out reduction is not worth naming whatever the probe.
MINIMUM_SHARE = 0.02

# Probe (scene frozen, per-view parameters fitted on half of each held-out view's pixel blocks):
# twice the largest held-out reduction on the clean calibration fits.
PROBE_ALLOWANCE: dict[str, float] = {
    "defocus_blur": 0.157,
    "motion_blur": 0.14,
    "pose_error": 0.108,
    "lens_distortion": 0.056,
    "vignetting": 0.02,
    "exposure": 0.02,
    "response_curve": 0.02,
    "white_balance": 0.02,
    "specular": 0.02,
    "shadows": 0.02,
    "interreflection": 0.02,
}

# The absorption evidence compares two refits of the same length from the same start, so its
# null spread is far smaller than a probe's (largest clean reduction 0.001 for specular): its
# floor is half the probe's. (The refits run only where the effect's probe removes at least
# MINIMUM_SHARE, recon.diagnose.absorption; the clean specular figure was measured before that
# rule, when they ran everywhere: no clean fit's specular probe reaches it.)
ABSORPTION_MINIMUM_SHARE = 0.01


# Vignetting's absorption evidence is a closed-form regression on interior pixels
# (recon.diagnose.radial_absorption), a share of a smaller error than the refits': on the clean
# calibration fits its reduction is at most 0.0005 (the fitted falloff mostly brightens or is
# flat), and on the other effects' datasets its lower bound stays below 0.0005. Its floor is
# half the refits'.
def absorption_minimum_share(effect: str) -> float:
    """The floor of an effect's absorption allowance (by the kind of its evidence)."""
    return 0.005 if effect == "vignetting" else ABSORPTION_MINIMUM_SHARE


# Absorption (a short refit with the effect against a control refit without it; vignetting's
# regression against the same without the falloff): twice the largest reduction over the
# control on the same calibration fits, floored at absorption_minimum_share.
ABSORPTION_ALLOWANCE: dict[str, float] = {
    "lens_distortion": 0.043,
    "vignetting": 0.005,
    "specular": 0.01,
}

# Relight response probe (recon.diagnose.relight_probe, with the fitted light's balance error
# divided out): twice the largest reduction on the clean calibration fits (0.015).
RELIGHT_ALLOWANCE = 0.03

# Visibility fingerprint (recon.diagnose.fingerprint): the share of the self-shadowing that the
# fitted mesh and light predict which the fit baked into its albedo. Clean fits stay below
# 0.011; its bootstrap lower bound must clear VISIBILITY_SHARE_MINIMUM to count. Light that is
# simply blocked leaves about 0.8 (the prediction is a 64-direction estimate of the true
# occlusion); bounced light fills part of it back, leaving about 1 - albedo of it: below
# SHADOW_SHARE the missing effect is interreflection, above it shadows.
VISIBILITY_SHARE_MINIMUM = 0.2
SHADOW_SHARE = 0.6


def probe_threshold(effect: str) -> float:
    """The held-out reduction a probe's bootstrap lower bound must clear."""
    return max(MINIMUM_SHARE, PROBE_ALLOWANCE.get(effect, MINIMUM_SHARE))


def absorption_threshold(effect: str) -> float:
    """The reduction over the control refit the absorption lower bound must clear."""
    return max(absorption_minimum_share(effect), ABSORPTION_ALLOWANCE.get(effect, MINIMUM_SHARE))

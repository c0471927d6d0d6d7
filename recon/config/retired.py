"""Config keys a recon version dropped, so that run folders written before still load.

A run's config.resolved.yaml spells out every key the recon that wrote it knew. When a later
version removes a key (its meaning moved elsewhere), `recon diagnose`, `recon report` or a
resumed run read that file again: a retired key is then skipped with a warning that says what
replaced it, instead of failing as an unknown key. A key nobody ever had stays an error (a
typo), and a retired key whose value mattered is named in the warning so the user can act.
"""

from __future__ import annotations

# dotted key path -> what replaced it (the decision note that retired it)
RETIRED_KEYS: dict[str, str] = {
    "diagnose.decision.visibility_share_minimum": (
        "the visibility fingerprint is tested against placebo lights now: "
        "diagnose.decision.fingerprint_minimum and fingerprint_alpha "
        "(docs/decisions/0206-fingerprint-share.md)"
    ),
}


def retired_reason(path: tuple[str | int, ...]) -> str | None:
    """What replaced the key at path, or None when it was never retired."""
    return RETIRED_KEYS.get(".".join(str(part) for part in path))

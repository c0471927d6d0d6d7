"""The world effects' strength parameters as a Markdown reference (docs/effect_parameters.md).

Generated from each world effect's ``PARAMETERS`` (``ParameterSpec``: default, range, kind,
description), so the page cannot drift from what ``capture.effects[].parameters`` accepts; a
test compares the file with ``effect_parameters_markdown()``. Regenerate with
``python -m data_synth.reference > docs/effect_parameters.md``.
"""

from __future__ import annotations

import inspect

from data_synth.effects.light_transport import LIGHT_TRANSPORT_EFFECTS
from data_synth.effects.registry import WORLD_EFFECTS
from data_synth.effects.world_effect import WorldEffect
from recon.config.run_config import EFFECT_NAMES

REGENERATE_COMMAND = "python -m data_synth.reference > docs/effect_parameters.md"


def world_effect_classes() -> dict[str, type[WorldEffect]]:
    """Every catalogue effect's world class, in catalogue order."""
    classes = {**WORLD_EFFECTS, **LIGHT_TRANSPORT_EFFECTS}
    return {name: classes[name] for name in EFFECT_NAMES}


def _summary(effect: type[WorldEffect]) -> str:
    doc = inspect.cleandoc(effect.__doc__ or "")
    return " ".join(doc.split("\n\n")[0].split())


def _number(value: object) -> str:
    return repr(value) if isinstance(value, bool) else f"{value:g}"


def effect_parameters_markdown() -> str:
    """One section per world effect: its stage, what it does, and a table of its parameters."""
    out = [
        "# World effect parameters",
        "",
        "What `capture.effects: [{name, parameters}]` accepts, per effect (data_synth's world",
        "implementations; see [data_synth.md](data_synth.md)). Generated from each effect's",
        f"`PARAMETERS`; do not edit by hand. Regenerate with `{REGENERATE_COMMAND}`.",
        "Parameters left out take their default; a value outside its range is an error.",
        "",
    ]
    for name, effect in world_effect_classes().items():
        out += [f"## {name}", "", f"Stage: {effect.stage}. {_summary(effect)}", ""]
        out += ["| parameter | kind | default | range | description |", "|---|---|---|---|---|"]
        for key, spec in effect.PARAMETERS.items():
            bounds = f"[{_number(spec.minimum)}, {_number(spec.maximum)}]"
            description = spec.description.replace("|", "\\|")
            out.append(
                f"| `{key}` | {spec.kind} | {_number(spec.default)} | {bounds} | {description} |"
            )
        out.append("")
    return "\n".join(out)


if __name__ == "__main__":
    print(effect_parameters_markdown(), end="")

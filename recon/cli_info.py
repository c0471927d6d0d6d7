"""The CLI's read-only views: ``recon config keys|show``, ``recon effects`` and ``recon scenes``.

They print what the code knows (the config schema, the effect catalogue) and touch no run
folder. cli.py adds their parsers with ``add_commands`` and calls ``run`` for them; torch is
imported only by ``recon effects`` (the effect modules are torch modules).
"""

from __future__ import annotations

import argparse
import inspect
import re
from collections.abc import Callable
from pathlib import Path

COMMANDS = ("config", "effects", "scenes")


def add_commands(commands: argparse._SubParsersAction) -> None:
    """Add ``config keys``, ``config show`` and ``effects`` to the CLI's subcommands."""
    config_parser = commands.add_parser(
        "config", help="the config reference (keys) or a config resolved (show)"
    )
    views = config_parser.add_subparsers(dest="config_command", required=True)
    keys_parser = views.add_parser(
        "keys", help="every config key with its type, default, allowed values and description"
    )
    keys_parser.add_argument(
        "--markdown",
        action="store_true",
        help="print docs/config.md (the reference as Markdown tables) instead",
    )
    show_parser = views.add_parser(
        "show", help="print CONFIG resolved (defaults filled in, overrides applied) as YAML"
    )
    show_parser.add_argument("config", help="YAML run config (see configs/)")
    show_parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value, e.g. --set capture.train_views=8 (repeatable)",
    )
    commands.add_parser(
        "effects", help="the effect catalogue: names, where each acts, what the model does"
    )
    scenes_parser = commands.add_parser(
        "scenes", help="the run configs in a folder (default: configs/), each with its summary"
    )
    scenes_parser.add_argument(
        "folder", nargs="?", default="configs", help="where to look (default: configs)"
    )


def run(arguments: argparse.Namespace) -> int:
    """Run one of COMMANDS; raises ReconError (e.g. a bad config) for the CLI to print."""
    handlers: dict[str, Callable[[argparse.Namespace], int]] = {
        "config": _config,
        "effects": _effects,
        "scenes": _scenes,
    }
    return handlers[arguments.command](arguments)


def _config(arguments: argparse.Namespace) -> int:
    from recon.config.reference import config_keys, format_keys, reference_markdown
    from recon.config.run_config import RunConfig

    if arguments.config_command == "keys":
        if arguments.markdown:
            print(reference_markdown(RunConfig), end="")
        else:
            print(format_keys(config_keys(RunConfig)), end="")
        return 0
    import yaml

    from recon.config import load_config, to_dict

    config = load_config(arguments.config, RunConfig, overrides=arguments.overrides)
    print(yaml.safe_dump(to_dict(config), sort_keys=False, allow_unicode=True), end="")
    return 0


def effect_catalogue() -> list[tuple[str, str, str]]:
    """(name, where it acts, one-line description) for every catalogue effect, in its order.

    Where it acts: the model module's stage (camera, shading or image) and whether it has
    parameters per view; noise has no model module (the diagnosis estimates it as a floor).
    """
    from recon.config.run_config import EFFECT_NAMES
    from recon.effects.registry import MODEL_EFFECTS

    rows = []
    for name in EFFECT_NAMES:
        effect = MODEL_EFFECTS.get(name)
        if effect is None:
            rows.append((name, "none", "no model module: a floor the diagnosis estimates"))
            continue
        where = f"{effect.stage}, per view" if effect.per_view else effect.stage
        summary = inspect.cleandoc(effect.__doc__ or "").split("\n\n")[0]
        rows.append((name, where, " ".join(summary.split())))
    return rows


def _effects(arguments: argparse.Namespace) -> int:
    rows = effect_catalogue()
    name_width = max(len(name) for name, _, _ in rows)
    where_width = max(len(where) for _, where, _ in rows)
    print(f"{'effect':{name_width}}  {'acts on':{where_width}}  model (recon/effects)")
    for name, where, summary in rows:
        print(f"{name:{name_width}}  {where:{where_width}}  {summary}")
    print(
        "\ncaptures inject them with capture.effects (data_synth's own implementations);\n"
        "fits add the model modules with fit.effects (then part of the model the diagnosis\n"
        "starts from); `recon diagnose` ranks the others as candidates."
    )
    return 0


def config_summary(path: Path, limit: int = 90) -> str:
    """The first sentence of a config file's leading comment block ('' when it has none),
    shortened to limit characters at a word boundary."""
    lines = []
    for line in path.read_text(encoding="utf-8").splitlines():
        if not line.startswith("#"):
            break
        text = line.lstrip("#").strip()
        if not text:
            break
        lines.append(text)
    comment = " ".join(lines)
    sentence_end = re.search(r"[.:](\s|$)", comment)
    sentence = comment[: sentence_end.start()] if sentence_end else comment
    if len(sentence) > limit:  # one terminal line per config
        sentence = sentence[: sentence.rfind(" ", 0, limit - 3)] + "..."
    return sentence


def _scenes(arguments: argparse.Namespace) -> int:
    from recon.errors import ReconError

    folder = Path(arguments.folder)
    if not folder.is_dir():
        raise ReconError(
            f"scenes: {folder} is not a folder (run from the repository root, or name the "
            "folder holding the YAML configs)"
        )
    paths = sorted(folder.rglob("*.yaml"))
    if not paths:
        raise ReconError(f"scenes: no .yaml configs under {folder}")
    width = max(len(str(path)) for path in paths)
    for path in paths:
        print(f"{str(path):{width}}  {config_summary(path)}")
    print(
        "\nrun one with `recon run CONFIG`; see it resolved with `recon config show CONFIG`;\n"
        "built-in shapes for scene.shape.procedural: `recon config keys`."
    )
    return 0

"""The README and docs/ stay a guide and a manual: size, links, and the CLI table."""

from __future__ import annotations

import re
from pathlib import Path

from recon.cli import build_parser

REPO_ROOT = Path(__file__).resolve().parents[1]
README = REPO_ROOT / "README.md"
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _markdown_files() -> list[Path]:
    return [README, *sorted((REPO_ROOT / "docs").rglob("*.md"))]


def test_readme_is_a_guide_of_at_most_250_lines():
    lines = README.read_text(encoding="utf-8").splitlines()
    assert len(lines) <= 250, f"README.md has {len(lines)} lines; move detail into docs/"


def test_relative_links_point_at_existing_files_and_headings():
    broken = []
    for path in _markdown_files():
        for target in LINK.findall(path.read_text(encoding="utf-8")):
            if re.match(r"^[a-z]+:", target):  # http:, https:, mailto:
                continue
            file_part, _, anchor = target.partition("#")
            linked = (path.parent / file_part).resolve() if file_part else path
            if not linked.exists():
                broken.append(f"{path.relative_to(REPO_ROOT)} -> {target}")
                continue
            if anchor and linked.suffix == ".md":
                headings = re.findall(r"^#+ (.+)$", linked.read_text(encoding="utf-8"), re.M)
                slugs = {
                    re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in headings
                }
                if anchor not in slugs:
                    broken.append(f"{path.relative_to(REPO_ROOT)} -> {target} (no such heading)")
    assert not broken, f"broken links: {broken}"


def test_readme_cli_table_names_every_command():
    text = README.read_text(encoding="utf-8")
    commands = build_parser()._subparsers._group_actions[0].choices
    missing = [name for name in commands if f"`recon {name}" not in text]
    assert not missing, f"README's command table lacks: {missing}"


def test_readme_keeps_the_ci_test_command():
    # .ci/run runs "the README's test command"; both must say the same.
    command = "python -m pytest -q"
    assert command in README.read_text(encoding="utf-8")
    assert command in (REPO_ROOT / ".ci" / "run").read_text(encoding="utf-8")

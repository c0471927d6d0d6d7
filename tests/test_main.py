"""Tests for recon.__main__ and the fast CLI entry: `python -m recon`, --version, --help."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import recon

REPO_ROOT = Path(__file__).resolve().parents[1]


def _python(*arguments: str) -> subprocess.CompletedProcess:
    environment = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    return subprocess.run(
        [sys.executable, *arguments],
        capture_output=True,
        text=True,
        cwd=REPO_ROOT,
        env=environment,
        timeout=120,
    )


def test_python_dash_m_recon_prints_the_version():
    result = _python("-m", "recon", "--version")
    assert result.returncode == 0, result.stderr
    # tomllib is 3.11+ and the project supports 3.10: the version line is read directly.
    pyproject = (REPO_ROOT / "pyproject.toml").read_text()
    version = re.search(r'^version = "([^"]+)"', pyproject, re.MULTILINE)[1]
    assert result.stdout.strip() == f"recon {version}" == f"recon {recon.__version__}"


def test_help_is_user_facing_and_lists_every_command():
    result = _python("-m", "recon", "--help")
    assert result.returncode == 0, result.stderr
    assert "recon run configs/quickstart.yaml" in result.stdout
    assert "Nothing else" not in result.stdout  # the module docstring is for developers
    for command in ("run", "synth", "fit", "evaluate", "report", "diagnose", "compare"):
        assert f"    {command} " in result.stdout
    for command in ("config", "effects"):
        assert f"    {command} " in result.stdout


def test_help_config_views_and_scenes_do_not_import_torch():
    # torch costs about 3 s to import; --help and the config views must not pay it.
    probe = (
        "import sys\n"
        "from recon.cli import main\n"
        "for argv in ({argv}):\n"
        "    try:\n"
        "        main(list(argv))\n"
        "    except SystemExit:\n"
        "        pass\n"
        "print('torch imported:', 'torch' in sys.modules, file=sys.stderr)\n"
    )
    argv = (
        "['--help'], ['config', 'keys'], ['config', 'show', 'configs/quickstart.yaml'], ['scenes']"
    )
    result = _python("-c", probe.format(argv=argv))
    assert result.returncode == 0, result.stderr
    assert "torch imported: False" in result.stderr

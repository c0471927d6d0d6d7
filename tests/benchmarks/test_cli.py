"""benchmarks/cli.py (recon-bench): every benchmark module is registered, each NAME --help
works, and failures are one line with exit code 2."""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.cli import BENCHMARKS, main

REPO_ROOT = Path(__file__).resolve().parents[2]
# Modules of the package that are not benchmarks.
NOT_BENCHMARKS = {"__init__", "__main__", "cli", "common", "record"}


def test_every_benchmark_module_is_registered_with_a_main():
    modules = {
        f"benchmarks.{path.stem}"
        for path in (REPO_ROOT / "benchmarks").glob("*.py")
        if path.stem not in NOT_BENCHMARKS
    }
    assert modules == {module for module, _ in BENCHMARKS.values()}
    for module, _ in BENCHMARKS.values():
        assert callable(importlib.import_module(module).main), module


@pytest.mark.parametrize("name", sorted(BENCHMARKS))
def test_help_of_every_benchmark(name, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([name, "--help"])
    assert exit_info.value.code == 0
    assert f"usage: recon-bench {name}" in capsys.readouterr().out
    assert sys.argv[0] != f"recon-bench {name}"  # restored after the benchmark


def test_listing_unknown_names_and_errors(tmp_path, capsys):
    assert main(["--help"]) == 0
    listing = capsys.readouterr().out
    assert all(f"  {name}  " in listing for name in BENCHMARKS)
    assert main([]) == 2
    assert "usage: recon-bench NAME" in capsys.readouterr().err
    assert main(["diagnose-bench"]) == 2
    assert "unknown benchmark 'diagnose-bench'" in capsys.readouterr().err
    missing = tmp_path / "missing.yaml"
    assert main(["diagnose-blind", str(missing), "--out", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert error.startswith("recon-bench: error: ") and "missing.yaml" in error
    assert not (tmp_path / "out").exists()


def test_python_dash_m_runs_the_package_and_a_module():
    environment = {**os.environ, "PYTHONPATH": str(REPO_ROOT)}
    listing = subprocess.run(
        [sys.executable, "-m", "benchmarks", "--help"],
        capture_output=True,
        text=True,
        env=environment,
        cwd=REPO_ROOT,
    )
    assert listing.returncode == 0 and "diagnose-blind" in listing.stdout
    module = subprocess.run(
        [sys.executable, "-m", "benchmarks.fit", "--help"],
        capture_output=True,
        text=True,
        env=environment,
        cwd=REPO_ROOT,
    )
    assert module.returncode == 0 and "--scenes" in module.stdout

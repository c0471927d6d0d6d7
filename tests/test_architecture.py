"""The house rules that no single module's test can hold: only stages touch the run folder, and
the tests mirror the modules.

The layering table (which package may import which) is tests/pipeline/test_cli.py's LAYERS.
"""

from __future__ import annotations

import ast
from pathlib import Path

from recon.io.run_folder import RunPaths

REPO_ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("recon", "data_synth", "benchmarks")

# Modules that may use RunPaths (import recon.io.run_folder, take a run folder's `paths`),
# besides recon/stages/ (the stages: the only modules that read or write a run folder), and why.
RUN_FOLDER_USERS = {
    "recon/io/run_folder.py": "defines RunPaths",
    "recon/pipeline.py": "creates, opens and resumes run folders, runs the stages, writes env.json",
    "recon/cli.py": "opens the run folder a command names (compare reads its metrics.json)",
    "recon/preflight.py": "checks a new run's folder before the pipeline creates it",
    "recon/sweep/trial.py": "a trial runs the pipeline, then reads the run's results as a user would",
    "data_synth/stage.py": "the synth stage (data_synth's, found by entry point)",
    "data_synth/calibration_splits.py": "completes a synthetic run's dataset with calibration frames",
}
# Where the rule does not hold yet, and why; each entry names the issue that removes it.
# (None since the diagnosis redesign, issue 20, moved the diagnose stage to
# recon/stages/diagnose.py and made the diagnosis library take objects.)
RUN_FOLDER_EXCEPTIONS: dict[str, str] = {}


def _sources(packages=PACKAGES) -> list[tuple[str, ast.Module]]:
    found = []
    for package in packages:
        for path in sorted((REPO_ROOT / package).rglob("*.py")):
            name = path.relative_to(REPO_ROOT).as_posix()
            found.append((name, ast.parse(path.read_text(), filename=name)))
    return found


def _excepted(name: str, function: str | None = None) -> bool:
    return any(
        name.startswith(key) if key.endswith("/") else key in (name, f"{name}:{function}")
        for key in RUN_FOLDER_EXCEPTIONS
    )


def _may_use_run_folder(name: str) -> bool:
    return name.startswith("recon/stages/") or name in RUN_FOLDER_USERS or _excepted(name)


def _run_folder_names() -> set[str]:
    """The file names a RunPaths property ends in (metrics.json, env.json, geometry.pt, ...)."""
    paths = RunPaths(Path("run"))
    names = set()
    for attribute in dir(RunPaths):
        value = (
            getattr(paths, attribute)
            if isinstance(getattr(RunPaths, attribute), property)
            else None
        )
        if isinstance(value, Path) and value.suffix:
            names.add(value.name)
    return names


def _run_paths_offences(sources: list[tuple[str, ast.Module]]) -> list[str]:
    """Imports of recon.io.run_folder, and functions taking a run's `paths`, outside the modules
    that may use the run folder."""
    offences = []
    for name, tree in sources:
        if _may_use_run_folder(name):
            continue
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module == "recon.io.run_folder":
                offences.append(f"{name}:{node.lineno} imports recon.io.run_folder")
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                arguments = node.args.posonlyargs + node.args.args + node.args.kwonlyargs
                if any(argument.arg == "paths" for argument in arguments) and not _excepted(
                    name, node.name
                ):
                    offences.append(f"{name}:{node.lineno} {node.name}() takes a run's paths")
    return offences


def _path_string_offences(sources: list[tuple[str, ast.Module]]) -> list[str]:
    """`folder / "metrics.json"` (a RunPaths file name joined by hand) anywhere but in
    RunPaths, and `folder / "transforms_..."` (a dataset layout probed by file name) outside the
    dataset readers and writers (recon/io/)."""
    names = _run_folder_names()
    offences = []
    for name, tree in sources:
        if name == "recon/io/run_folder.py" or _excepted(name):
            continue
        for node in ast.walk(tree):
            if not (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Div)):
                continue
            right = node.right
            if isinstance(right, ast.JoinedStr):
                right = right.values[0] if right.values else None
            if not (isinstance(right, ast.Constant) and isinstance(right.value, str)):
                continue
            if right.value in names:
                offences.append(f"{name}:{node.lineno} joins {right.value!r}")
            if right.value.startswith("transforms_") and not name.startswith("recon/io/"):
                offences.append(f"{name}:{node.lineno} probes the dataset layout by file name")
    return offences


def test_only_stages_the_pipeline_and_the_cli_use_run_paths():
    """recon.io.run_folder is imported, and a run folder's `paths` taken, only by the stages,
    the pipeline, the CLI and the modules in RUN_FOLDER_USERS (benchmarks/ may, being above
    everything): library functions take tensors, dataclasses and config sections."""
    offences = _run_paths_offences(_sources(("recon", "data_synth")))
    assert not offences, "run folder used outside recon/stages/:\n" + "\n".join(offences)


def test_run_folder_paths_come_from_run_paths():
    """No module joins a run-folder file name (metrics.json, env.json, ...) to a folder itself:
    each is a RunPaths property. A dataset's split files are asked of its DatasetLayout."""
    assert {"metrics.json", "env.json", "config.resolved.yaml", "geometry.pt"} <= (
        _run_folder_names()
    )
    offences = _path_string_offences(_sources())
    assert not offences, "run-folder paths built from strings:\n" + "\n".join(offences)


def test_the_run_folder_rules_see_a_violation():
    """The checks above catch what they are meant to (a rule that passes because it looks at
    nothing is no rule), and let the stages and the listed exceptions through."""
    source = ast.parse(
        "from recon.io.run_folder import RunPaths\n"
        "def score(paths, folder, split):\n"
        "    return paths.root / 'metrics.json', folder / f'transforms_{split}.json'\n"
    )
    assert len(_run_paths_offences([("recon/metrics/scores.py", source)])) == 2
    assert _run_paths_offences([("recon/stages/score.py", source)]) == []
    assert len(_run_paths_offences([("recon/diagnose/gap.py", source)])) == 2
    found = _path_string_offences([("recon/stages/score.py", source)])
    assert len(found) == 2 and "'metrics.json'" in found[0] and "dataset layout" in found[1]
    assert not _excepted("recon/optimize/fit.py", "fit_scene")


# Tests that exercise several modules together through the pipeline or the CLI (end to end,
# bad inputs, fault injection, repeatability) and regression/cross-checks against independent
# references: these folders are declared, every other test file mirrors one module.
SCENARIO_FOLDERS = {
    "tests/pipeline": "whole runs through recon.cli and recon.pipeline",
    "tests/regression": "tiny fits end to end against metric bounds, and resume",
}
# Test files outside the mirror, and why.
UNMIRRORED = {
    "tests/test_architecture.py": "the house rules themselves (this file)",
    "tests/test_docs.py": "docs/ (generated pages are fresh, links resolve)",
}
# Top-level folders of tests/ and the package each mirrors.
MIRRORED_PACKAGES = {"data_synth": "data_synth", "benchmarks": "benchmarks", "scripts": "scripts"}


def _module_for(test_file: Path) -> list[Path]:
    """The modules a test file may mirror: tests/a/test_b.py -> recon/a/b.py (or the package
    a/b/), tests/data_synth/x/test_y.py -> data_synth/x/y.py, likewise benchmarks/ and
    scripts/. A long module's tests may be split by topic: test_b_topic.py also mirrors b.py.
    Dunder modules drop their underscores (recon/__main__.py -> tests/test_main.py)."""
    relative = test_file.relative_to(REPO_ROOT / "tests")
    parts = list(relative.parts[:-1])
    if parts and parts[0] in MIRRORED_PACKAGES:
        root = REPO_ROOT / MIRRORED_PACKAGES[parts[0]]
        parts = parts[1:]
    else:
        root = REPO_ROOT / "recon"
    folder = root.joinpath(*parts)
    words = test_file.stem.removeprefix("test_").split("_")
    candidates = []
    for count in range(len(words), 0, -1):
        name = "_".join(words[:count])
        for module in (f"{name}.py", f"__{name}__.py"):
            candidates.append(folder / module)
        candidates.append(folder / name / "__init__.py")
    return [path for path in candidates if path.exists()]


def _unmirrored_tests() -> list[str]:
    found = []
    for path in sorted((REPO_ROOT / "tests").rglob("test_*.py")):
        name = path.relative_to(REPO_ROOT).as_posix()
        if name in UNMIRRORED or any(name.startswith(f"{folder}/") for folder in SCENARIO_FOLDERS):
            continue
        if not _module_for(path):
            found.append(name)
    return found


def test_tests_mirror_modules():
    """recon/a/b.py is tested in tests/a/test_b.py (data_synth/x.py in tests/data_synth/
    test_x.py, benchmarks/x.py in tests/benchmarks/test_x.py): a test file that mirrors no
    module lives in a declared scenario folder or is listed, with its reason, in UNMIRRORED."""
    found = _unmirrored_tests()
    assert not found, "test files that mirror no module:\n" + "\n".join(found)
    for name in UNMIRRORED:
        assert (REPO_ROOT / name).exists(), f"UNMIRRORED lists {name}, which is gone"


def test_the_mirror_rule_finds_modules():
    tests = REPO_ROOT / "tests"
    assert _module_for(tests / "render" / "test_rasterize.py") == [
        REPO_ROOT / "recon" / "render" / "rasterize.py"
    ]
    assert _module_for(tests / "io" / "test_datasets_real_captures.py")[0].name == "datasets.py"
    assert _module_for(tests / "data_synth" / "effects" / "test_optics.py")[0] == (
        REPO_ROOT / "data_synth" / "effects" / "optics.py"
    )
    assert _module_for(tests / "test_main.py") == [REPO_ROOT / "recon" / "__main__.py"]
    assert _module_for(tests / "render" / "test_nothing_here.py") == []
    assert _module_for(tests / "io" / "test_io_meshes.py") == []

"""Faults a user's machine throws at recon: a read-only folder, a full disk, kill -9 mid-synth.

Writes that fail end as `recon: error: PATH: reason (ERRNO: what to do)` with exit 2, keep what
was written (resumable) and never touch files outside the run. The fault is injected twice: by
monkeypatching the lowest write call to raise the OS error, and for real on a small tmpfs where
the test may mount one (root; skipped elsewhere).
"""

from __future__ import annotations

import errno
import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

from recon.cli import main

REPO_ROOT = Path(__file__).resolve().parents[2]

# Files whose content names the moment or the folder they were written in.
VOLATILE = {"env.json", ".recon-run"}


def tiny_config(**capture) -> dict:
    config = yaml.safe_load((REPO_ROOT / "configs" / "quickstart.yaml").read_text())
    config["stages"] = ["synth"]
    config["device"] = "cpu"
    config["capture"]["cameras"]["resolution"] = [32, 32]
    config["capture"].update({"train_views": 2, "val_views": 1, "test_views": 2, **capture})
    config["scene"]["shape"]["resolution"] = 16
    config["scene"]["material"]["texture_size"] = 16
    return config


def hashes(root: Path) -> dict[str, str]:
    return {
        str(path.relative_to(root)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(root.rglob("*"))
        if path.is_file() and path.name not in VOLATILE
    }


@pytest.fixture
def config_file(tmp_path) -> Path:
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump(tiny_config()))
    return path


@pytest.fixture
def tmpfs(tmp_path):
    """A fresh 4 MiB tmpfs (mount needs root with CAP_SYS_ADMIN; skipped elsewhere)."""
    mount_point = tmp_path / "tmpfs"
    mount_point.mkdir()
    if shutil.which("mount") is None or os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mount_point)],
        capture_output=True,
    )
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
    yield mount_point
    subprocess.run(["umount", "-l", str(mount_point)], check=False)


def _remount(mount_point: Path, options: str) -> None:
    subprocess.run(["mount", "-o", f"remount,{options}", str(mount_point)], check=True)


def _error_line(capsys) -> str:
    error = capsys.readouterr().err
    assert "Traceback" not in error
    lines = [line for line in error.splitlines() if line.startswith("recon: error: ")]
    assert len(lines) == 1, error
    return lines[0]


def test_read_only_folder_injected(config_file, tmp_path, monkeypatch, capsys):
    """Every atomic write goes through mkstemp in the target's folder: make it raise EROFS."""
    import recon.io.atomic as atomic

    def read_only(*arguments, dir=None, **keywords):
        raise OSError(errno.EROFS, os.strerror(errno.EROFS), dir)

    monkeypatch.setattr(atomic.tempfile, "mkstemp", read_only)
    code = main(["synth", str(config_file), "--out", str(tmp_path / "run")])
    message = _error_line(capsys)
    assert code == 2
    assert "Read-only file system" in message and "EROFS" in message and ".recon-run" in message
    assert not (tmp_path / "run").exists()


def test_full_disk_during_a_checkpoint_injected(tiny_run, tmp_path, monkeypatch, capsys):
    """torch.save reports a failed write as RuntimeError('[enforce fail at inline_container...'):
    it must end as a clear error naming the checkpoint, with the run kept for --resume."""
    import recon.io.checkpoints as checkpoints

    def disk_full(state, path):
        Path(path).write_bytes(b"PK\x03\x04")
        raise RuntimeError(
            "[enforce fail at inline_container.cc:672] . PytorchStreamWriter failed writing "
            "file data/0: file write failed"
        )

    monkeypatch.setattr(checkpoints.torch, "save", disk_full)
    config = yaml.safe_load((tiny_run / "config.resolved.yaml").read_text())
    config["stages"] = ["fit"]
    path = tmp_path / "fit.yaml"
    path.write_text(yaml.safe_dump(config))
    before = hashes(tiny_run)
    out = tmp_path / "fitted"
    code = main(["fit", str(path), "--data", str(tiny_run / "dataset"), "--out", str(out)])
    message = _error_line(capsys)
    assert code == 2
    assert "cannot write checkpoint" in message and "disk may be full" in message
    assert f"recon fit --resume {out}" in message
    assert (out / "config.resolved.yaml").exists()  # kept: resumable once space is freed
    assert not list(out.rglob("*.tmp*"))  # no half-written checkpoint left
    assert hashes(tiny_run) == before


def test_full_disk_in_report_injected(tiny_run, tmp_path, monkeypatch, capsys):
    import matplotlib.figure

    def disk_full(self, path, **keywords):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))

    run = tmp_path / "run"
    shutil.copytree(tiny_run, run)
    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", disk_full)
    assert main(["report", str(run), "--device", "cpu"]) == 2
    message = _error_line(capsys)
    assert "No space left on device" in message and "ENOSPC" in message and ".png" in message


def test_real_full_disk_then_resume_equals_an_uninterrupted_synth(
    config_file, tmpfs, tmp_path, capsys
):
    """A 4 MiB tmpfs filled by a ballast file: synth fails with ENOSPC, keeps what it wrote;
    after space is freed, --resume finishes with exactly the files of an uninterrupted run."""
    config = tiny_config(train_views=4, val_views=2, test_views=4)
    config["capture"]["cameras"]["resolution"] = [48, 48]
    config_file.write_text(yaml.safe_dump(config))
    reference = tmp_path / "reference"
    assert main(["synth", str(config_file), "--out", str(reference)]) == 0
    needed = sum(path.stat().st_size for path in reference.rglob("*") if path.is_file())
    ballast = tmpfs / "ballast"
    # Leave room for about half the run, so the disk fills in the middle of the synthesis.
    free = shutil.disk_usage(tmpfs).free
    ballast.write_bytes(b"\0" * max(0, free - needed // 2))
    run = tmpfs / "run"
    capsys.readouterr()
    assert main(["synth", str(config_file), "--out", str(run)]) == 2
    message = _error_line(capsys)
    # The disk fills during an image write (the OS error) or a progress checkpoint (torch's).
    assert ("No space left on device" in message and "ENOSPC" in message) or (
        "cannot write checkpoint" in message and "the disk may be full" in message
    ), message
    assert f"recon synth --resume {run}" in message
    assert run.is_dir() and not (run / "ground_truth").exists()
    ballast.unlink()
    assert main(["synth", "--resume", str(run)]) == 0
    assert hashes(run) == hashes(reference)


def test_real_read_only_run_folder_for_diagnose(tiny_run, tmpfs, capsys):
    """A run folder on a file system remounted read-only: diagnose refuses before it computes."""
    run = tmpfs / "run"
    shutil.copytree(tiny_run, run)
    _remount(tmpfs, "ro")
    started = time.perf_counter()
    assert main(["diagnose", str(run), "--refit", "none", "--device", "cpu"]) == 2
    message = _error_line(capsys)
    assert "not writable" in message and str(run) in message
    assert time.perf_counter() - started < 10  # refused up front, not after the diagnosis
    assert main(["report", str(run), "--device", "cpu"]) == 2
    assert "not writable" in _error_line(capsys)


def test_kill_9_mid_synth_then_resume_equals_an_uninterrupted_run(tmp_path):
    """kill -9 while the test split is being written; --resume must end with the same files."""
    config = tiny_config(train_views=2, val_views=1, test_views=120)
    config["capture"]["cameras"]["resolution"] = [48, 48]
    path = tmp_path / "kill.yaml"
    path.write_text(yaml.safe_dump(config))
    command = [sys.executable, "-m", "recon.cli"]
    reference = tmp_path / "reference"
    subprocess.run([*command, "synth", str(path), "--out", str(reference)], check=True)
    run = tmp_path / "run"
    process = subprocess.Popen(
        [*command, "synth", str(path), "--out", str(run)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    test_folder = run / "dataset" / "test"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and process.poll() is None:
        if test_folder.is_dir() and len(list(test_folder.glob("*.png"))) >= 5:
            break
        time.sleep(0.005)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert process.returncode == -signal.SIGKILL, "synth ended before it could be killed"
    assert not (run / "dataset" / "transforms_test.json").exists()
    done = subprocess.run([*command, "synth", "--resume", str(run)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert hashes(run) == hashes(reference)

"""The Makefile picks a Python the rclpy wheels exist for (3.11-3.13), and says so when there is none."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
MAKE = shutil.which("make")


# Under `make test PYTHON=...` (as .ci/run runs the suite) the outer make hands its command-line
# variables to every make below it through these; a test of the Makefile's own choice must drop them.
_MAKE_INHERITED = ("PYTHON", "MAKEFLAGS", "MFLAGS", "MAKEOVERRIDES", "MAKELEVEL", "MAKE_TERMOUT", "MAKE_TERMERR")


def _clean_env(path: str) -> dict[str, str]:
    """The environment of a first-level ``make`` with only ``path`` on PATH."""
    env = {key: value for key, value in os.environ.items() if key not in _MAKE_INHERITED}
    env["PATH"] = path
    return env


def _make_setup(path: str, venv: Path) -> subprocess.CompletedProcess[str]:
    """``make setup`` with only ``path`` on PATH; -n unless it is to fail, so nothing is installed."""
    env = _clean_env(path)
    return subprocess.run(
        [str(MAKE), "-n", "setup", f"VENV={venv}"], cwd=REPO, env=env, capture_output=True, text=True, timeout=60
    )


@pytest.mark.skipif(MAKE is None, reason="make is not installed")
@pytest.mark.parametrize("version", ["3.12", "3.13"])
def test_a_newer_python_is_taken_when_3_11_is_absent(tmp_path: Path, version: str) -> None:
    """Ubuntu 24.04 ships 3.12 and no 3.11: make must not stop at a hard-coded python3.11."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / f"python{version}"
    fake.write_text("#!/bin/sh\nexit 0\n")
    fake.chmod(0o755)
    result = _make_setup(f"{bin_dir}:/nonexistent", tmp_path / "venv")
    assert result.returncode == 0, result.stderr
    assert f"{fake} -m venv {tmp_path / 'venv'}" in result.stdout


@pytest.mark.skipif(MAKE is None, reason="make is not installed")
def test_no_suitable_python_is_said_in_one_clear_line(tmp_path: Path) -> None:
    env = _clean_env(str(tmp_path))
    result = subprocess.run(
        [str(MAKE), "setup", f"VENV={tmp_path / 'venv'}"], cwd=REPO, env=env, capture_output=True, text=True, timeout=60
    )
    assert result.returncode != 0
    assert "no python3.11, python3.12 or python3.13 on PATH" in result.stderr
    assert not (tmp_path / "venv").exists()

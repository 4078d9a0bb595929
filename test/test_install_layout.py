"""What `ros2 run lenn_ros identifier` relies on, checked on a real `colcon build`.

ros2cli cannot be installed here, so the test does what `ros2 run` does: find the
package prefix through the ament index on AMENT_PREFIX_PATH (ament_index_python,
the library ros2cli uses), then run `<prefix>/lib/lenn_ros/identifier`.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
colcon = shutil.which("colcon") or str(Path(sys.executable).with_name("colcon"))


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_colcon_build_gives_the_layout_ros2_run_needs(tmp_path: Path) -> None:
    if not Path(colcon).exists():
        pytest.fail("colcon is not installed: pip install '.[test]' brings colcon-common-extensions")
    source = tmp_path / "src" / "lenn_ros"
    listed = subprocess.run(["git", "ls-files"], cwd=REPO, capture_output=True, text=True)
    if listed.returncode != 0:  # no git (e.g. colcon test of a copied tree): the tree minus build products
        skip = shutil.ignore_patterns(".git", ".venv", "build", "install", "log", "bags", "__pycache__", "*.egg-info")
        shutil.copytree(REPO, source, ignore=skip)
    for name in listed.stdout.split() if listed.returncode == 0 else []:
        if name.startswith("bags/") or not (REPO / name).is_file():
            continue
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(REPO / name, source / name)
    build = subprocess.run(
        [colcon, "build", "--packages-select", "lenn_ros"], cwd=tmp_path, capture_output=True, text=True, timeout=240
    )
    assert build.returncode == 0, build.stdout + build.stderr
    prefix = tmp_path / "install" / "lenn_ros"
    assert (prefix / "share" / "ament_index" / "resource_index" / "packages" / "lenn_ros").is_file()
    assert (prefix / "share" / "lenn_ros" / "package.xml").is_file()
    assert (prefix / "share" / "lenn_ros" / "config" / "example1_lenn.yaml").is_file()
    assert (prefix / "share" / "lenn_ros" / "launch" / "identification.launch.py").is_file()
    for executable in ("identifier", "plant_simulator", "recorder", "replay"):
        assert os.access(prefix / "lib" / "lenn_ros" / executable, os.X_OK), executable

    # `ros2 run lenn_ros identifier`: resolve through the ament index, then execute.
    site = next(prefix.glob("lib/python3*/site-packages"))
    env = {**os.environ, "AMENT_PREFIX_PATH": str(prefix), "PYTHONPATH": str(site)}
    resolve = "from ament_index_python.packages import get_package_prefix; print(get_package_prefix('lenn_ros'))"
    found = subprocess.run([sys.executable, "-c", resolve], env=env, capture_output=True, text=True, check=True)
    assert Path(found.stdout.strip()) == prefix
    run = subprocess.run(
        [str(prefix / "lib" / "lenn_ros" / "identifier"), "--ros-args", "-p", "example:=9"],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
        cwd=tmp_path,
    )
    assert run.returncode == 2 and "example out of range" in run.stderr  # it ran, from the install space
    imported = subprocess.run(
        [sys.executable, "-c", "import lenn_ros; print(lenn_ros.__file__)"],
        env=env,
        capture_output=True,
        text=True,
        cwd=tmp_path,
        check=True,
    )
    assert str(prefix) in imported.stdout

"""The README and the documentation site say what is true, and the site builds.

- The parameter reference is generated from lenn_ros/config.py: the committed page must be
  what docs/gen_parameters.py writes now, so it cannot drift from the node's parameters.
- The README stays short (issue 19: at most 15 KB), its quick start names make targets that
  exist, its links resolve, and its robot command is the one test_robot_defaults.py runs.
- ``mkdocs build --strict`` passes, and the link validation in mkdocs.yml really fails a
  build on a broken link or anchor (checked on a copy with one of each).
"""

from __future__ import annotations

import importlib.util
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
MKDOCS = importlib.util.find_spec("mkdocs") is not None
README_LIMIT = 15_000  # bytes (issue 19)


def _generator():
    spec = importlib.util.spec_from_file_location("gen_parameters", REPO / "docs" / "gen_parameters.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_parameter_page_is_what_config_generates() -> None:
    generator = _generator()
    committed = (REPO / "docs" / "parameters.md").read_text()
    assert committed == generator.render(), "docs/parameters.md is stale: run python docs/gen_parameters.py"


def test_every_declared_parameter_has_a_row_with_its_default() -> None:
    from lenn_ros.config import NODE_PARAMETERS, identifier_parameters

    page = (REPO / "docs" / "parameters.md").read_text()
    generator = _generator()
    for parameter in identifier_parameters(0, "lenn") + NODE_PARAMETERS:
        row = next((line for line in page.splitlines() if f'<span id="{parameter.name}"></span>' in line), None)
        assert row is not None, parameter.name
        assert generator.show(parameter.default).replace("|", "\\|") in row, (parameter.name, row)
        assert ("| live |" in row) == parameter.live, (parameter.name, row)


def test_the_readme_is_short_and_its_links_resolve() -> None:
    text = README.read_text()
    assert len(text.encode()) <= README_LIMIT, len(text.encode())
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    assert links, "the README links to the documentation"
    for target in links:
        if "://" in target:
            continue
        assert (REPO / target).exists(), target


def test_the_quick_start_commands_are_make_targets() -> None:
    text = README.read_text()
    quick = text.split("## Quick start", 1)[1].split("\n## ", 1)[0]
    commands = re.findall(r"^make (\w+)", quick, flags=re.MULTILINE)
    assert commands == ["demo", "test"], commands
    makefile = (REPO / "Makefile").read_text()
    for target in commands:
        assert re.search(rf"^{target}:", makefile, flags=re.MULTILINE), target
    builds_site = re.search(r"^test:.*\n(\t.*\n)*\t\$\(MAKE\) docs$", makefile, flags=re.MULTILINE)
    assert builds_site, "make test builds the site"


def test_the_readme_robot_command_is_the_one_test_robot_defaults_runs() -> None:
    """The README says "nothing else is needed": test_robot_defaults.py runs exactly its parameters."""
    try:
        from test_robot_defaults import README_COMMAND
    except pytest.skip.Exception:
        pytest.skip("rclpy is not installed (test_robot_defaults.py needs it)")
    text = README.read_text()
    block = text.split("## Connecting a real robot", 1)[1].split("```bash", 1)[1].split("```", 1)[0]
    command = block.split("ros2 topic echo", 1)[0]
    given = re.findall(r"-p (\w+):=", command)
    assert given == [item.split(":=")[0] for item in README_COMMAND], given


@pytest.mark.skipif(not MKDOCS, reason="mkdocs is not installed (pip install -e '.[docs]')")
def test_the_site_builds_strict(tmp_path: Path) -> None:
    result = _build(REPO, tmp_path / "site")
    assert result.returncode == 0, result.stdout + result.stderr
    assert (tmp_path / "site" / "parameters" / "index.html").exists()
    assert (tmp_path / "site" / "results" / "index.html").exists(), "bench/RESULTS.md is part of the site"


@pytest.mark.skipif(not MKDOCS, reason="mkdocs is not installed (pip install -e '.[docs]')")
@pytest.mark.parametrize(
    ("broken", "said"),
    [("[x](nowhere.md)", "nowhere.md"), ("[x](robots.md#no-such-section)", "no-such-section")],
)
def test_a_broken_link_or_anchor_fails_the_build(tmp_path: Path, broken: str, said: str) -> None:
    copy = tmp_path / "repo"
    (copy / "bench").mkdir(parents=True)
    shutil.copy(REPO / "mkdocs.yml", copy)
    shutil.copy(REPO / "bench" / "RESULTS.md", copy / "bench")
    shutil.copytree(REPO / "docs", copy / "docs", symlinks=True)
    index = copy / "docs" / "index.md"
    index.write_text(index.read_text() + f"\nA link that must fail: {broken}\n")
    result = _build(copy, tmp_path / "site")
    assert result.returncode != 0
    assert said in result.stdout + result.stderr


def _build(root: Path, site: Path) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)]
    return subprocess.run(command, cwd=root, capture_output=True, text=True, timeout=120)

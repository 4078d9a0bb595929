"""Dependencies: everything lenn_ros imports is declared, and the optional ones say what to install.

Plots (matplotlib) and progress bars (tqdm) are extras (``plot``, ``progress``). Without
matplotlib a plot request ends in one line naming the extra (exit 2, no traceback);
without tqdm a run goes on without a bar and says so once.
"""

from __future__ import annotations

import ast
import importlib.metadata
import re
import subprocess
import sys
from pathlib import Path

import pytest

from lenn_ros import progress as bars

REPO = Path(__file__).resolve().parents[1]
#: ROS packages come from apt or the ``ros`` extra's wheels; package.xml declares each
ROS_DECLARED = set(re.findall(r"<exec_depend>(\w+)</exec_depend>", (REPO / "package.xml").read_text()))


def _imported_top_level_modules() -> set[str]:
    modules: set[str] = set()
    for path in (REPO / "lenn_ros").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                modules |= {alias.name.split(".")[0] for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                modules.add(node.module.split(".")[0])
    return modules - set(sys.stdlib_module_names) - {"lenn_ros", "__future__"}


def _normalise(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def test_every_imported_package_is_declared() -> None:
    """zstandard and lz4 (bag/scalars.py) were imported but declared nowhere: mcap happened to bring them."""
    setup = (REPO / "setup.py").read_text()
    declared = {_normalise(name) for name in re.findall(r'"([A-Za-z0-9_.-]+)\s*(?:[<>=!~]=?|")', setup)}
    distributions = importlib.metadata.packages_distributions()
    undeclared = []
    for module in sorted(_imported_top_level_modules()):
        if module in ROS_DECLARED:
            continue
        names = {_normalise(name) for name in distributions.get(module, [module])}
        if not names & declared:
            undeclared.append(module)
    assert not undeclared, f"imported by lenn_ros but not in setup.py: {undeclared}"


def test_a_plot_without_matplotlib_says_which_extra_in_one_line(tmp_path: Path) -> None:
    code = (
        "import sys; sys.modules['matplotlib'] = None\n"  # as if not installed: its import fails
        "from lenn_ros.cli import main\n"
        f"sys.exit(main(['evaluate', {str(REPO / 'bags' / 'example1')!r}, '--plot', {str(tmp_path / 'p.png')!r}]))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=REPO)
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    lines = result.stderr.strip().splitlines()
    said = "lenn-ros evaluate: error: plots need matplotlib, which is not installed: pip install 'lenn_ros[plot]'"
    assert lines == [said]
    assert not (tmp_path / "p.png").exists()


def test_without_tqdm_a_run_goes_on_without_a_bar_and_says_so(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "tqdm", None)
    bar = bars.progress(3, True, "reproduce")
    for _ in range(3):
        bar.update(1)
    bar.close()
    assert capsys.readouterr().err.strip().splitlines() == [
        "reproduce: no progress bar (tqdm is not installed: pip install 'lenn_ros[progress]')"
    ]
    bars.progress(3, False, "reproduce --json").close()  # no bar asked for: nothing said
    assert capsys.readouterr().err == ""

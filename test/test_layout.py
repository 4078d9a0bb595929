"""The package's layout: no import cycles, layers that import downwards only, no benchmarks inside it,
figures that leave the backend alone."""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lenn_ros.paper.examples import EXAMPLES

REPO = Path(__file__).resolve().parents[1]
PACKAGE = REPO / "lenn_ros"


def _modules() -> dict[str, Path]:
    modules = {}
    for path in PACKAGE.rglob("*.py"):
        parts = path.relative_to(REPO).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def _imports(path: Path, modules: dict[str, Path] | None = None) -> set[str]:
    """lenn_ros modules a file imports, at module level or inside functions.

    ``from pkg import sub`` is an edge to ``pkg.sub`` when that is a module, else to ``pkg``.
    """
    modules = _modules() if modules is None else modules
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("lenn_ros"):
            for alias in node.names:
                sub = f"{node.module}.{alias.name}"
                names.add(sub if sub in modules else node.module)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names if alias.name.startswith("lenn_ros"))
    return names


def _module_graph() -> dict[str, set[str]]:
    """Edges between lenn_ros modules; a submodule's own parent packages are left out (Python
    runs a package's __init__ before any of its submodules, whoever imports them)."""
    modules = _modules()
    return {
        name: {m for m in _imports(path, modules) if m in modules and m != name and not name.startswith(m + ".")}
        for name, path in modules.items()
    }


def test_no_import_cycles_in_the_package() -> None:
    """Lazy imports count too: cli -> bench -> cli was such a cycle."""
    graph = _module_graph()
    state: dict[str, int] = {}

    def visit(name: str, trail: list[str]) -> None:
        state[name] = 1
        for target in sorted(graph[name]):
            if state.get(target) == 1:
                cycle = [*trail[trail.index(target) :], target] if target in trail else [name, target]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if target not in state:
                visit(target, [*trail, target])
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [name])


#: what each layer must not import, at module level or inside functions (a prefix covers its submodules)
_LAYERS = {
    # the runtime: numpy/numba only; model building, the paper, ROS and bags sit above it
    "core": ("lenn_ros.fit", "lenn_ros.paper", "lenn_ros.nodes", "lenn_ros.bag", "rclpy"),
    # model building runs offline, without ROS (it reads bags through lenn_ros.bag, not rclpy)
    "fit": ("rclpy", "lenn_ros.nodes"),
}
#: the only lenn_ros modules outside lenn_ros.core that core may import (none today)
_CORE_MAY_IMPORT: tuple[str, ...] = ()


def _imported_modules(path: Path) -> set[str]:
    """Every module a file names in an import statement (absolute names; relative ones resolved)."""
    package = ".".join(path.relative_to(REPO).with_suffix("").parts[:-1])
    names: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1]) if node.level else ""
            module = ".".join(part for part in (base, node.module or "") if part)
            names.add(module)
            names.update(f"{module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return names


def test_the_layers_import_downwards_only() -> None:
    """core (the runtime) imports no fit, paper, nodes, bag or rclpy, and nothing else of the package
    beyond _CORE_MAY_IMPORT; fit imports no rclpy and no nodes. Checked in the source (lazy imports
    too) and by importing every module of both in a fresh interpreter (what they pull in)."""

    def under(name: str, prefixes: tuple[str, ...]) -> bool:
        return any(name == prefix or name.startswith(prefix + ".") for prefix in prefixes)

    offenders = []
    for layer, forbidden in _LAYERS.items():
        for path in sorted((PACKAGE / layer).rglob("*.py")):
            for name in sorted(_imported_modules(path)):
                allowed = name == "lenn_ros" or under(name, ("lenn_ros.core", *_CORE_MAY_IMPORT))
                if under(name, forbidden) or (layer == "core" and under(name, ("lenn_ros",)) and not allowed):
                    offenders.append(f"{path.relative_to(REPO)} imports {name}")
    assert not offenders, "\n".join(offenders)
    code = (
        "import importlib, pkgutil, sys\n"
        f"layers = {_LAYERS!r}\n"
        "for layer, forbidden in layers.items():\n"
        "    package = importlib.import_module('lenn_ros.' + layer)\n"
        "    for module in pkgutil.iter_modules(package.__path__):\n"
        "        importlib.import_module(f'lenn_ros.{layer}.{module.name}')\n"
        "    print(layer, *sorted(m for m in sys.modules if any(m == f or m.startswith(f + '.') for f in forbidden)))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split("\n")[:2] == ["core", "fit"], result.stdout


#: single modules with a rule of their own: what each must not import (a prefix covers its submodules)
_MODULE_RULES = {
    # the one table of parameters: a preset's numbers are data (lenn_ros.presets), not the paper harness
    # (simulators, networks); the service layer builds from the table, so the table is below it
    "lenn_ros.config": ("lenn_ros.paper", "lenn_ros.service"),
    # presets are data: the table and the paper harness both read them, so they import neither (nor numpy)
    "lenn_ros.presets": ("lenn_ros.config", "lenn_ros.core", "lenn_ros.paper", "lenn_ros.service", "numpy"),
}


def test_config_reads_presets_as_data_not_the_paper_harness() -> None:
    """config imports no lenn_ros.paper (nor the service layer above it) and presets import nothing heavy:
    in the source (lazy imports too) and by what importing each pulls in, in a fresh interpreter."""
    modules = _modules()
    offenders = [
        f"{modules[module].relative_to(REPO)} imports {name}"
        for module, forbidden in _MODULE_RULES.items()
        for name in sorted(_imported_modules(modules[module]))
        if any(name == prefix or name.startswith(prefix + ".") for prefix in forbidden)
    ]
    assert not offenders, "\n".join(offenders)
    for module, forbidden in _MODULE_RULES.items():
        code = (
            f"import importlib, sys; importlib.import_module({module!r})\n"
            f"print(*sorted(m for m in sys.modules if any(m == f or m.startswith(f + '.') for f in {forbidden!r})))\n"
        )
        result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, cwd=REPO)
        assert result.returncode == 0, result.stderr
        assert result.stdout.strip() == "", f"importing {module} loads {result.stdout.strip()}"


#: rclpy's non-public API as the code would spell it: the native module, the C handles, its private fields
_RCLPY_INTERNALS = (
    "implementation_singleton",
    r"rclpy\.impl",
    r"\.handle\b",
    "take_message",
    "publish_raw",
    "_callback_type",
)


def test_rclpy_internals_are_used_in_one_module_only() -> None:
    """Package, benchmarks and tests go through lenn_ros.nodes.rclpy_internals (version check, fallback)."""
    allowed = PACKAGE / "nodes" / "rclpy_internals.py"
    offenders = []
    for folder in (PACKAGE, REPO / "bench", REPO / "test"):
        for path in folder.rglob("*.py"):
            if path == allowed or path == Path(__file__).resolve():
                continue
            for number, line in enumerate(path.read_text().splitlines(), 1):
                code = line.split("#", 1)[0]
                offenders += [f"{path.relative_to(REPO)}:{number}: {w}" for w in _RCLPY_INTERNALS if re.search(w, code)]
    assert not offenders, "\n".join(offenders)
    assert all(re.search(word, allowed.read_text()) for word in _RCLPY_INTERNALS[:-2])  # it looks for real words


def test_benchmarks_live_outside_the_installed_package() -> None:
    assert not (PACKAGE / "bench.py").exists() and not (PACKAGE / "benchmarks").exists()
    assert (REPO / "bench" / "speed.py").is_file()
    assert not any("bench" in m for m in _imports(PACKAGE / "cli.py"))


@pytest.mark.parametrize("number", [1, 2, 3, 4])
def test_training_pairs_are_the_series_parallel_offset(number: int) -> None:
    """Row r: x(k), k = warm_up - 1 + r, predicts y(k+1); the target is y(k+1) - lin(k)."""
    structure = EXAMPLES[number].structure
    rng = np.random.default_rng(number)
    u, y = rng.uniform(-1, 1, 40), rng.uniform(-1, 1, 40)
    inputs, targets, linear = structure.training_pairs(u, y)
    x, lin = structure.regressors(u, y)
    assert len(inputs) == len(targets) == len(linear) == len(y) - structure.warm_up
    for r in (0, len(targets) - 1):
        k = structure.warm_up - 1 + r
        assert np.array_equal(inputs[r], x[r]) and linear[r] == lin[r]
        assert targets[r] == y[k + 1] - lin[r]


def test_figures_do_not_switch_the_callers_matplotlib_backend(tmp_path: Path) -> None:
    """A caller that chose a backend keeps it after lenn_ros draws (matplotlib.use('Agg') switched it)."""
    png = tmp_path / "figure.png"
    code = (
        "import matplotlib, numpy as np\n"
        "matplotlib.use('svg')\n"
        "from lenn_ros.plotting import plot_identification\n"
        f"plot_identification({str(png)!r}, np.sin(np.arange(50) / 5), np.zeros(50), 'test', np.ones(50))\n"
        "import matplotlib.pyplot as plt\n"
        "print(matplotlib.get_backend(), len(plt.get_fignums()))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert result.stdout.split() == ["svg", "0"]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_no_module_over_900_lines_no_class_over_500_and_one_pair_raw() -> None:
    """Issue 42's structure: small modules and classes, each rule written once."""
    too_long, classes, pair_raw = [], [], []
    for path in PACKAGE.rglob("*.py"):
        text = path.read_text()
        if text.count("\n") > 900:
            too_long.append(f"{path.relative_to(REPO)}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef) and node.end_lineno - node.lineno + 1 > 500:
                classes.append(f"{path.relative_to(REPO)}: {node.name}, {node.end_lineno - node.lineno + 1} lines")
            if isinstance(node, ast.FunctionDef) and node.name == "pair_raw":
                pair_raw.append(str(path.relative_to(REPO)))
    assert too_long == [] and classes == []
    assert pair_raw == ["lenn_ros/service/recording.py"]


def test_single_or_several_channel_branches_stay_few() -> None:
    """A model of several channels composes one-channel models: its branches are counted (68 before issue 42)."""
    branch = re.compile(r"^\s*(?:el)?if .*(?:mimo|Mimo|MIMO)")
    found = [
        f"{path.relative_to(REPO)}:{number}"
        for path in PACKAGE.rglob("*.py")
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if branch.match(line)
    ]
    assert len(found) <= 15, found


def test_readme_and_results_stay_short() -> None:
    assert len((REPO / "README.md").read_bytes()) <= 15_000
    assert (REPO / "bench" / "RESULTS.md").read_text().count("\n") <= 480

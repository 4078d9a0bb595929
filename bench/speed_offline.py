"""Offline speed: cost per update, training throughput, compiled-vs-Python agreement.

Every figure is the median over ``Sizes.repeats`` runs, each on a fresh model (same
seed, same data), with the garbage collector off (as ``timeit`` does); the variants
compared with each other take turns within every repeat (:func:`interleaved_medians`). Times are the
process's CPU time (``time.process_time``: user + system, CLOCK_PROCESS_CPUTIME_ID),
not wall-clock time: on a shared machine another process's share of the core is then
not counted against the code measured. Everything measured here runs on one thread
(the kernels are not parallel, numpy's ufuncs on these sizes neither), so CPU time is
what the wall clock shows on an idle core; :data:`CLOCK` records both for the report.
Every ratio is formed from figures measured in the same call. The data are the
examples' own series (the plant simulated with the paper's input), so the learning
rules do what they do in a real run; where more samples are needed than were
simulated, the simulated series is repeated.
"""

from __future__ import annotations

import contextlib
import copy
import gc
import io
import math
import statistics
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from lenn_ros.core import jit, learning_rules
from lenn_ros.core.networks import MLP, FunctionalLinkNetwork, OnlineRegressor
from lenn_ros.core.structure import Identifier
from lenn_ros.paper.evaluation import simulate
from lenn_ros.paper.examples import EXAMPLES, PaperExample

#: Samples simulated per example; longer series repeat this one (simulating the plant
#: in Python costs ~30 us a sample, far more than what is being measured).
SIMULATED = 50_000


@dataclass(frozen=True)
class Sizes:
    repeats: int
    fit_samples: int  # samples per partial_fit / predict call (cost per update)
    single_calls: int  # one-sample update() calls timed in a row
    train_samples: int  # Ex. 1 LeNN / MLP training throughput
    numpy_samples: int  # the plain-numpy reference loop (slow)
    run_samples: int  # Ex. 4 LeNN through Identifier.run
    bag_samples: int  # lenn-ros evaluate on a bag of this many samples
    equality_samples: int = 2000

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


FULL = Sizes(
    repeats=7,
    fit_samples=50_000,
    single_calls=2_000,
    train_samples=200_000,
    numpy_samples=20_000,
    run_samples=1_000_000,
    bag_samples=50_000,
)
QUICK = Sizes(
    repeats=3,
    fit_samples=10_000,
    single_calls=300,
    train_samples=50_000,
    numpy_samples=3_000,
    run_samples=100_000,
    bag_samples=5_000,
)


# --------------------------------------------------------------------------- helpers


#: CPU and wall-clock seconds of everything :func:`timed` measured (CPU / wall = the share
#: of a core the benchmark got; well below 1 means the machine was busy with other work).
CLOCK = {"cpu_s": 0.0, "wall_s": 0.0}


def timed(function: Callable[[], Any]) -> float:
    """CPU seconds one call of ``function`` takes, garbage collector off."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        wall, cpu = time.perf_counter(), time.process_time()
        function()
        cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
        CLOCK["cpu_s"] += cpu
        CLOCK["wall_s"] += wall
        return cpu
    finally:
        if enabled:
            gc.enable()


Case = tuple[Callable[[Any], Any], Callable[[], Any] | None]  # (function(state), setup() -> state)


def interleaved_medians(cases: dict[str, Case], repeats: int) -> dict[str, float]:
    """Median CPU seconds of each case, the cases taking turns within every repeat.

    Taking turns puts every case into the same stretches of time: on a shared machine
    a busy spell (a neighbour on the other hyper-thread, a cache-hungry process) then
    slows all of them, not only the one that happened to run, and the ratios formed
    from them stay fair. Each case gets a fresh ``setup()`` state every time.
    """
    times: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(repeats):
        for name, (function, setup) in cases.items():
            state = setup() if setup is not None else None
            times[name].append(timed(lambda function=function, state=state: function(state)))
    return {name: float(statistics.median(values)) for name, values in times.items()}


@lru_cache(maxsize=8)
def _simulated(number: int, samples: int) -> tuple[np.ndarray, np.ndarray]:
    example = EXAMPLES[number]
    series = simulate(example.plant(), example.noise_db, seed=0, train_samples=samples, test_samples=0)
    return series.u, series.y


def example_series(number: int, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """(u, y) of example ``number``: ``samples`` long, the simulated run repeated as needed."""
    base = min(samples, SIMULATED)
    u, y = _simulated(number, base)
    repeats = -(-samples // base)
    return np.tile(u, repeats)[:samples], np.tile(y, repeats)[:samples]


def training_pairs(example: PaperExample, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Network inputs x and targets d (what Identifier.run feeds the model), ``samples`` rows."""
    structure = example.structure
    u, y = example_series(example.number, samples + structure.warm_up)
    inputs, targets, _ = structure.training_pairs(u, y)
    return np.ascontiguousarray(inputs), targets


def fresh_network(example: PaperExample, kind: str, x: np.ndarray, d: np.ndarray) -> OnlineRegressor:
    """The example's network, seed 0, initialised and its compiled kernel loaded."""
    network = example.make_network(kind, 0)
    network.update(x[:1], d[:1], learn=False)
    return network


def kernel_inputs(network: OnlineRegressor, x: np.ndarray) -> np.ndarray:
    """What ``network.update`` hands its kernel for inputs ``x`` (features for a LeNN)."""
    if isinstance(network, MLP):
        return np.ascontiguousarray(network._check_inputs(x)[:, network.input_order_])
    return network.features(x)


def run_kernel(
    network: OnlineRegressor, inputs: np.ndarray, targets: np.ndarray, learn: bool = True, python: bool = False
) -> np.ndarray:
    """Call the network's kernel directly on prepared ``inputs`` (its own state arrays).

    ``python`` runs the kernel's ``.py_func`` (the pure-Python fallback) instead of
    the compiled version. Targets are passed read-only, as ``update`` passes them, so
    the compiled specialisation is the one the package uses.
    """

    def pick(function):
        return function.py_func if python else function

    targets = np.broadcast_to(np.asarray(targets, dtype=np.float64), (inputs.shape[0],))
    y = np.empty(inputs.shape[0])
    net = network
    if isinstance(net, MLP):
        done = pick(learning_rules.mlp_sgd)(
            net.params_,
            net.momentum_,
            inputs,
            targets,
            net.layout_,
            net.n_activations_,
            float(net.alpha),
            float(net.beta),
            net.output == "tanh",
            float(net.output_scale),
            learn,
            y,
        )
    elif isinstance(net, FunctionalLinkNetwork) and net.solver == "sgd":
        done = pick(learning_rules.functional_link_sgd)(
            net.weights_,
            net.momentum_,
            inputs,
            targets,
            net.feature_branch_,
            len(net.branch_inputs_),
            float(net.alpha),
            float(net.beta),
            net.output == "tanh",
            float(net.output_scale),
            learn,
            y,
        )
    elif isinstance(net, FunctionalLinkNetwork) and net.solver == "nlms":
        done = pick(learning_rules.functional_link_nlms)(
            net.weights_, inputs, targets, float(net.nlms_step), 1e-6, learn, y
        )
    else:
        done = pick(learning_rules.functional_link_rls)(
            net.weights_, net.covariance_, inputs, targets, float(net.forgetting), net.trace_bound, learn, y,
            np.empty(0),  # (no leverage wanted)
        )  # fmt: skip
    if done != inputs.shape[0]:
        raise FloatingPointError(f"kernel stopped at sample {done} (divergence) during the benchmark")
    return y


# --------------------------------------------------------------------------- 1. cost per update


def cost_per_update(sizes: Sizes) -> list[dict[str, Any]]:
    """Per example and network: us per sample of partial_fit, kernel, predict; us per 1-sample call."""
    rows = []
    for number, example in EXAMPLES.items():
        x, d = training_pairs(example, sizes.fit_samples)
        row: dict[str, Any] = {"example": number}
        for kind in ("lenn", "mlp"):
            row[kind] = _update_costs(example, kind, x, d, sizes)
        lenn, mlp = row["lenn"], row["mlp"]
        row["table1_mult_ratio"] = mlp["multiplications"] / lenn["multiplications"]
        for key in ("partial_fit_us", "kernel_us", "predict_us", "single_call_us", "live_step_us"):
            row[f"ratio_{key.removesuffix('_us')}"] = mlp[key] / lenn[key]
        row["explanation"] = explain(row)
        rows.append(row)
    return rows


def live_step_case(example: PaperExample, kind: str, calls: int) -> Case:
    """The node's path: ``Identifier.step``, one pair at a time (one compiled call for the LeNN)."""
    u_series, y_series = (series.tolist() for series in example_series(example.number, calls))

    def setup() -> Identifier:
        return Identifier(example.structure, example.make_network(kind, 0))

    def live(identifier: Identifier) -> None:
        for k in range(calls):
            identifier.step(k + 1, u_series[k], y_series[k], True)

    live(setup())  # the first call compiles (or loads) the step
    return live, setup


def _update_costs(example: PaperExample, kind: str, x: np.ndarray, d: np.ndarray, sizes: Sizes) -> dict[str, Any]:
    n, repeats = len(d), sizes.repeats

    def setup() -> OnlineRegressor:
        return fresh_network(example, kind, x, d)

    def kernel_setup() -> tuple[OnlineRegressor, np.ndarray]:
        network = setup()
        return network, kernel_inputs(network, x)

    calls = min(sizes.single_calls, n)

    def single(network: OnlineRegressor) -> None:
        for k in range(calls):
            network.update(x[k : k + 1], d[k : k + 1])

    def single_expansion(network: OnlineRegressor) -> None:
        for k in range(calls):
            network.features(x[k : k + 1])

    trained = setup()
    trained.partial_fit(x, d)
    cases: dict[str, Case] = {
        "fit": (lambda network: network.partial_fit(x, d), setup),
        "kernel": (lambda state: run_kernel(state[0], state[1], d), kernel_setup),
        "predict": (lambda _: trained.predict(x), None),
        "single": (single, setup),
        "live": live_step_case(example, kind, calls),
    }
    if kind == "lenn":
        cases["expansion"] = (lambda _: trained.features(x), None)
        cases["single_expansion"] = (single_expansion, setup)
    medians = interleaved_medians(cases, repeats)
    fit, kernel, predict, one = medians["fit"], medians["kernel"], medians["predict"], medians["single"]
    expansion, one_expansion = medians.get("expansion", 0.0), medians.get("single_expansion", 0.0)
    counts = example.complexity(kind)
    return {
        "partial_fit_us": fit / n * 1e6,
        "kernel_us": kernel / n * 1e6,
        "expansion_us": expansion / n * 1e6,
        "predict_us": predict / n * 1e6,
        "single_call_us": one / calls * 1e6,
        "live_step_us": medians["live"] / calls * 1e6,
        "single_call_expansion_us": one_expansion / calls * 1e6,
        "weights": counts.weights,
        "multiplications": counts.multiplications,
        "additions": counts.additions,
        "tanh": counts.tanh,
    }


def explain(row: dict[str, Any]) -> str:
    """One line on why the measured MLP/LeNN ratios differ from Table I's (built from the figures)."""
    lenn, mlp = row["lenn"], row["mlp"]
    predicted, kernel = row["table1_mult_ratio"], row["ratio_kernel"]
    # cost per multiplication Table I counts: fixed per-sample work and tanh show up here
    lenn_ns = lenn["kernel_us"] * 1e3 / lenn["multiplications"]
    mlp_ns = mlp["kernel_us"] * 1e3 / mlp["multiplications"]
    per_mult = f"LeNN {lenn_ns:.1f} ns, MLP {mlp_ns:.1f} ns per counted multiplication"
    if abs(math.log(kernel / predicted)) < math.log(1.3):
        head = f"kernel {kernel:.1f}x ~ Table I's {predicted:.1f}x ({per_mult})"
    elif kernel > predicted:
        head = (
            f"kernel {kernel:.1f}x > {predicted:.1f}x ({per_mult}): the MLP's {mlp['tanh']} tanh per sample "
            f"(vs {lenn['tanh']}) cost far more than a multiplication"
        )
    else:
        head = (
            f"kernel {kernel:.1f}x < {predicted:.1f}x ({per_mult}): the LeNN's fixed per-sample work (a-priori "
            f"output store, finite-step check pass, loop set-up) is not in Table I and weighs more on "
            f"{lenn['weights']} weights"
        )
    fit = (
        f"partial_fit {row['ratio_partial_fit']:.1f}x: the LeNN also pays its Legendre expansion, not counted in "
        f"Table I: alone it measures {lenn['expansion_us']:.2f} of the LeNN's {lenn['partial_fit_us']:.2f} us per "
        "sample (vectorised over the batch, it streams order + 1 columns of 8 B per sample through memory)"
    )
    single = (
        f"1-sample call {row['ratio_single_call']:.2f}x: fixed per-call overhead swamps the arithmetic: "
        f"{lenn['single_call_us']:.0f} us per LeNN call (its one-sample expansion alone: "
        f"{lenn['single_call_expansion_us']:.0f} us), {mlp['single_call_us']:.0f} us per MLP call: Python and "
        "numpy work per call (input checks, array wrapping, kernel dispatch) that does not grow with the network"
    )
    live = (
        f"live step {row['ratio_live_step']:.2f}x: the node's Identifier.step is {lenn['live_step_us']:.1f} us for "
        f"the LeNN (regressor, expansion, rule and prediction in one compiled call), {mlp['live_step_us']:.1f} us "
        "for the MLP (a Python regressor and two kernel calls)"
    )
    return "; ".join((head, fit, single, live))


# --------------------------------------------------------------------------- 2. throughput


def numpy_reference_loop(
    phi: np.ndarray, d: np.ndarray, weights: np.ndarray, alpha: float, beta: float
) -> tuple[np.ndarray, np.ndarray]:
    """The paper's rule as plain numpy, one sample at a time (the reference to beat).

    y = tanh(w . phi); e = d - y; dw = alpha e (1 - y^2) phi + beta dw; w += dw.
    """
    w = np.array(weights, copy=True)
    dw = np.zeros_like(w)
    y_out = np.empty(len(d))
    for k in range(len(d)):
        p = phi[k]
        y = np.tanh(w @ p)
        e = d[k] - y
        dw = alpha * e * (1.0 - y * y) * p + beta * dw
        w += dw
        y_out[k] = y
    return w, y_out


def offline_throughput(sizes: Sizes) -> dict[str, Any]:
    """Samples/s: Ex. 1 LeNN compiled vs the numpy loop, MLP {1-20-10-1}, Ex. 4 through Identifier.run."""
    result: dict[str, Any] = {}
    ex1 = EXAMPLES[1]
    x, d = training_pairs(ex1, sizes.train_samples)

    def setup_lenn():
        return fresh_network(ex1, "lenn", x, d)

    def setup_mlp():
        return fresh_network(ex1, "mlp", x, d)

    # the learning rule alone runs on features expanded beforehand: compiled kernel vs numpy loop
    reference_net = setup_lenn()
    phi = reference_net.features(x)
    n_np = sizes.numpy_samples

    def numpy_run(net):
        return numpy_reference_loop(phi[:n_np], d[:n_np], net.weights_, float(net.alpha), float(net.beta))

    ex4 = EXAMPLES[4]
    u, y = example_series(4, sizes.run_samples)
    warm = Identifier(ex4.structure, ex4.make_network("lenn", 0))
    warm.run(u[:2000], y[:2000])  # load the compiled kernel once

    def run_setup():
        return Identifier(ex4.structure, ex4.make_network("lenn", 0))

    medians = interleaved_medians(
        {
            "compiled": (lambda net: net.partial_fit(x, d), setup_lenn),
            "expansion": (lambda _: reference_net.features(x), None),
            "kernel": (lambda net: run_kernel(net, phi, d), setup_lenn),
            "numpy": (numpy_run, setup_lenn),
            "mlp": (lambda net: net.partial_fit(x, d), setup_mlp),
            "run": (lambda identifier: identifier.run(u, y), run_setup),
        },
        sizes.repeats,
    )
    n = sizes.train_samples
    compiled_rate, kernel_rate = n / medians["compiled"], n / medians["kernel"]
    loop_rate, expansion = n_np / medians["numpy"], medians["expansion"]
    # the numpy loop fed by the same vectorised expansion partial_fit uses
    numpy_rate = 1.0 / (1.0 / loop_rate + expansion / n)
    # both implement the same rule: weights after the same samples agree to rounding
    a, b = setup_lenn(), setup_lenn()
    a.partial_fit(x[:n_np], d[:n_np])
    w_numpy, _ = numpy_run(b)
    result["lenn_ex1"] = {
        "samples": n,
        "samples_per_s": compiled_rate,
        "kernel_samples_per_s": kernel_rate,
        "expansion_us_per_sample": expansion / n * 1e6,
        "numpy_loop_samples": n_np,
        "numpy_loop_samples_per_s": numpy_rate,
        "numpy_rule_only_samples_per_s": loop_rate,
        "speedup_vs_numpy": compiled_rate / numpy_rate,
        "kernel_speedup_vs_numpy_rule": kernel_rate / loop_rate,
        "numpy_loop_max_abs_weight_difference": float(np.max(np.abs(a.weights_ - w_numpy))),
    }
    result["mlp_ex1"] = {"layers": "1-20-10-1", "samples": n, "samples_per_s": n / medians["mlp"]}
    run = medians["run"]
    result["identifier_run_ex4"] = {"samples": sizes.run_samples, "samples_per_s": sizes.run_samples / run}
    result["evaluate_bag"] = evaluate_throughput(sizes)
    return result


#: the identifier configuration the evaluated bag is run with (the bag holds no identifier_config)
PARAMS_EXAMPLE1 = Path(__file__).resolve().parents[1] / "config" / "example1_lenn.yaml"


def evaluate_throughput(sizes: Sizes) -> dict[str, Any]:
    """``lenn-ros evaluate BAG --json`` (in-process) on a bag of Ex. 1 data; skipped without lenn_ros.bag."""
    try:
        from lenn_ros import cli
        from lenn_ros.bag import BagWriter, read_run
    except ImportError as error:
        return {"skipped": f"lenn_ros.bag not available ({error})"}
    n = sizes.bag_samples
    test = min(600, n // 10)
    example = EXAMPLES[1]
    series = simulate(example.plant(), example.noise_db, seed=0, train_samples=n - test, test_samples=test)
    with tempfile.TemporaryDirectory(prefix="lenn-bench-") as directory:
        bag = Path(directory) / "bench_bag"
        start = time.process_time()
        with BagWriter(bag, flush_period=None) as writer:
            for topic in ("/u", "/y_p", "/test_start"):
                writer.add_topic(topic)
            writer.write_value("/test_start", n - test + 1, 0)
            for k, (u, y) in enumerate(zip(series.u.tolist(), series.y.tolist(), strict=True)):
                writer.write_value("/u", u, k * 1_000_000)
                writer.write_value("/y_p", y, k * 1_000_000)
        write_seconds = time.process_time() - start
        output = io.StringIO()

        def evaluate() -> None:
            output.seek(0)
            output.truncate()
            with contextlib.redirect_stdout(output):
                code = cli.main(["evaluate", str(bag), "--params", str(PARAMS_EXAMPLE1), "--json"])
            if code != 0:
                raise RuntimeError(f"lenn-ros evaluate failed with status {code}")

        evaluate()  # warm-up (imports, compiled kernel)
        medians = interleaved_medians(
            {"evaluate": (lambda _: evaluate(), None), "read": (lambda _: read_run(bag), None)}, sizes.repeats
        )
        total, read = medians["evaluate"], medians["read"]
    return {
        "samples": n,
        "samples_per_s": n / total,
        "seconds": total,
        "read_seconds": read,
        "read_share": read / total,
        "bag_write_cpu_seconds": write_seconds,
    }


# --------------------------------------------------------------------------- 3. compiled == Python


def equality_cases(samples: int) -> list[tuple[str, OnlineRegressor, np.ndarray, np.ndarray]]:
    """Networks of every kernel with data: (name, initialised network, x, d)."""
    ex1, ex3 = EXAMPLES[1], EXAMPLES[3]
    x1, d1 = training_pairs(ex1, samples)
    x3, d3 = training_pairs(ex3, samples)
    linear = {"order": 14, "output": "linear"}
    cases = [
        ("lenn_sgd", ex1.make_network("lenn", 0), x1, d1),
        ("lenn_sgd_two_branches", ex3.make_network("lenn", 0), x3, d3),
        ("lenn_nlms", FunctionalLinkNetwork(solver="nlms", **linear), x1, d1),
        ("lenn_rls", FunctionalLinkNetwork(solver="rls", forgetting=0.999, **linear), x1, d1),
        ("mlp", ex1.make_network("mlp", 0), x1, d1),
        ("mlp_two_branches", ex3.make_network("mlp", 0), x3, d3),
    ]
    for _, network, _, _ in cases:
        network._initialise()
    return cases


def kernel_equality(samples: int = 2000) -> dict[str, dict[str, float]]:
    """Max |compiled - py_func| of the learned state and the outputs after ``samples`` updates."""
    result = {}
    for name, network, x, d in equality_cases(samples):
        python = copy.deepcopy(network)
        inputs = kernel_inputs(network, x)
        y_compiled = run_kernel(network, inputs, d)
        start = time.process_time()
        y_python = run_kernel(python, inputs, d, python=True)
        seconds = time.process_time() - start
        compiled_state, python_state = network.state(), python.state()
        state_difference = max(
            (
                float(np.max(np.abs(compiled_state[k] - python_state[k])))
                for k in compiled_state
                if compiled_state[k].size
            ),
            default=0.0,
        )
        result[name] = {
            "samples": samples,
            "max_abs_state_difference": state_difference,
            "max_abs_output_difference": float(np.max(np.abs(y_compiled - y_python))),
            "py_func_cpu_seconds": seconds,
            "compiled": jit.COMPILED,
        }
    return result

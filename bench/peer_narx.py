"""``lenn-ros fit`` against SysIdentPy's FROLS polynomial NARX and a linear ARX on every shared data set.

All get the same protocol, in the same run, on the same splits:
- only the samples before the test start build the model;
- ``lenn-ros fit`` with its defaults (no per-set setting);
- FROLS: the structure chosen on the last 20 % of the build samples by free-run RMSE
  (a grid of lags and polynomial degrees, terms chosen by FROLS with AIC, as a
  competent user would; grid limited to dictionaries of <= 60 candidate terms, since
  SysIdentPy's FROLS takes minutes beyond that on the Silverbox), then refitted on all
  of them;
- linear ARX: least squares, its lags (1..10, equal for y and u) chosen the same way
  by free run on the last 20 % of the build samples, then refitted on all of them;
- the score is the free-run (simulation) RMSE on the test part, the free run starting
  from the measured outputs just before it (a live switch from series-parallel to
  parallel); a diverged run scores nan. Where ``fit`` judges the test part a record of
  its own (:func:`~lenn_ros.fit.scoring.separate_test_record`), every method is seeded by
  the test part's own first samples instead, as many as it reads, and scored after them;
- wall time is measured around each whole procedure (selection included);
- beside them, the test-mean predictor: the RMSE of predicting every test sample by the
  mean of the test part (its standard deviation, an oracle no causal model is handed).
  A free-run RMSE above it means the model simulates the test part worse than a flat
  line would, whichever tool is ahead (NMSE above 0 dB); such rows are marked;
- where a best free-run figure on the same test is published, that figure
  (``PUBLISHED``, with its source), in its own column.

    pip install -e .[bench]                 # sysidentpy
    python bench/peer_narx.py               # all sets, ~15 minutes on 2 cores
    python bench/peer_narx.py --quick       # the small sets only

The several-input several-output set (the six-axis industrial robot) gets a table of
its own, one row per joint, with the same protocol: ``lenn-ros fit`` with several
``--u``/``--y`` (its MIMO model and the one-SISO-model-per-output comparison it
reports), FROLS (one model per output over the six torques and that output's own lags:
SysIdentPy's MISO form) and a full MIMO ARX (every output on the lags of every channel),
each chosen by the joint free run on the last 20 % of the build samples.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lenn_ros.core.scaling import Scaling
from lenn_ros.fit.data import Data
from lenn_ros.fit.procedure import fit
from lenn_ros.fit.termmodel import Layout, TermModel, siso_view

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
VALIDATION_FRACTION = 0.2
FROLS_GRID = [(lag, degree) for lag in (1, 2, 3, 4, 6, 8, 10) for degree in (1, 2, 3)]
FROLS_MAX_DICTIONARY = 60


@dataclass
class Split:
    name: str
    u: np.ndarray
    y: np.ndarray
    test_from: int  # 1-based, as lenn-ros fit --test-from
    note: str
    published: str = ""  # best published free-run RMSE on this test, with its source


#: best published free-run RMSE on the same test part (README of ../shared/data)
PUBLISHED = {
    "silverbox_multisine": "0.00030 (GP-NARX; SUBNET 0.00036)",
    "bouc_wen": "1.87e-05 (PNLSS tailored; dynoNet 4.52e-05)",
}


def tail_start(start: int) -> int:
    """Where the peers' held-out tail begins: the last VALIDATION_FRACTION of the build samples (at least 50).

    The peers choose their lags (and FROLS its degree) by free run on this tail, refit on
    all build samples, and are scored on the test part, as ``fit`` is (its blocks instead of a tail).
    """
    return start - max(50, round(VALIDATION_FRACTION * start))


def _csv(name: str, u: str, y: str) -> tuple[np.ndarray, np.ndarray]:
    table = np.genfromtxt(DATA / name, delimiter=",", names=True)
    return np.asarray(table[u], float), np.asarray(table[y], float)


def splits(quick: bool) -> list[Split]:
    """The shared data sets with the splits their README gives."""
    result = []
    for name, u, y in (
        ("daisy_robot-arm.csv", "u", "y"),
        ("daisy_ball-and-beam.csv", "u", "y"),
        ("daisy_exchanger.csv", "q", "th"),
    ):
        uu, yy = _csv(name, u, y)
        build = len(yy) * 2 // 3
        result.append(Split(name.removesuffix(".csv"), uu, yy, build + 1, "first 2/3 build"))
    u_id, y_id = _csv("buck_converter_id.csv", "input", "y")
    u_va, y_va = _csv("buck_converter_valid.csv", "input", "y")
    result.append(
        Split("buck_converter", np.r_[u_id, u_va], np.r_[y_id, y_va], len(y_id) + 1, "build _id, test _valid")
    )
    if quick:
        return result
    u, y = _csv("bouc_wen_multisine.csv", "u", "y")
    result.append(Split("bouc_wen", u, y, 40_961, "README split", PUBLISHED["bouc_wen"]))
    u, y = _csv("silverbox_multisine.csv", "u", "y")
    result.append(Split("silverbox_multisine", u, y, 65_063, "README split", PUBLISHED["silverbox_multisine"]))
    u, y = _csv("silverbox_arrow.csv", "u", "y")
    result.append(Split("silverbox_arrow (first 32 000 test)", u[: 65_062 + 32_000], y[: 65_062 + 32_000], 65_063,
                        "test rows inside the build amplitudes"))  # fmt: skip
    result.append(Split("silverbox_arrow (all test)", u, y, 65_063, "end extrapolates beyond the build amplitudes"))
    return result


def _rmse(y: np.ndarray, y_hat: np.ndarray) -> float:
    return float(np.sqrt(np.mean((y - y_hat) ** 2))) if np.all(np.isfinite(y_hat)) else math.nan


def seeded_from(start: int, lags: int, own: bool) -> int:
    """Where a peer's free run starts: at ``start``, or ``lags`` samples into the test part where ``fit`` judged
    it a record of its own (``own``), so that no method starts from another record's samples."""
    return start + lags if own else start


def frols_model(lag: int, degree: int, u: np.ndarray, y: np.ndarray):
    from sysidentpy.basis_function import Polynomial
    from sysidentpy.model_structure_selection import FROLS
    from sysidentpy.parameter_estimation import LeastSquares

    dictionary = math.comb(2 * lag + degree, degree)
    model = FROLS(
        order_selection=True,
        n_info_values=min(30, dictionary - 1),
        ylag=lag,
        xlag=lag,
        info_criteria="aic",
        estimator=LeastSquares(),
        basis_function=Polynomial(degree=degree),
    )
    model.fit(X=u[:, None], y=y[:, None])
    return model


def frols_free_run(model, u: np.ndarray, y: np.ndarray, start: int) -> np.ndarray:
    """SysIdentPy's simulation, seeded with the measured outputs just before ``start``."""
    lag = model.max_lag
    with np.errstate(all="ignore"):
        y_hat = model.predict(X=u[start - lag :, None], y=y[start - lag :, None])
    return np.asarray(y_hat, float).ravel()[lag:]


def run_frols(split: Split, own: bool = False) -> dict:
    began = time.perf_counter()
    start = split.test_from - 1
    u, y = split.u[:start], split.y[:start]
    validation = tail_start(start)
    tried = []
    for lag, degree in FROLS_GRID:
        if math.comb(2 * lag + degree, degree) > FROLS_MAX_DICTIONARY or 40 * lag > validation:
            continue
        try:
            model = frols_model(lag, degree, u[:validation], y[:validation])
            score = _rmse(y[validation:], frols_free_run(model, u, y, validation))
        except (ValueError, np.linalg.LinAlgError, FloatingPointError):
            score = math.nan
        tried.append((score if math.isfinite(score) else math.inf, lag, degree))
    _, lag, degree = min(tried)
    model = frols_model(lag, degree, u, y)
    first = seeded_from(start, model.max_lag, own)
    y_free = frols_free_run(model, split.u, split.y, first)
    return {
        "rmse_free_run": _rmse(split.y[first:], y_free),
        "seconds": time.perf_counter() - began,
        "model": f"lags {lag}/{lag}, degree {degree}, {len(model.final_model)} terms",
    }


def run_lenn(split: Split, breaks: tuple[int, ...] = ()) -> dict:
    began = time.perf_counter()
    result = fit(Data(split.u, split.y, split.name, breaks=list(breaks)), split.test_from)
    m = result.model
    refined = result.choices["refinement"].get("iterations", 0)
    return {
        "rmse_free_run": result.rmse_free_run,
        "seconds": time.perf_counter() - began,
        "model": f"{m['family']} degree {m['expansion']['degree']}, lags {m['structure']['y_lags']}, "
        f"{m['n_terms']} terms" + (f", refined {refined}x" if refined else ""),
        "clipped": result.free_run["clipped_inputs"],
        "own_record": bool(result.free_run["test_record_of_its_own"]),
    }


ARX_LAGS = (1, 2, 3, 4, 6, 8, 10)


def _arx(lag: int, u: np.ndarray, y: np.ndarray, scaling) -> TermModel:
    """Least-squares ARX(lag, lag) with a bias, as a term model (its compiled free run)."""
    rows = np.zeros((2 * lag + 1, 2 * lag), dtype=np.int64)
    rows[1:] = np.eye(2 * lag, dtype=np.int64)
    model = TermModel(Layout.of(lag, scaling), rows)
    features, targets = model.regression(siso_view(u, y))
    model.weights = np.linalg.lstsq(features, targets, rcond=None)[0]
    return model


def run_arx(split: Split, own: bool = False) -> dict:
    """A linear ARX, its lags chosen by free-run RMSE on the last 20 % of the build samples, refitted on all."""
    began = time.perf_counter()
    start = split.test_from - 1
    u, y = split.u[:start], split.y[:start]
    scaling = Scaling.from_training(u, y, margin=10.0)  # wide: a linear model needs no clipping
    validation = tail_start(start)
    tried = []
    for lag in ARX_LAGS:
        if 40 * lag > validation:
            continue
        y_sim, _, diverged_at = _arx(lag, u[:validation], y[:validation], scaling).free_run(siso_view(u, y), validation)
        tried.append((_rmse(y[validation:], y_sim) if diverged_at < 0 else math.inf, lag))
    score, lag = min(tried)
    model = _arx(lag, u, y, scaling)
    first = seeded_from(start, lag, own)
    y_free, _, diverged_at = model.free_run(siso_view(split.u, split.y), first)
    return {
        "rmse_free_run": _rmse(split.y[first:], y_free) if diverged_at < 0 else math.nan,
        "seconds": time.perf_counter() - began,
        "model": f"ARX lags {lag}/{lag}" + ("" if math.isfinite(score) else " (every lag diverged on the tail)"),
    }


MIMO_FROLS_GRID = ((1, 1), (2, 1), (3, 1), (1, 2))  # (lag, degree): dictionaries of <= 36 terms with 6 inputs
MIMO_ARX_LAGS = (1, 2, 3, 4, 6, 8)


@dataclass
class MimoSplit:
    name: str
    u: np.ndarray  # (N, n_u)
    y: np.ndarray  # (N, n_y)
    test_from: int
    note: str
    y_names: tuple[str, ...]


def mimo_splits() -> list[MimoSplit]:
    """The several-channel shared sets (README of ../shared/data)."""
    table = np.genfromtxt(DATA / "industrial_robot.csv", delimiter=",", names=True)
    u = np.stack([np.asarray(table[f"u{i}"], float) for i in range(1, 7)], axis=1)
    y = np.stack([np.asarray(table[f"y{i}"], float) for i in range(1, 7)], axis=1)
    names = tuple(f"y{i}" for i in range(1, 7))
    return [MimoSplit("industrial_robot", u, y, 39_931, "README split (build = train + validation)", names)]


def _rmse_columns(y: np.ndarray, y_hat: np.ndarray) -> list[float]:
    return [_rmse(y[:, j], y_hat[:, j]) for j in range(y.shape[1])]


def run_lenn_mimo(split: MimoSplit) -> dict:
    """``lenn-ros fit`` with several --u/--y, and ``lenn-ros fit`` once per output from its own input (one SISO
    model per output, where there are as many inputs as outputs), each timed."""
    from lenn_ros.fit.data import Data

    began = time.perf_counter()
    u_names = tuple(f"u{i + 1}" for i in range(split.u.shape[1]))
    result = fit(Data(split.u, split.y, split.name, u_names=u_names, y_names=split.y_names), split.test_from)
    seconds = time.perf_counter() - began
    model = result.model
    lags = [part.model["structure"]["y_lags"] for part in result.per_output]
    families = [part.model["family"] for part in result.per_output]
    siso, siso_models, siso_seconds = [], [], 0.0
    # each SISO fit judges the split from its own channel pair alone; compared with the MIMO fit, it is
    # seeded where the MIMO fit was (a break at the test start), so both score the same kind of run
    own = (split.test_from - 1,) if result.free_run["test_record_of_its_own"] else ()
    if split.u.shape[1] == split.y.shape[1]:
        for j in range(split.y.shape[1]):
            part = run_lenn(Split(f"{split.name} {split.y_names[j]}", split.u[:, j], split.y[:, j], split.test_from,
                                  split.note), own)  # fmt: skip
            siso.append(part["rmse_free_run"])
            siso_models.append(part["model"])
            siso_seconds += part["seconds"]
    reads = "reads the other outputs" if model.get("coupling", {}).get("reads_other_outputs") else "own past only"
    return {
        "rmse_free_run": [o.rmse_free_run for o in result.per_output],
        "siso_rmse_free_run": siso,
        "seconds": seconds,
        "siso_seconds": siso_seconds,
        "model": f"{reads}; family/lags per output: "
        + ", ".join(f"{f} {lag}" for f, lag in zip(families, lags, strict=True)),
        "siso_model": "; ".join(siso_models) or "-",
        "own_record": bool(own),
    }


def _frols_miso(lag: int, degree: int, u: np.ndarray, y: np.ndarray):
    from sysidentpy.basis_function import Polynomial
    from sysidentpy.model_structure_selection import FROLS
    from sysidentpy.parameter_estimation import LeastSquares

    dictionary = math.comb(lag * (1 + u.shape[1]) + degree, degree)
    model = FROLS(
        order_selection=True,
        n_info_values=min(30, dictionary - 1),
        ylag=lag,
        xlag=[list(range(1, lag + 1))] * u.shape[1],
        info_criteria="aic",
        estimator=LeastSquares(),
        basis_function=Polynomial(degree=degree),
    )
    model.fit(X=u, y=y[:, None])
    return model


def _frols_miso_free_run(model, u: np.ndarray, y: np.ndarray, start: int) -> np.ndarray:
    lag = model.max_lag
    with np.errstate(all="ignore"):
        y_hat = model.predict(X=u[start - lag :], y=y[start - lag :, None])
    return np.asarray(y_hat, float).ravel()[lag:]


def run_frols_mimo(split: MimoSplit, own: bool = False) -> dict:
    """FROLS per output (MISO: the six inputs and the output's own lags), each structure chosen by its free run."""
    began = time.perf_counter()
    start = split.test_from - 1
    validation = tail_start(start)
    scores, models = [], []
    for j in range(split.y.shape[1]):
        u, y = split.u[:start], split.y[:start, j]
        tried = []
        for lag, degree in MIMO_FROLS_GRID:
            try:
                model = _frols_miso(lag, degree, u[:validation], y[:validation])
                score = _rmse(y[validation:], _frols_miso_free_run(model, u, y, validation))
            except (ValueError, np.linalg.LinAlgError, FloatingPointError):
                score = math.nan
            tried.append((score if math.isfinite(score) else math.inf, lag, degree))
        _, lag, degree = min(tried)
        model = _frols_miso(lag, degree, u, y)
        first = seeded_from(start, model.max_lag, own)
        y_free = _frols_miso_free_run(model, split.u, split.y[:, j], first)
        scores.append(_rmse(split.y[first:, j], y_free))
        models.append(f"{lag}/{degree}/{len(model.final_model)}")
    return {"rmse_free_run": scores, "seconds": time.perf_counter() - began,
            "model": "lag/degree/terms per output: " + ", ".join(models)}  # fmt: skip


def _mimo_arx(lag: int, u: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Least-squares weights of every output on y[k-1..k-lag], u[k-1..k-lag] of every channel and a bias."""
    past = [y[lag - i - 1 : len(y) - i - 1] for i in range(lag)] + [u[lag - i - 1 : len(u) - i - 1] for i in range(lag)]
    rows = np.hstack([*past, np.ones((len(y) - lag, 1))])
    return np.linalg.lstsq(rows, y[lag:], rcond=None)[0]


def _mimo_arx_free_run(weights: np.ndarray, lag: int, u: np.ndarray, y: np.ndarray, start: int) -> np.ndarray:
    """Every output fed the model's own outputs from ``start`` on; nan from a divergence on."""
    y_sim = np.array(y, float)
    for k in range(start, len(y)):
        row = np.concatenate([*(y_sim[k - i - 1] for i in range(lag)), *(u[k - i - 1] for i in range(lag)), [1.0]])
        y_sim[k] = row @ weights
        if not np.all(np.abs(y_sim[k]) < 1e9):
            y_sim[k:] = math.nan
            break
    return y_sim[start:]


def run_arx_mimo(split: MimoSplit, own: bool = False) -> dict:
    """A full MIMO ARX, its lags chosen by the joint free run (mean NMSE) on the build tail, refitted on all."""
    began = time.perf_counter()
    start = split.test_from - 1
    u, y = split.u[:start], split.y[:start]
    validation = tail_start(start)
    variance = np.var(y[validation:], axis=0)
    tried = []
    for lag in MIMO_ARX_LAGS:
        y_sim = _mimo_arx_free_run(_mimo_arx(lag, u[:validation], y[:validation]), lag, u, y, validation)
        error = np.mean((y_sim - y[validation:]) ** 2, axis=0) / variance
        tried.append((float(np.mean(error)) if np.all(np.isfinite(error)) else math.inf, lag))
    _, lag = min(tried)
    first = seeded_from(start, lag, own)
    y_free = _mimo_arx_free_run(_mimo_arx(lag, u, y), lag, split.u, split.y, first)
    return {"rmse_free_run": _rmse_columns(split.y[first:], y_free), "seconds": time.perf_counter() - began,
            "model": f"MIMO ARX lags {lag}/{lag}"}  # fmt: skip


def mimo_table(rows: list[dict]) -> str:
    """One row per output: the MIMO fit, fit's own one-SISO-per-output model, FROLS per output, MIMO ARX."""
    lines = [
        "| data: output | lenn-ros fit MIMO | lenn-ros fit, one SISO per output | FROLS per output | MIMO ARX "
        "| test-mean predictor |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        lenn, frols, arx = row["lenn"], row["frols"], row["arx"]
        for j, name in enumerate(row["outputs"]):
            mean = row["test_mean_rmse"][j]
            siso = lenn["siso_rmse_free_run"][j] if lenn["siso_rmse_free_run"] else math.nan
            lines.append(
                f"| {row['data']}: {name} | {_vs_mean(lenn['rmse_free_run'][j], mean)} | {_vs_mean(siso, mean)} "
                f"| {_vs_mean(frols['rmse_free_run'][j], mean)} | {_vs_mean(arx['rmse_free_run'][j], mean)} "
                f"| {_fmt(mean)} |"
            )
        lines.append(
            f"| {row['data']}: time (s), model | {lenn['seconds']:.1f}, {lenn['model']} | "
            f"{lenn['siso_seconds']:.1f}, {lenn['siso_model']} | {frols['seconds']:.1f}, {frols['model']} "
            f"| {arx['seconds']:.1f}, {arx['model']} | |"
        )
    return "\n".join(lines)


def free_run_speed(steps: int = 1_000_000) -> dict:
    """Free-run steps per second of the paper's Example-1 LeNN: compiled kernel vs the per-sample loop."""
    from lenn_ros.core.structure import Identifier
    from lenn_ros.paper.examples import get_example

    example = get_example(1)
    identifier = Identifier(example.structure, example.make_network("lenn", 0))
    u = np.random.default_rng(0).uniform(-1, 1, steps + 10)
    identifier.free_run(u[:100], np.zeros(100), 10)  # compile
    began = time.perf_counter()
    identifier.free_run(u, np.zeros(len(u)), 10)
    compiled = steps / (time.perf_counter() - began)
    window, y_model, loop_steps = example.structure.warm_up, np.zeros(2010), 2000
    began = time.perf_counter()
    for k in range(9, 9 + loop_steps):
        x, linear = example.structure.regressors(u[k - window + 1 : k + 1], y_model[k - window + 1 : k + 1])
        y_model[k + 1] = linear[-1] + identifier.model.predict(np.clip(x[-1:], -1.0, 1.0))[0]
    loop = loop_steps / (time.perf_counter() - began)
    return {"compiled_steps_per_s": compiled, "python_loop_steps_per_s": loop, "ratio": compiled / loop}


def _fmt(value: float) -> str:
    return "diverged" if not math.isfinite(value) else f"{value:.4g}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the small data sets only")
    parser.add_argument("--json", action="store_true")
    parser.add_argument("--speed-only", action="store_true", help="only the free-run speed")
    parser.add_argument("--mimo-only", action="store_true", help="only the several-channel sets")
    args = parser.parse_args(argv)
    warnings.filterwarnings("ignore")  # SysIdentPy warns per candidate (overflow in diverging simulations)
    # compile the LeNN kernels once, outside the timed runs
    rng = np.random.default_rng(0)
    u0 = rng.uniform(-1, 1, 400)
    fit(Data(u0, np.convolve(u0, [0.0, 0.5, 0.2])[:400], "warm-up"), 301)
    speed = free_run_speed()
    print(
        f"free run, Example-1 LeNN: {speed['compiled_steps_per_s'] / 1e6:.2f} M steps/s compiled, "
        f"{speed['python_loop_steps_per_s']:.0f} steps/s per-sample Python loop ({speed['ratio']:.0f}x)",
        file=sys.stderr if args.json else sys.stdout,
    )
    if args.speed_only:
        return 0
    rows: list[dict] = []
    for split in [] if args.mimo_only else splits(args.quick):
        lenn = run_lenn(split)
        frols, arx = run_frols(split, lenn["own_record"]), run_arx(split, lenn["own_record"])
        rows.append({"data": split.name, "split": split.note, "test_samples": len(split.y) - split.test_from + 1,
                     "test_mean_rmse": test_mean_rmse(split), "lenn": lenn, "frols": frols, "arx": arx,
                     "published": split.published})  # fmt: skip
        print(f"done {split.name}", file=sys.stderr, flush=True)
    mimo_rows = []
    for split in [] if args.quick else mimo_splits():
        start = split.test_from - 1
        lenn = run_lenn_mimo(split)
        frols, arx = run_frols_mimo(split, lenn["own_record"]), run_arx_mimo(split, lenn["own_record"])
        mimo_rows.append({"data": split.name, "split": split.note, "outputs": list(split.y_names),
                          "test_samples": len(split.y) - start, "test_mean_rmse": list(np.std(split.y[start:], axis=0)),
                          "lenn": lenn, "frols": frols, "arx": arx})  # fmt: skip
        print(f"done {split.name}", file=sys.stderr, flush=True)
    if args.json:
        print(json.dumps({"siso": rows, "mimo": mimo_rows}, indent=1))
        return 0
    print("\n\n".join(([table(rows)] if rows else []) + ([mimo_table(mimo_rows)] if mimo_rows else [])))
    return 0


def test_mean_rmse(split: Split) -> float:
    """RMSE of the test part's own mean as the prediction: the bar below which a model is worth anything."""
    return float(np.std(split.y[split.test_from - 1 :]))


def _vs_mean(value: float, mean: float) -> str:
    """The RMSE, marked when it is no better than the test-mean predictor (or diverged)."""
    return _fmt(value) + (" (worse than the mean)" if not value < mean else "")


def table(rows: list[dict]) -> str:
    """The RESULTS table: the three tools' free-run RMSE and times, the test-mean predictor, the published best."""
    lines = [
        "| data (test samples) | lenn-ros fit: free-run RMSE | SysIdentPy FROLS: free-run RMSE | linear ARX: free-run "
        "RMSE | test-mean predictor: RMSE | best published | lenn-ros fit: time (s) | FROLS: time (s) | ARX: time (s) "
        "| lenn-ros model | FROLS model | ARX model |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    missing = {"rmse_free_run": math.nan, "seconds": math.nan, "model": "-"}
    for row in rows:
        lenn, frols, mean = row["lenn"], row["frols"], row["test_mean_rmse"]
        arx = row.get("arx", missing)
        lines.append(
            f"| {row['data']} ({row['test_samples']}) | {_vs_mean(lenn['rmse_free_run'], mean)} "
            f"| {_vs_mean(frols['rmse_free_run'], mean)} | {_vs_mean(arx['rmse_free_run'], mean)} | {_fmt(mean)} "
            f"| {row.get('published') or '-'} | {lenn['seconds']:.1f} | {frols['seconds']:.1f} | {arx['seconds']:.1f} "
            f"| {lenn['model']} | {frols['model']} | {arx['model']} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())

"""``import-csv`` and ``fit`` with several --u / --y columns, on data simulated from the coupled 2x2 plant.

``fit`` is one procedure for any number of channels: these tests hold it to what a model of
several outputs must do beyond one model per output (read the other outputs where the plant
couples them, simulate them together) and to the node running it from the files it writes.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from lenn_ros.bag import BagError, import_csv, read_run
from lenn_ros.config import resolve
from lenn_ros.core.mimo import MimoIdentifier
from lenn_ros.core.networks import ModelFileError
from lenn_ros.fit.data import Data
from lenn_ros.fit.export import write_outputs
from lenn_ros.fit.load import load_data
from lenn_ros.fit.procedure import fit
from lenn_ros.fit.regression import RIDGE
from lenn_ros.paper.evaluation import simulate_mimo
from lenn_ros.paper.plants import narendra_mimo_plant
from lenn_ros.service.building import build_identifier
from lenn_ros.service.params import read_params_file

REPO = Path(__file__).resolve().parents[1]
TRAIN, TEST = 2000, 400


def simulated_csv(path: Path, seed: int = 0) -> Path:
    """Training (random inputs, -30 dB input noise) then test (sinusoids) of narendra2x2, with a time column."""
    series = simulate_mimo(narendra_mimo_plant(), -30.0, seed=seed, train_samples=TRAIN, test_samples=TEST)
    k = np.arange(len(series.y)) * 0.01
    np.savetxt(path, np.c_[k, series.u, series.y], delimiter=",", header="t,u1,u2,y1,y2", comments="")
    return path


def lenn_ros(*arguments: str) -> subprocess.CompletedProcess[str]:
    command = [sys.executable, "-m", "lenn_ros.cli", *arguments]
    return subprocess.run(command, capture_output=True, text=True, timeout=300, cwd=REPO, check=False)


def identifier_from_params(values: dict) -> MimoIdentifier:
    """What the identifier node builds from the params file's values (``_build_model``)."""
    resolved, network = resolve(values)
    identifier = build_identifier({**values, **resolved}, network)
    assert isinstance(identifier, MimoIdentifier)
    return identifier


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """One fit of a simulated log, shared: the fit is the slow part (a few seconds)."""
    directory = tmp_path_factory.mktemp("mimo")
    data = load_data(simulated_csv(directory / "log.csv"), ["u1", "u2"], ["y1", "y2"])
    result = fit(data, TRAIN + 1)
    files = write_outputs(directory / "model", result, data)
    return {"data": data, "result": result, "files": files}


def test_mimo_fit_beats_one_siso_model_per_output_on_both_outputs(fitted: dict) -> None:
    """The plant couples its outputs: the fit reads the other outputs (chosen by the outputs' free runs
    together on the blocks) and simulates each far better than one model per output from its own input."""
    report = fitted["result"]
    assert report.samples == TEST and report.outputs == ["y1", "y2"]
    assert report.warnings == [] and not report.free_run["diverged"]
    coupling = report.model["coupling"]
    assert coupling["reads_other_outputs"]
    assert coupling["nmse_blocks"]["coupled"]["mean"] < 0.5 * coupling["nmse_blocks"]["own"]["mean"]
    data = fitted["data"]
    for j, full in enumerate(report.per_output):
        siso = fit(Data(data.u[:, j], data.y[:, j], f"output {j} from input {j}"), TRAIN + 1)
        assert full.nmse_free_run_db < siso.nmse_free_run_db - 5.0, (full.nmse_free_run_db, siso.as_dict())
        assert full.nmse_db < siso.nmse_db - 5.0
        assert full.rmse_free_run < 0.5 * siso.rmse_free_run


def test_params_and_weights_rebuild_the_fitted_model(fitted: dict) -> None:
    document = yaml.safe_load(Path(fitted["files"]["params"]).read_text())
    assert list(document) == ["/**"]
    values = document["/**"]["ros__parameters"]
    assert values["u_type"] == values["y_type"] == "std_msgs/msg/Float64MultiArray"
    assert values["u_field"] == values["y_field"] == "data[*]"
    assert (values["u_names"], values["y_names"]) == (["u1", "u2"], ["y1", "y2"])
    assert values["couplings"] == "y0 y1 u0 u1; y1 y0 u0 u1"  # each output reads the other's past
    assert all(len(values[key]) == 2 for key in ("u_scales", "u_offsets", "y_scales", "y_offsets", "y_pass_through"))
    assert values["y_pass_through"] == [False, False]  # neither output integrates
    assert Path(values["weights_in"]).is_absolute() and Path(values["weights_in"]).exists()
    assert not {"separate", "known_a", "known_b"} & set(values)
    per_output = [[t.split(":", 1)[1].strip() for t in values["terms"] if t.startswith(f"y{j}:")] for j in (0, 1)]
    assert sum(map(len, per_output)) == len(values["terms"]) and all(per_output)
    assert all("1" in terms for terms in per_output)  # the bias the node's output offset comes off
    assert read_params_file(fitted["files"]["params"]) == values
    identifier = identifier_from_params(values)
    identifier.load_state(values["weights_in"])
    data, report = fitted["data"], fitted["result"]
    np.testing.assert_array_equal(identifier.free_run(data.u, data.y, TRAIN), report.y_free_test)
    np.testing.assert_array_equal(identifier.run(data.u, data.y, learn=False)[TRAIN:], report.y_hat_test)


def test_weights_of_another_shape_or_output_count_are_refused(fitted: dict, tmp_path: Path) -> None:
    values = yaml.safe_load(Path(fitted["files"]["params"]).read_text())["/**"]["ros__parameters"]
    other = identifier_from_params({**values, "y_lags": values["y_lags"] + 1})
    with pytest.raises(ModelFileError, match=r"output 0 \(y1\): weights are for a different network.*n_inputs"):
        other.load_state(values["weights_in"])
    one_output = {"y_names": ["y1"], "y_scales": [1.0], "y_offsets": [0.0], "terms": [""], "couplings": "full",
                  "y_pass_through": [False]}  # fmt: skip
    one = identifier_from_params({**values, **one_output})
    with pytest.raises(ModelFileError, match=r"weights of 2 output\(s\), this model has 1 outputs"):
        one.load_state(values["weights_in"])
    with np.load(values["weights_in"]) as archive:
        arrays = {name: archive[name] for name in archive.files}
    arrays["y1_weights_"] = arrays["y1_weights_"][:-1]
    np.savez(tmp_path / "cut.npz", **arrays)
    whole = identifier_from_params(values)
    before = [model.weights_.copy() for model in whole.models]
    with pytest.raises(ModelFileError, match=r"output 1 \(y2\): array 'weights_' missing or of shape"):
        whole.load_state(tmp_path / "cut.npz")
    for weights, model in zip(before, whole.models, strict=True):  # all or nothing: output 0 untouched
        np.testing.assert_array_equal(weights, model.weights_)


def test_import_csv_with_several_columns_writes_labelled_vector_samples(tmp_path: Path) -> None:
    csv = tmp_path / "log.csv"
    csv.write_text("t,a,b,c,d\n" + "".join(f"{k / 10},{k},{-k},{2 * k},{k / 4}\n" for k in range(12)))
    bag = import_csv(csv, ["a", "b"], ["d", "c"], 0.1, tmp_path / "bag", test_from=9)
    with (bag / "bag.mcap").open("rb") as f:  # an independent reader: mcap + mcap_ros2
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        decoded = [(c.topic, s.name, m, d) for s, c, m, d in reader.iter_decoded_messages(log_time_order=True)]
    u = [d for topic, *_, d in decoded if topic == "/u"]
    y = [d for topic, *_, d in decoded if topic == "/y_p"]
    assert {name for topic, name, *_ in decoded if topic in ("/u", "/y_p")} == {"std_msgs/msg/Float64MultiArray"}
    assert [list(d.data) for d in u] == [[float(k), float(-k)] for k in range(12)]
    assert [list(d.data) for d in y] == [[k / 4, 2.0 * k] for k in range(12)]
    assert [(dim.label, dim.size, dim.stride) for dim in u[0].layout.dim] == [("a,b", 2, 2)]
    assert [(dim.label, dim.size, dim.stride) for dim in y[5].layout.dim] == [("d,c", 2, 2)]
    assert [m.log_time for topic, _n, m, _d in decoded if topic == "/u"][:2] == [0, 100_000_000]
    assert [d.data for topic, *_, d in decoded if topic == "/test_start"] == [9]
    siso = read_run(import_csv(csv, ["a"], ["c"], 0.1, tmp_path / "siso"))  # one of each: the Float64 bag as before
    assert siso.u.tolist() == [float(k) for k in range(12)] and siso.topics["u"] == "/u"


@pytest.mark.parametrize(
    ("text", "u", "y", "pattern"),
    [
        ("a,b,c\n1,2,3\n", ["a", "x"], ["c"], r"no column 'x' \(columns: a, b, c\)"),
        ("a,b,c\n1,2,3\n4,5,z\n", ["a", "b"], ["c"], r"line 3, column 'c': 'z' is not a number"),
        ("a,b,c\n1,2,3\n", ["a", "a"], ["c"], r"column 'a' given twice as --u"),
    ],
)
def test_import_csv_several_columns_errors(tmp_path: Path, text: str, u: list, y: list, pattern: str) -> None:
    csv = tmp_path / "log.csv"
    csv.write_text(text)
    with pytest.raises(BagError, match=pattern):
        import_csv(csv, u, y, 0.1, tmp_path / "bag")
    assert not (tmp_path / "bag").exists()


def test_cli_import_csv_then_fit_the_vector_bag(tmp_path: Path) -> None:
    csv = simulated_csv(tmp_path / "log.csv", seed=1)
    bag, model = tmp_path / "bag", tmp_path / "model"
    done = lenn_ros("import-csv", str(csv), "--u", "u1", "--u", "u2", "--y", "y1", "--y", "y2",
                    "--dt", "0.01", "-o", str(bag), "--test-from", str(TRAIN + 1))  # fmt: skip
    assert done.returncode == 0, done.stderr
    done = lenn_ros("fit", str(bag), "--json", "-o", str(model), "--plot", str(tmp_path / "fit.png"))
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert report["test_from"] == TRAIN + 1 and report["inputs"] == ["u1", "u2"]  # test start and names from the bag
    assert report["model"]["coupling"]["reads_other_outputs"]
    assert all(output["nmse_free_run_db"] < -20.0 for output in report["per_output"])
    assert (model / "weights.npz").exists() and (tmp_path / "fit.png").stat().st_size > 0
    # evaluate the same bag from the written params (which start from the fitted weights): per channel
    done = lenn_ros("evaluate", str(bag), "--params", str(model / "params.yaml"), "--json")
    assert done.returncode == 0, done.stderr
    scores = json.loads(done.stdout)["channels"]
    assert set(scores) == {"y1", "y2"} and all(channel["nmse_free_run_db"] < -15 for channel in scores.values())
    plot = tmp_path / "evaluate.png"
    done = lenn_ros("evaluate", str(bag), "--params", str(model / "params.yaml"), "--plot", str(plot))
    assert done.returncode == 0 and "NMSE one-step" in done.stdout and plot.stat().st_size > 10_000, done.stderr
    text = lenn_ros("fit", str(csv), "--u", "u1", "--u", "u2", "--y", "y1", "--y", "speed", "--test-from", "2001")
    assert text.returncode == 2 and text.stderr.count("\n") == 1
    assert "no column 'speed' (columns: t, u1, u2, y1, y2)" in text.stderr


def test_load_model_runs_the_mimo_fit_as_fit_reported(fitted: dict) -> None:
    """lenn_ros.load_model on a several-channel fit: simulate and the stepper give fit's free run."""
    import lenn_ros

    model = lenn_ros.load_model(Path(fitted["files"]["params"]).parent)
    assert (model.n_u, model.n_y) == (2, 2)
    data, w = fitted["data"], model.history
    before = {"y_initial": data.y[TRAIN - w : TRAIN], "u_initial": data.u[TRAIN - w : TRAIN]}
    free = model.simulate(data.u[TRAIN:], **before)
    np.testing.assert_array_equal(free, fitted["result"].y_free_test)
    stepper = model.stepper(**before)
    np.testing.assert_array_equal(np.array([stepper.step(row) for row in data.u[TRAIN : TRAIN + 50]]), free[:50])


def test_a_gap_in_a_vector_record_is_a_break_of_the_mimo_fit() -> None:
    """Samples missing from a vector record (a lost or refused sample of a robot bag) are never joined.

    The two runs either side of each gap come from different plant states, as after a
    stall. Least squares with the gap equals least squares on each run's own regressors
    stacked (computed run by run here); the test part's free run restarts from the
    measured outputs after its gap, its warm-up unscored, and then equals a free run
    started afresh on that run.
    """
    from lenn_ros.paper.signals import noise_std

    rng = np.random.default_rng(3)
    pieces, cuts = [], (700, 1800, 2000)
    plant = narendra_mimo_plant()
    for length in np.diff((0, *cuts)):
        plant.y_past = rng.uniform(-1.0, 1.0, 2)  # another state after each gap
        u = 0.7 * rng.uniform(-1.0, 1.0, (length, 2))
        pieces.append((u, plant.run(u + rng.normal(0.0, noise_std(-40.0), (length, 2)))[:-1]))
    u, y = np.concatenate([p[0] for p in pieces]), np.concatenate([p[1] for p in pieces])
    index = np.arange(1, len(y) + 1) + np.where(np.arange(len(y)) >= cuts[0], 50, 0)
    index += np.where(np.arange(len(y)) >= cuts[1], 30, 0)
    breaks = [int(b) for b in np.flatnonzero(np.diff(index) != 1) + 1]
    assert breaks == [cuts[0], cuts[1]]
    data = Data(u, y, "two gaps", breaks=breaks, index=index, u_names=("u1", "u2"), y_names=("y1", "y2"))

    train = 1500
    result = fit(data, test_from=int(index[train]), refine=False)  # by number: the first test sample's index
    assert result.train_samples == train and result.numbers == {"train": [1, int(index[train - 1])],
                                                                "first_test": int(index[train])}  # fmt: skip
    identifier = result.identifier
    for output in result.fits:  # each output's selected model over its view (columns of [y, u])
        model, view = output.model, np.column_stack([y, u])[:, output.columns]
        # least squares with the gap = least squares on each run's own regressors stacked
        systems = [model.regression(view[a:b]) for a, b in ((0, cuts[0]), (cuts[0], train))]
        features = np.vstack([f for f, _ in systems])
        targets = np.concatenate([t for _, t in systems])
        gram = features.T @ features  # the selection's solve: normal equations with a RIDGE relative to the trace
        gram += RIDGE * np.trace(gram) / len(gram) * np.eye(len(gram))
        expected = np.linalg.solve(gram, features.T @ targets)
        np.testing.assert_allclose(model.weights, expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())
        joined = model.regression(view[:train])
        assert not np.allclose(np.linalg.lstsq(*joined, rcond=None)[0], expected, rtol=1e-3)  # joining would differ
    assert result.per_output[0].choices["gaps"] == 1
    warm = identifier.structure.warm_up
    y_free, gap = result.y_free_test, cuts[1] - train
    assert np.isfinite(y_free[:gap]).all() and np.isnan(y_free[gap : gap + warm]).all()
    np.testing.assert_array_equal(y_free[gap + warm :], identifier.free_run(u[cuts[1] :], y[cuts[1] :], warm))
    assert np.isnan(result.y_hat_test[gap : gap + warm]).all()  # one step ahead: history restarts too
    assert np.isfinite(result.y_hat_test[gap + warm :]).all()
    assert all(output.nmse_free_run_db < -27.0 for output in result.per_output)


def test_an_integrating_output_is_passed_through_and_simulates_beyond_its_training_range(tmp_path: Path) -> None:
    """A wheel beside a stable joint: its angle integrates the command, and the test part drives it one way,
    to four times its training range. Its network reads the angle widened (as a SISO model's) and the node
    passes y(k) through (``y_pass_through``), so the free run follows it there, from the params file too."""
    rng = np.random.default_rng(0)
    n, start = 3000, 2000
    u = np.column_stack([np.repeat(rng.uniform(-1, 1, n // 20 + 1), 20)[:n] for _ in range(2)])
    u[start:, 0] = np.abs(u[start:, 0]) * 0.8 + 0.2
    y = np.zeros((n, 2))
    for k in range(n - 1):
        y[k + 1, 0] = y[k, 0] + 0.05 * u[k, 0]
        y[k + 1, 1] = 0.8 * y[k, 1] + 0.3 * np.tanh(2 * u[k, 1])
    y += rng.normal(0, 1e-4, y.shape)
    assert y[start:, 0].max() > 4 * y[:start, 0].max()  # far beyond what the network was trained on
    data = Data(u, y, "wheel", u_names=("u0", "u1"), y_names=("y0", "y1"))
    result = fit(data, start + 1)
    wheel, joint = result.per_output
    assert wheel.model["family"] == "increment"
    # measured: -95.8 dB (without the pass-through, +3.3 dB: the angle read clipped at the range's edge)
    assert wheel.nmse_free_run_db < -80.0 and joint.nmse_free_run_db < -60.0, (wheel, joint)
    files = write_outputs(tmp_path / "model", result, data)
    values = yaml.safe_load(Path(files["params"]).read_text())["/**"]["ros__parameters"]
    assert values["y_pass_through"] == [True, False]
    identifier = identifier_from_params(values)
    identifier.load_state(values["weights_in"])
    np.testing.assert_array_equal(identifier.free_run(data.u, data.y, start), result.y_free_test)


def test_each_output_reads_an_input_from_its_dead_time(tmp_path: Path) -> None:
    """Two outputs: p = a first-order lag of tanh(2 a) behind 6 samples, q = a lag of b and of p. Each output's
    view finds a's dead time (6 for p; 7 for q, which sees a through p one sample later), the report names
    it, and the params file rebuilds the several-output model's free run exactly. Without the dead times:
    p -29.9 and q -34.9 dB; with them -44.3 and -38.5 dB (measured)."""
    rng = np.random.default_rng(1)
    n = 5000
    u = np.column_stack([np.repeat(rng.uniform(-1, 1, n // 10), 10), np.repeat(rng.uniform(-1, 1, n // 20), 20)])
    y = np.zeros((n, 2))
    for k in range(8, n - 1):
        y[k + 1, 0] = 0.8 * y[k, 0] + 0.3 * np.tanh(2 * u[k - 6, 0])
        y[k + 1, 1] = 0.7 * y[k, 1] + 0.2 * u[k, 1] + 0.1 * y[k, 0]
    y += 0.005 * rng.standard_normal(y.shape)
    data = Data(u, y, "dead time", u_names=("a", "b"), y_names=("p", "q"))
    report = fit(data, 4001)
    assert [part.choices["dead_time"] for part in report.per_output] == [{"u0": 6}, {"u0": 7}]
    assert report.per_output[0].nmse_free_run_db < -43.0 and report.per_output[1].nmse_free_run_db < -37.5
    values = read_params_file(write_outputs(tmp_path / "model", report, data)["params"])
    identifier = identifier_from_params(values)
    identifier.load_state(values["weights_in"])
    np.testing.assert_array_equal(identifier.free_run(u, y, 4000), report.y_free_test)

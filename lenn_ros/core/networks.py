"""The learning models: functional-link networks (LeNN and relatives) and the MLP.

Both follow scikit-learn's online-estimator convention, which is what a Python user
expects of a learning model: hyper-parameters are stored unchanged by ``__init__``,
learned state carries a trailing underscore and appears on the first
``partial_fit``, ``predict`` never learns. ``update`` is the one call the identifier
uses: it returns the a-priori predictions (made before each sample's update), from
which the online error e(k) follows without a second forward pass.

A model expects its inputs in [-1, 1] (the Legendre recursion is only bounded
there); scaling is the model structure's job (``structure.ModelStructure``), and what
arrives outside the interval is handled by ``out_of_range``: ``"clip"`` (counted in
``n_clipped_``) or ``"error"``. It is never extrapolated silently.
"""

from __future__ import annotations

import json
import os
import tempfile
from functools import lru_cache
from pathlib import Path
from typing import Any, ClassVar

import numpy as np

from lenn_ros.core import jit, learning_rules
from lenn_ros.core.expansions import (
    BASES,
    COMPILED_BASES,
    checked_factors,
    expand,
    feature_count,
    full_exponents,
    term_features,
)

SOLVERS = ("sgd", "nlms", "rls")
OUTPUTS = ("tanh", "linear")
FORMAT_VERSION = 1


class DivergenceError(FloatingPointError):
    """An update would have made a weight non-finite; the model was left as it was."""

    def __init__(self, sample_index: int, predictions: np.ndarray | None = None) -> None:
        super().__init__(f"update of sample {sample_index} would make the weights non-finite")
        self.sample_index = sample_index
        #: a-priori outputs of the samples before ``sample_index`` (and of that one)
        self.predictions = predictions


class ModelFileError(ValueError):
    """A weights file is unreadable or belongs to a differently configured model."""


class OnlineRegressor:
    """Shared plumbing: parameter handling, input checks, atomic save and load."""

    _state_names: ClassVar[tuple[str, ...]] = ()
    _kind: ClassVar[str] = ""

    def __init__(self, **params: Any) -> None:
        for name, value in params.items():
            setattr(self, name, value)
        self._param_names = tuple(params)

    def get_params(self) -> dict[str, Any]:
        """Hyper-parameters as given to ``__init__`` (JSON-friendly)."""
        return {name: _jsonable(getattr(self, name)) for name in self._param_names}

    def set_params(self, **params: Any) -> OnlineRegressor:
        """Change hyper-parameters; on a fitted model only those that keep its learned state valid.

        Structural parameters (order, n_inputs, solver, hidden...) fix the shape and meaning
        of the learned arrays: changed under a fitted model, the compiled kernels would
        index past them. They are refused there (make a new model instead). The change is
        all or nothing: a refused or invalid value leaves every parameter as it was.
        """
        unknown = sorted(name for name in params if name not in self._param_names)
        if unknown:
            raise ValueError(f"{type(self).__name__} has no parameter {', '.join(map(repr, unknown))}")
        if self.is_initialised:
            structural = sorted(
                name
                for name, value in params.items()
                if name in self._structural_params and _jsonable(value) != _jsonable(getattr(self, name))
            )
            if structural:
                raise ValueError(
                    f"cannot change {', '.join(structural)} of a fitted {type(self).__name__}: it changes the "
                    "learned state's shape or meaning; build a new model with the new value"
                )
        before = {name: getattr(self, name) for name in params}
        for name, value in params.items():
            setattr(self, name, value)
        try:
            self._validate()
        except ValueError:
            for name, value in before.items():
                setattr(self, name, value)
            raise
        return self

    def _validate(self) -> None:
        """Checks every model shares; subclasses add their own and call this."""
        if self.output not in OUTPUTS:
            raise ValueError(f"output must be 'tanh' or 'linear', not {self.output!r}")
        if not self.alpha >= 0.0 or not 0.0 <= self.beta < 1.0:
            raise ValueError("alpha must be >= 0 and beta in [0, 1)")
        if self.out_of_range not in ("clip", "error"):
            raise ValueError("out_of_range must be 'clip' or 'error'")
        _as_branches(self.branches, self.n_inputs)

    @property
    def is_initialised(self) -> bool:
        return all(hasattr(self, name) for name in self._state_names)

    def _check_inputs(self, x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        if x.shape[1] != self.n_inputs:
            raise ValueError(f"expected {self.n_inputs} inputs per sample, got {x.shape[1]}")
        if not np.all(np.isfinite(x)):
            raise ValueError("non-finite network input")
        outside = np.abs(x) > 1.0
        if outside.any():
            if self.out_of_range == "error":
                raise ValueError(
                    f"{int(outside.sum())} network input(s) outside [-1, 1] "
                    f"(max |x| = {np.abs(x).max():.3g}); raise the scale factor"
                )
            self.n_clipped_ = getattr(self, "n_clipped_", 0) + int(outside.sum())
            x = np.clip(x, -1.0, 1.0)
        return x

    def partial_fit(self, x: np.ndarray, d: np.ndarray) -> OnlineRegressor:
        """Learn from samples in order, one update per sample (scikit-learn style)."""
        self.update(x, d, learn=True)
        return self

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Outputs for inputs ``x`` with the current weights; nothing is learnt."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        return self.update(x, np.zeros(x.shape[0]), learn=False)

    def update(self, x: np.ndarray, d: np.ndarray, learn: bool = True) -> np.ndarray:
        raise NotImplementedError

    # -- persistence ---------------------------------------------------------------
    def state(self) -> dict[str, np.ndarray]:
        """Copies of the learned arrays (weights and optimiser state)."""
        return {name: np.array(getattr(self, name), copy=True) for name in self._state_names}

    def set_state(self, state: dict[str, np.ndarray]) -> None:
        """Restore learned arrays taken by :meth:`state` (shapes must match)."""
        for name in self._state_names:
            setattr(self, name, np.array(state[name], dtype=np.float64, copy=True))
        self.n_samples_seen_ = int(state.get("n_samples_seen_", getattr(self, "n_samples_seen_", 0)))

    def save(self, path: str | os.PathLike[str], scaling: dict[str, float] | None = None) -> None:
        """Write hyper-parameters and learned state to ``path`` (npz) atomically.

        The file is written next to its destination and renamed over it, so a crash
        mid-write leaves the previous file intact: a restart never finds half a model.
        ``scaling``: the offsets and scales the caller fed the inputs with (the weights
        mean nothing without them; a run that learnt them restarts from the file alone).
        """
        if not self.is_initialised:
            self._initialise()
        header = {
            "format": FORMAT_VERSION,
            "kind": self._kind,
            "params": self.get_params(),
            "n_samples_seen": int(getattr(self, "n_samples_seen_", 0)),
            **({"scaling": {k: float(v) for k, v in scaling.items()}} if scaling else {}),
        }
        write_weights_file(path, header, self.state())

    @staticmethod
    def load(path: str | os.PathLike[str]) -> OnlineRegressor:
        """Rebuild the model saved at ``path`` (any kind)."""
        header, arrays = _read_model_file(path)
        cls = {"functional_link": FunctionalLinkNetwork, "mlp": MLP}[header["kind"]]
        model = cls(**header["params"])
        model._install(arrays, header, path)
        return model

    def load_state(self, path: str | os.PathLike[str]) -> None:
        """Load learned state into this model; refuse a file of another configuration."""
        header, arrays = _read_model_file(path)
        mine = self.get_params()
        structural = {k: v for k, v in mine.items() if k in self._structural_params}
        theirs = {k: header["params"].get(k) for k in structural}
        if header["kind"] != self._kind or theirs != structural:
            differing = sorted(k for k in structural if theirs.get(k) != structural[k])
            raise ModelFileError(
                f"{path}: weights are for a different network "
                f"({header['kind']}, differs in {', '.join(differing) or 'kind'}); "
                "configure the same network or start without the file"
            )
        self._install(arrays, header, path)

    _structural_params: ClassVar[tuple[str, ...]] = ()

    def _install(self, arrays: dict[str, np.ndarray], header: dict, path: Any) -> None:
        self._initialise()
        for name in self._state_names:
            if name not in arrays or arrays[name].shape != getattr(self, name).shape:
                raise ModelFileError(f"{path}: array {name!r} missing or of the wrong shape")
        self.set_state(arrays)
        self.n_samples_seen_ = int(header.get("n_samples_seen", 0))

    def _initialise(self) -> None:
        raise NotImplementedError


def write_weights_file(path: str | os.PathLike[str], header: dict, arrays: dict[str, np.ndarray]) -> None:
    """A JSON ``header`` and named arrays as one .npz, written next to ``path`` and renamed over it.

    Shared by one model's :meth:`OnlineRegressor.save` and a MIMO model's ``save_state``,
    so both keep the guarantee that a crash mid-write leaves the previous file intact.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(handle, "wb") as stream:
            np.savez(stream, header=np.array(json.dumps(header)), **arrays)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise


def read_weights_file(path: str | os.PathLike[str]) -> tuple[dict, dict[str, np.ndarray]]:
    """(header, arrays) of a file :func:`write_weights_file` wrote; any unreadable file is a ModelFileError."""
    try:
        with np.load(path, allow_pickle=False) as archive:
            header = json.loads(str(archive["header"]))
            arrays = {name: archive[name] for name in archive.files if name != "header"}
    except FileNotFoundError:
        raise ModelFileError(f"{path}: no such weights file") from None
    except (OSError, ValueError, KeyError) as error:
        raise ModelFileError(f"{path}: not a lenn_ros weights file ({error})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT_VERSION:
        raise ModelFileError(f"{path}: unsupported weights file format")
    return header, arrays


def _read_model_file(path: str | os.PathLike[str]) -> tuple[dict, dict[str, np.ndarray]]:
    header, arrays = read_weights_file(path)
    if header.get("kind") == "mimo":
        raise ModelFileError(
            f"{path}: weights of a model with {len(header.get('outputs', []))} outputs (MIMO); "
            "this one has one output: configure y_names/u_names as the file's model or start without it"
        )
    if header.get("kind") not in ("functional_link", "mlp"):
        raise ModelFileError(f"{path}: unsupported weights file format")
    return header, arrays


def _jsonable(value: Any) -> Any:
    if isinstance(value, tuple):
        return [_jsonable(v) for v in value]
    if isinstance(value, list):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _as_branches(branches: Any, n_inputs: int) -> list[list[int]]:
    if branches is None:
        return [list(range(n_inputs))]
    result = [[int(i) for i in branch] for branch in branches]
    flat = sorted(i for branch in result for i in branch)
    if flat != list(range(n_inputs)):
        raise ValueError(f"branches {branches} must partition the inputs 0..{n_inputs - 1}")
    return result


class FunctionalLinkNetwork(OnlineRegressor):
    """Single-layer functional-link network: y = sum_b out(w_b . phi(x_b)).

    With ``basis="legendre"`` and the defaults this is the paper's LeNN (Fig. 3,
    eqs. 4-10). ``branches`` splits the inputs among output nodes whose outputs are
    summed (Ex. 3's N1[y(k)] + N2[u(k)]); each branch has its own bias and expansion.
    ``solver`` picks the learning rule: the paper's ``"sgd"`` (gradient with
    momentum; tanh or linear output), or, for a linear output only, ``"nlms"`` and
    ``"rls"`` (recursive least squares with forgetting factor and bounded trace).

    ``max_trace`` bounds trace(P) under forgetting; None (the default) bounds it at the
    prior's, ``n_weights * initial_covariance``: a plant at rest for minutes then leaves the
    model no less certain than before it saw any data, instead of winding P up by
    orders of magnitude (issue 18: 60 times the prior's with the old fixed 1e6, 17 weights).
    """

    _state_names = ("weights_", "momentum_", "covariance_")
    _kind = "functional_link"
    _structural_params = (
        "n_inputs",
        "order",
        "basis",
        "cross_degree",
        "branches",
        "output",
        "solver",
        "exponents",
        "factors",
    )

    def __init__(
        self,
        n_inputs: int = 1,
        order: int = 4,
        basis: str = "legendre",
        cross_degree: int = 0,
        branches: list[list[int]] | None = None,
        output: str = "tanh",
        output_scale: float = 1.0,
        solver: str = "sgd",
        alpha: float = 0.5,
        beta: float = 0.5,
        nlms_step: float = 0.5,
        forgetting: float = 1.0,
        initial_covariance: float = 1000.0,
        max_trace: float | None = None,
        init_scale: float = 0.1,
        out_of_range: str = "clip",
        random_state: int | None = 0,
        exponents: list[list[int]] | None = None,
        factors: list[list[float]] | None = None,
    ) -> None:
        super().__init__(
            n_inputs=n_inputs,
            order=order,
            basis=basis,
            cross_degree=cross_degree,
            branches=branches,
            output=output,
            output_scale=output_scale,
            solver=solver,
            alpha=alpha,
            beta=beta,
            nlms_step=nlms_step,
            forgetting=forgetting,
            initial_covariance=initial_covariance,
            max_trace=max_trace,
            init_scale=init_scale,
            out_of_range=out_of_range,
            random_state=random_state,
            exponents=None if exponents is None else [[int(e) for e in row] for row in exponents],
            factors=None if factors is None else [[float(v) for v in row] for row in factors],
        )
        self._validate()

    def _validate(self) -> None:
        if self.exponents is not None:
            self._validate_exponents()
        elif self.factors is not None:
            raise ValueError("factors go with selected terms (exponents), one row per term")
        if self.basis not in BASES:
            raise ValueError(f"basis must be one of {', '.join(BASES)}, not {self.basis!r}")
        if self.solver not in SOLVERS:
            raise ValueError(f"solver must be one of {', '.join(SOLVERS)}, not {self.solver!r}")
        super()._validate()
        if self.solver != "sgd" and self.output != "linear":
            raise ValueError(f"solver {self.solver!r} needs output='linear' (it is linear least squares)")
        if self.solver != "sgd" and self.branches is not None and len(self.branches) > 1:
            raise ValueError("nlms/rls learn one linear combiner: use branches=None")
        if int(self.order) < 1 or int(self.n_inputs) < 1:
            raise ValueError("order and n_inputs must be >= 1")
        if not 0.0 < self.forgetting <= 1.0:
            raise ValueError("forgetting factor lambda must lie in (0, 1]")
        if not 0.0 < self.nlms_step < 2.0:
            raise ValueError("nlms_step must lie in (0, 2) for NLMS to converge")

    def _validate_exponents(self) -> None:
        """One exponent per input, none negative: the compiled free run indexes its table with them unchecked."""
        rows = np.asarray(self.exponents, dtype=np.int64).reshape(len(self.exponents), -1)
        if len(self.exponents) == 0 or rows.shape[1] != int(self.n_inputs) or (rows < 0).any():
            raise ValueError(f"exponents must be non-empty rows of {self.n_inputs} non-negative integers")
        if self.branches is not None and len(self.branches) > 1:
            raise ValueError("selected terms (exponents) make one combiner: use branches=None")
        if self.factors is not None:
            checked_factors(np.asarray(self.factors, dtype=np.float64), len(self.exponents), int(self.n_inputs))

    @property
    def trace_bound(self) -> float:
        """The bound on trace(P) the RLS rule keeps: ``max_trace``, or the prior's trace when that is None."""
        if self.max_trace is not None:
            return float(self.max_trace)
        return float(self.n_weights) * float(self.initial_covariance)

    @property
    def branch_inputs_(self) -> list[list[int]]:
        return _as_branches(self.branches, self.n_inputs)

    @property
    def n_weights(self) -> int:
        """Weights incl. one bias per branch: Table I's n1 N0 per output node.

        Read on every compiled step (the RLS trace bound): once the weights exist, their
        count, instead of summing the expansion's size over the branches again."""
        weights = self.__dict__.get("weights_")
        if weights is not None:
            return weights.size
        if self.exponents is not None:
            return len(self.exponents)
        return sum(1 + feature_count(len(b), self.order, self.cross_degree) for b in self.branch_inputs_)

    def term_exponents(self) -> tuple[np.ndarray, np.ndarray]:
        """(exponent row of every weight over all inputs, branch of every weight).

        The one description of the features the compiled free run needs, whether the
        terms were selected (``exponents``) or are the full per-branch expansion.
        """
        if self.exponents is not None:
            rows = np.asarray(self.exponents, dtype=np.int64).reshape(len(self.exponents), int(self.n_inputs))
            return rows, np.zeros(len(rows), dtype=np.int64)
        blocks, branch_of = [], []
        for index, branch in enumerate(self.branch_inputs_):
            local = full_exponents(len(branch), int(self.order), int(self.cross_degree))
            rows = np.zeros((len(local), int(self.n_inputs)), dtype=np.int64)
            rows[:, branch] = local
            blocks.append(rows)
            branch_of += [index] * len(local)
        return np.vstack(blocks), np.array(branch_of, dtype=np.int64)

    def term_factors(self) -> np.ndarray:
        """Factor row of every weight (:mod:`~lenn_ros.core.expansions`), or (0, n_inputs + 2) when none has one."""
        n = int(self.n_inputs)
        if self.factors is None:
            return np.zeros((0, n + 2))
        return checked_factors(np.asarray(self.factors, dtype=np.float64), len(self.exponents), n)

    def _initialise(self) -> None:
        rng = np.random.default_rng(self.random_state)
        branch_of = []
        if self.exponents is not None:
            branch_of = [0] * len(self.exponents)
        for index, branch in enumerate(self.branch_inputs_ if self.exponents is None else []):
            branch_of += [index] * (1 + feature_count(len(branch), self.order, self.cross_degree))
        self.feature_branch_ = np.array(branch_of, dtype=np.int64)
        n = len(branch_of)
        self.weights_ = rng.uniform(-self.init_scale, self.init_scale, n) if self.init_scale else np.zeros(n)
        self.momentum_ = np.zeros(n)
        if self.solver == "rls":
            self.covariance_ = np.eye(n) * float(self.initial_covariance)
        else:
            self.covariance_ = np.zeros((0, 0))
        self.n_samples_seen_ = 0
        self.n_clipped_ = 0

    def features(self, x: np.ndarray) -> np.ndarray:
        """Expanded pattern (bias first) of each branch, concatenated."""
        x = self._check_inputs(x)
        if self.exponents is not None:
            return term_features(x, np.asarray(self.exponents, dtype=np.int64), self.basis, self.term_factors())
        if x.shape[0] > 1 and jit.JIT and self.basis in COMPILED_BASES:
            # one compiled pass over all branches, in the column order of the hstack below
            # (the same bits; test_offline_speed checks it); one sample keeps expand's scalar path
            rows = _expansion_rows(int(self.n_inputs), int(self.order), int(self.cross_degree), _branch_key(self))
            return term_features(x, rows, self.basis)
        parts = [expand(x[:, branch], self.order, self.basis, self.cross_degree) for branch in self.branch_inputs_]
        return parts[0] if len(parts) == 1 else np.hstack(parts)

    def update(
        self, x: np.ndarray, d: np.ndarray, learn: bool = True, leverage_out: np.ndarray | None = None
    ) -> np.ndarray:
        """A-priori outputs for each sample, learning from each in turn if ``learn``.

        ``leverage_out`` (RLS only; one entry per sample): filled with each pattern's
        phi' P phi, for the one-step std of each output (``core.spread``).
        """
        if not self.is_initialised:
            self._initialise()
        return self.update_features(self.features(x), d, learn, leverage_out)

    def update_features(
        self, phi: np.ndarray, d: np.ndarray | float, learn: bool = True, leverage_out: np.ndarray | None = None
    ) -> np.ndarray:
        """:meth:`update` for patterns already expanded by :meth:`features`.

        The live identifier expands each regressor once, to predict the next output,
        and learns from the same pattern when that output arrives.
        """
        if not self.is_initialised:
            self._initialise()
        if isinstance(d, float) and phi.shape[0] == 1:
            d = np.array([d])  # the live path: one sample, a plain float target
        else:
            d = np.ascontiguousarray(np.broadcast_to(np.asarray(d, dtype=np.float64), (phi.shape[0],)))
        y = np.empty(phi.shape[0])
        if self.solver == "sgd":
            done = learning_rules.functional_link_sgd(
                self.weights_,
                self.momentum_,
                phi,
                d,
                self.feature_branch_,
                len(self.branch_inputs_),
                float(self.alpha),
                float(self.beta),
                self.output == "tanh",
                float(self.output_scale),
                learn,
                y,
            )
        elif self.solver == "nlms":
            done = learning_rules.functional_link_nlms(self.weights_, phi, d, float(self.nlms_step), 1e-6, learn, y)
        else:
            done = learning_rules.functional_link_rls(
                self.weights_,
                self.covariance_,
                phi,
                d,
                float(self.forgetting),
                self.trace_bound,
                learn,
                y,
                _NO_LEVERAGE if leverage_out is None else leverage_out,
            )
        if learn:
            self.n_samples_seen_ += done
        if done < phi.shape[0]:
            raise DivergenceError(done, y[: done + 1])
        return y


#: ``leverage_out`` of the RLS kernel when nobody asked for it
_NO_LEVERAGE = np.empty(0)


class LeNN(FunctionalLinkNetwork):
    """The paper's Legendre neural network (a functional-link network, Legendre basis)."""


class MLP(OnlineRegressor):
    """Multilayer perceptron, tanh hidden units with biases, backprop with momentum.

    ``hidden=(20, 10)`` with one input is the paper's {1-20-10-1}. ``branches`` sums
    several such networks (Ex. 3's two {1-20-10-1}), trained on the error of the sum.
    """

    _state_names = ("params_", "momentum_")
    _kind = "mlp"
    _structural_params = ("n_inputs", "hidden", "branches", "output")

    def __init__(
        self,
        n_inputs: int = 1,
        hidden: tuple[int, ...] | list[int] = (20, 10),
        branches: list[list[int]] | None = None,
        output: str = "tanh",
        output_scale: float = 1.0,
        alpha: float = 0.5,
        beta: float = 0.5,
        init_scale: float = 0.5,
        out_of_range: str = "clip",
        random_state: int | None = 0,
    ) -> None:
        super().__init__(
            n_inputs=n_inputs,
            hidden=list(hidden),
            branches=branches,
            output=output,
            output_scale=output_scale,
            alpha=alpha,
            beta=beta,
            init_scale=init_scale,
            out_of_range=out_of_range,
            random_state=random_state,
        )
        self._validate()

    def _validate(self) -> None:
        if any(int(h) < 1 for h in self.hidden):
            raise ValueError("hidden layer sizes must be >= 1")
        super()._validate()

    @property
    def trace_bound(self) -> float:
        """The bound on trace(P) the RLS rule keeps: ``max_trace``, or the prior's trace when that is None."""
        if self.max_trace is not None:
            return float(self.max_trace)
        return float(self.n_weights) * float(self.initial_covariance)

    @property
    def branch_inputs_(self) -> list[list[int]]:
        return _as_branches(self.branches, self.n_inputs)

    def layer_sizes(self) -> list[list[int]]:
        """{n0-n1-...-1} of each branch network."""
        return [[len(b), *map(int, self.hidden), 1] for b in self.branch_inputs_]

    @property
    def n_weights(self) -> int:
        return sum(sum((sizes[i] + 1) * sizes[i + 1] for i in range(len(sizes) - 1)) for sizes in self.layer_sizes())

    def _build_layout(self) -> None:
        rows = []
        order = [i for branch in self.branch_inputs_ for i in branch]
        self.input_order_ = np.array(order, dtype=np.int64)
        weight_offset, activation_offset, input_offset = 0, self.n_inputs, 0
        for sizes in self.layer_sizes():
            a_in = input_offset
            input_offset += sizes[0]
            for layer in range(len(sizes) - 1):
                fan_in, fan_out = sizes[layer], sizes[layer + 1]
                is_last = int(layer == len(sizes) - 2)
                rows.append([weight_offset, fan_in, fan_out, a_in, activation_offset, is_last])
                weight_offset += fan_out * (fan_in + 1)
                a_in = activation_offset
                activation_offset += fan_out
        self.layout_ = np.array(rows, dtype=np.int64)
        self.n_activations_ = activation_offset

    def _initialise(self) -> None:
        self._build_layout()
        rng = np.random.default_rng(self.random_state)
        self.params_ = rng.uniform(-self.init_scale, self.init_scale, self.n_weights)
        self.momentum_ = np.zeros(self.n_weights)
        self.n_samples_seen_ = 0
        self.n_clipped_ = 0

    def update(self, x: np.ndarray, d: np.ndarray, learn: bool = True) -> np.ndarray:
        """A-priori outputs for each sample, learning from each in turn if ``learn``."""
        if not self.is_initialised:
            self._initialise()
        elif not hasattr(self, "layout_"):
            self._build_layout()
        x = np.ascontiguousarray(self._check_inputs(x)[:, self.input_order_])
        d = np.ascontiguousarray(np.broadcast_to(np.asarray(d, dtype=np.float64), (x.shape[0],)))
        y = np.empty(x.shape[0])
        done = learning_rules.mlp_sgd(
            self.params_,
            self.momentum_,
            x,
            d,
            self.layout_,
            self.n_activations_,
            float(self.alpha),
            float(self.beta),
            self.output == "tanh",
            float(self.output_scale),
            learn,
            y,
        )
        if learn:
            self.n_samples_seen_ += done
        if done < x.shape[0]:
            raise DivergenceError(done, y[: done + 1])
        return y


def _branch_key(network: FunctionalLinkNetwork) -> tuple[tuple[int, ...], ...]:
    return tuple(tuple(branch) for branch in network.branch_inputs_)


@lru_cache(maxsize=64)
def _expansion_rows(n_inputs: int, order: int, cross_degree: int, branches: tuple[tuple[int, ...], ...]) -> np.ndarray:
    """Exponent rows of a full per-branch expansion (:meth:`FunctionalLinkNetwork.term_exponents`).

    Cached: the identifier expands a series in blocks of a thousand samples, and
    building the rows in Python each time would cost a good part of expanding them.
    """
    network = FunctionalLinkNetwork(
        n_inputs=n_inputs, order=order, cross_degree=cross_degree, branches=[list(b) for b in branches]
    )
    return np.ascontiguousarray(network.term_exponents()[0])


def make_network(kind: str, **params: Any) -> OnlineRegressor:
    """Build a network by name: ``lenn`` (any functional-link basis) or ``mlp``."""
    if kind in ("lenn", "flnn", "functional_link"):
        return FunctionalLinkNetwork(**params)
    if kind == "mlp":
        return MLP(**params)
    raise ValueError(f"unknown network {kind!r}; expected 'lenn' or 'mlp'")

"""Configurations tried beyond the paper: a linear output with RLS / NLMS, other bases, cross terms.

The best one per example is *not* picked on the reported seeds: ``bench/beyond_search.py``
scores every candidate on :data:`CALIBRATION_SEEDS` and :data:`WINNERS` records its choice
(its output is in ``bench/beyond-search-latest.md``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from lenn_ros.core.networks import OnlineRegressor
from lenn_ros.paper.examples import EXAMPLES, PaperExample

#: seeds the candidates are scored on; the reported results use seeds 0..K-1
CALIBRATION_SEEDS = (100, 101, 102)

_BASIS_LABEL = {"legendre": "Legendre", "chebyshev": "Chebyshev", "trigonometric": "trig."}


@dataclass(frozen=True)
class Candidate:
    """A functional-link network with a linear output and a least-squares-type rule.

    ``params`` are constructor overrides on top of the example's LeNN parameters
    (a tuple of pairs so the candidate is immutable and hashable).
    """

    solver: str
    basis: str
    order: int
    cross_degree: int = 0
    params: tuple[tuple[str, Any], ...] = ()

    @property
    def name(self) -> str:
        text = f"{self.solver.upper()} {_BASIS_LABEL[self.basis]} order {self.order}"
        if self.cross_degree:
            text += f" + cross deg {self.cross_degree}"
        extra = dict(self.params)
        if "nlms_step" in extra:
            text += f", mu {extra['nlms_step']:g}"
        if extra.get("forgetting", 1.0) != 1.0:
            text += f", lambda {extra['forgetting']:g}"
        return text

    def feature_overrides(self) -> dict[str, Any]:
        """The expansion alone: what :func:`least_squares_floor` needs.

        ``branches=None``: RLS/NLMS learn one linear combiner, so Ex. 3's two
        sub-networks become one expansion of [y, u] with one bias (same span).
        """
        return {"basis": self.basis, "order": self.order, "cross_degree": self.cross_degree, "branches": None}

    def overrides(self) -> dict[str, Any]:
        return {
            **self.feature_overrides(),
            "output": "linear",
            "output_scale": 1.0,
            "solver": self.solver,
            **dict(self.params),
        }

    def make(self, example: PaperExample, seed: int) -> OnlineRegressor:
        return example.make_network("lenn", seed, **self.overrides())

    def with_params(self, **params: Any) -> Candidate:
        return Candidate(
            self.solver, self.basis, self.order, self.cross_degree, tuple({**dict(self.params), **params}.items())
        )


def rls(basis: str, order: int, cross_degree: int = 0, **params: Any) -> Candidate:
    return Candidate("rls", basis, order, cross_degree, tuple(params.items()))


def nlms(basis: str, order: int, cross_degree: int = 0, step: float = 0.5) -> Candidate:
    return Candidate("nlms", basis, order, cross_degree, (("nlms_step", step),))


def candidates(number: int) -> list[Candidate]:
    """The small set tried per example (see bench/beyond_search.py for their scores).

    Always: RLS and NLMS on the paper's own features (the rule alone changes). With
    several inputs: cross terms of total degree 2 and 3, and a higher degree where the
    plant needs it (Ex. 2's numerator is of degree 4 over a rational denominator, Ex.
    4's of degree 5), in each of the three bases. Ex. 1 has one input, so cross terms
    do not exist there; its variants change the order and the basis instead.
    """
    order = EXAMPLES[number].lenn["order"]
    paper_features = [rls("legendre", order), nlms("legendre", order, step=0.5), nlms("legendre", order, step=0.1)]
    if number == 1:
        return [*paper_features, rls("legendre", 20), rls("chebyshev", order), rls("trigonometric", order)]
    if number == 3:
        # additive f(y) + g(u): cross terms are not needed, a lower order is tried instead
        return [
            *paper_features,
            rls("legendre", order, 2),
            rls("legendre", order, 3),
            rls("legendre", 8),
            rls("chebyshev", 8),
            rls("trigonometric", order),
        ]
    high = {2: 8, 4: 4}[number]
    return [
        *paper_features,
        rls("legendre", order, 2),
        rls("legendre", order, 3),
        rls("legendre", order, high),
        rls("chebyshev", order, high),
        rls("trigonometric", order, high),
        nlms("trigonometric", order, high, step=0.5),
    ]


def find_candidate(number: int, name: str) -> Candidate:
    for candidate in candidates(number):
        if candidate.name == name:
            return candidate
    raise ValueError(f"example {number} has no candidate {name!r}")


#: Chosen by bench/beyond_search.py on seeds 100-102 (bench/beyond-search-latest.md):
#: lowest max(mean one-step NMSE, mean free-run NMSE), i.e. the best worse-of-the-two.
WINNERS: dict[int, str] = {
    1: "RLS Legendre order 20",
    2: "RLS trig. order 6 + cross deg 8",
    3: "RLS Legendre order 14 + cross deg 2",
    4: "RLS trig. order 2 + cross deg 4",
}


def winner(number: int) -> Candidate:
    return find_candidate(number, WINNERS[number])

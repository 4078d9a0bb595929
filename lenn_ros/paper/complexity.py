"""Table I of the paper: operations per training iteration, for any configuration."""

from __future__ import annotations

from dataclasses import asdict, dataclass


@dataclass(frozen=True)
class Complexity:
    """Counts per training iteration (evaluating the polynomials is not counted)."""

    weights: int
    additions: int
    multiplications: int
    tanh: int

    def __add__(self, other: Complexity) -> Complexity:
        return Complexity(*(a + b for a, b in zip(asdict(self).values(), asdict(other).values(), strict=True)))

    def as_dict(self) -> dict[str, int]:
        return asdict(self)


def mlp_complexity(layers: list[int]) -> Complexity:
    """Table I, MLP column, for {n0-n1-...-nL}."""
    if len(layers) < 2:
        raise ValueError("an MLP needs at least an input and an output layer")
    big_l = len(layers) - 1
    s1 = sum((layers[i] + 1) * layers[i + 1] for i in range(big_l))
    s2 = sum(layers[i] * layers[i + 1] for i in range(big_l))
    s3 = sum(layers[1:])
    n0, n1, n_last = layers[0], layers[1], layers[-1]
    return Complexity(
        weights=s1,
        additions=3 * s2 + 3 * n_last - n0 * n1,
        multiplications=4 * s2 + 3 * s3 - n0 * n1 + 2 * n_last,
        tanh=s3,
    )


def lenn_complexity(expanded_terms: int, outputs: int = 1) -> Complexity:
    """Table I, LeNN column: n0 = expanded pattern size (no bias), N0 = n0 + 1."""
    n0, n1 = expanded_terms, outputs
    big_n0 = n0 + 1
    return Complexity(
        weights=n1 * big_n0,
        additions=2 * n1 * big_n0 + n1,
        multiplications=3 * n1 * big_n0 + n0,
        tanh=n1,
    )

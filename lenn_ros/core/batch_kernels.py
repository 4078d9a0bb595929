"""A term model over a whole series at once, compiled: its features, and least squares formed on the fly.

``expansions.term_features`` in numpy makes a pass over the whole batch per degree and per
term; :func:`term_expansion` computes each block of samples' polynomials once and shares them
among the terms. The least-squares fits (``paper.evaluation``) need only sums over the rows
of [Phi | d]: :func:`normal_equations` and :func:`qr_rows` expand the rows block by block and
accumulate them, so the N x p feature matrix is never built. The terms are read through
``term_kernels``' term plan (:func:`~lenn_ros.core.term_kernels.sparse_terms`), the one the
free run reads them through.
"""

from __future__ import annotations

import math

import numpy as np

from lenn_ros.core.jit import njit
from lenn_ros.core.term_kernels import factor_value, sparse_terms, top_degree

#: samples expanded side by side. One sample's recursion is a chain of dependent
#: divisions, bound by their latency; across a block the same step of every sample is
#: independent and runs in SIMD lanes, with unchanged arithmetic per element (the same
#: bits). Ex. 1's 15 terms of 550 000 samples took 35 ms in blocks of 4, 18 ms of 16,
#: 14 ms of 32 and about the same of 64 (one run each, a busy 2-core machine).
EXPANSION_BLOCK = 32
#: the same for a column-major ``out`` (``fit``'s designs): each term's run of samples is written to its
#: own column, and runs of 32 spread a block's writes over as many pages as there are terms (a 281-term
#: design of 40 000 samples: 41 ms in blocks of 32, 31 ms of 256, 26 ms row-major)
COLUMN_MAJOR_BLOCK = 256


@njit(cache=True, nogil=True, inline="always")
def _univariate_block(x: np.ndarray, k0: int, count: int, i: int, top: int, basis: int, table: np.ndarray) -> None:
    """table[n, b] = P_n(x[k0 + b, i]) for n <= top, b < count: ``term_kernels._univariate_row`` for a block.

    The recursions are written exactly as in ``expansions`` ((2n+1) x P_n - n P_{n-1},
    then / (n+1)), so each element gets the numpy path's bits.
    """
    for b in range(count):
        table[0, b] = 1.0
    if top == 0:
        return
    for b in range(count):
        table[1, b] = x[k0 + b, i]
    for n in range(1, top):
        if basis == 0:
            for b in range(count):
                table[n + 1, b] = ((2 * n + 1) * table[1, b] * table[n, b] - n * table[n - 1, b]) / (n + 1)
        elif basis == 1:
            for b in range(count):
                table[n + 1, b] = 2.0 * table[1, b] * table[n, b] - table[n - 1, b]
        else:
            harmonic = (n + 1) // 2
            for b in range(count):
                angle = harmonic * math.pi * table[1, b]
                table[n + 1, b] = math.sin(angle) if n % 2 else math.cos(angle)


@njit(cache=True, nogil=True, inline="always")
def _expand_block(
    x: np.ndarray,
    k0: int,
    count: int,
    plan,
    factors: np.ndarray,
    basis: int,
    table: np.ndarray,
    phi: np.ndarray,
) -> None:
    """phi[t, b] = prod_i P_{e_ti}(x[k0 + b, i]), multiplied from 1.0 in input order.

    1.0 first and the inputs in order is what ``expansions.term_features_reference``
    does (and ``expand``, whose single-input columns are 1.0 * P exactly), so the bits agree.
    ``plan`` is :func:`sparse_terms` of the terms: only the inputs some term reads get
    polynomials, and each term visits only its own entries. A long lag span's dictionary
    (hundreds of inputs, averages over dozens of them) costs what its terms read.
    """
    e_start, e_input, e_degree, f_start, f_input, f_weight, need = plan
    for i in range(x.shape[1]):
        if need[i] > 0:
            _univariate_block(x, k0, count, i, need[i], basis, table[i])
    for t in range(e_start.shape[0] - 1):
        for b in range(count):
            phi[t, b] = 1.0
        for e in range(e_start[t], e_start[t + 1]):
            row = table[e_input[e], e_degree[e]]
            for b in range(count):
                phi[t, b] *= row[b]
    _factor_block(x, k0, count, f_start, f_input, f_weight, factors, phi)


@njit(cache=True, nogil=True, inline="always")
def _factor_block(
    x: np.ndarray,
    k0: int,
    count: int,
    f_start: np.ndarray,
    f_input: np.ndarray,
    f_weight: np.ndarray,
    factors: np.ndarray,
    phi: np.ndarray,
) -> None:
    """phi[t, b] *= g_t(b_t + w_t . x(k0 + b)) for every term with a factor, over its non-zero weights in order."""
    for t in range(factors.shape[0]):
        if factors[t, 0] != 0.0:
            kind = int(factors[t, 0])
            for b in range(count):
                z = factors[t, 1]
                for f in range(f_start[t], f_start[t + 1]):
                    z += f_weight[f] * x[k0 + b, f_input[f]]
                phi[t, b] *= factor_value(kind, z)


@njit(cache=True, nogil=True)
def term_expansion(x: np.ndarray, exponents: np.ndarray, basis: int, factors: np.ndarray, out: np.ndarray) -> None:
    """out[k, t] = prod_i P_{e_ti}(x[k, i]): ``expansions.term_features`` in one compiled pass.

    Each sample's polynomials are computed once and shared by all its terms; numpy
    instead makes a pass over the whole batch per degree and per term, several times
    the arithmetic in memory traffic.
    """
    n_samples = x.shape[0]
    block = EXPANSION_BLOCK if out.strides[1] <= out.strides[0] else COLUMN_MAJOR_BLOCK
    table = np.empty((x.shape[1], top_degree(exponents) + 1, block))
    phi = np.empty((exponents.shape[0], block))
    plan = sparse_terms(exponents, factors)
    for k0 in range(0, n_samples, block):
        count = min(block, n_samples - k0)
        _expand_block(x, k0, count, plan, factors, basis, table, phi)
        for t in range(exponents.shape[0]):  # term by term: contiguous runs in a column-major ``out`` too
            for b in range(count):
                out[k0 + b, t] = phi[t, b]


@njit(cache=True, nogil=True, inline="always")
def _augmented_rows(
    x: np.ndarray,
    targets: np.ndarray,
    k0: int,
    plan,
    factors: np.ndarray,
    basis: int,
    table: np.ndarray,
    phi: np.ndarray,
    rows: np.ndarray,
) -> int:
    """rows[b] = [phi(x[k0 + b]) | d(k0 + b)] for one block; returns how many rows it filled.

    The one place both least-squares kernels (normal equations and Givens QR) form the
    augmented rows they consume.
    """
    n_terms = phi.shape[0]
    count = min(EXPANSION_BLOCK, x.shape[0] - k0)
    _expand_block(x, k0, count, plan, factors, basis, table, phi)
    for b in range(count):
        for t in range(n_terms):
            rows[b, t] = phi[t, b]
        rows[b, n_terms] = targets[k0 + b]
    return count


@njit(cache=True, nogil=True)
def normal_equations(
    x: np.ndarray, targets: np.ndarray, exponents: np.ndarray, factors: np.ndarray, basis: int, gram: np.ndarray
) -> None:
    """gram += [Phi | d]' [Phi | d], each sample's features expanded on the fly.

    The batch least-squares fit needs only Phi' Phi (gram[:p, :p]), Phi' d
    (gram[:p, p]) and d' d, so the N x p feature matrix (70 MB at 550 000 samples and
    16 terms) is never built. Full rows rather than the upper triangle: the fixed
    length vectorises, and costs less than half the work it saves.
    """
    n_samples, n_terms = x.shape[0], exponents.shape[0]
    table = np.empty((x.shape[1], top_degree(exponents) + 1, EXPANSION_BLOCK))
    rows = np.empty((EXPANSION_BLOCK, n_terms + 1))
    phi = np.empty((n_terms, EXPANSION_BLOCK))
    plan = sparse_terms(exponents, factors)
    for k0 in range(0, n_samples, EXPANSION_BLOCK):
        count = _augmented_rows(x, targets, k0, plan, factors, basis, table, phi, rows)
        for b in range(count):
            for i in range(n_terms + 1):
                v = rows[b, i]
                for j in range(n_terms + 1):
                    gram[i, j] += v * rows[b, j]


@njit(cache=True, nogil=True)
def qr_rows(
    x: np.ndarray, targets: np.ndarray, exponents: np.ndarray, factors: np.ndarray, basis: int, r: np.ndarray
) -> None:
    """Update the triangular R of [Phi | d] (p + 1 columns) with every sample, by Givens rotations.

    R' R = [Phi | d]' [Phi | d] as with :func:`normal_equations`, but R is formed from
    the rows by orthogonal transformations, so its conditioning is that of Phi, not
    its square: what an ill-conditioned expansion needs. Compiled and single-threaded
    on purpose: numpy's QR of tall blocks of rows runs on OpenBLAS's threads, and on a
    busy 2-core machine took 1.5-50 s for 550 000 rows of 16-42 columns, where this
    loop takes about 0.45 us a row at 16 columns and 1 us at 31.
    """
    n_samples, n_terms = x.shape[0], exponents.shape[0]
    table = np.empty((x.shape[1], top_degree(exponents) + 1, EXPANSION_BLOCK))
    rows = np.empty((EXPANSION_BLOCK, n_terms + 1))
    phi = np.empty((n_terms, EXPANSION_BLOCK))
    plan = sparse_terms(exponents, factors)
    for k0 in range(0, n_samples, EXPANSION_BLOCK):
        count = _augmented_rows(x, targets, k0, plan, factors, basis, table, phi, rows)
        for b in range(count):
            _givens_row(r, rows[b])


@njit(cache=True, nogil=True, inline="always")
def _givens_row(r: np.ndarray, row: np.ndarray) -> None:
    """Rotate ``row`` into the upper triangular ``r``, zeroing it entry by entry."""
    n = len(row)
    for j in range(n):
        b = row[j]
        if b == 0.0:
            continue
        a = r[j, j]
        h = math.hypot(a, b)
        c, s = a / h, b / h
        r[j, j] = h
        for col in range(j + 1, n):
            upper, lower = r[j, col], row[col]
            r[j, col] = c * upper + s * lower
            row[col] = c * lower - s * upper

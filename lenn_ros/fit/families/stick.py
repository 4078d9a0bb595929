"""The ``stick`` family: the increment form's linear terms and the dead zone of the friction-free next increment.

relu(p - c) and relu(-p - c) at knots c around the Coulomb step: a body with Coulomb
friction moves on by what drives it beyond the friction and stops exactly, within one
sample, where that is less. This is the exact sampled form of Coulomb friction with
sticking, which smooth terms of the velocity only approach (a tanh of it creeps where the
body sticks). The direction p and the step come from the training record
(:func:`_dead_zone_terms`). Least squares fits the stick threshold badly when the measured
velocity at rest is noise (a 1 kHz encoder): its weights are a start that the refinement
on simulation error takes further than other families' (FAR_ITERATIONS).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from lenn_ros.fit.families.base import Builder, Dictionary
from lenn_ros.fit.families.increment import linear_increments

if TYPE_CHECKING:
    from lenn_ros.fit.families import Spec

#: lags of the ``stick`` family, and the dead zone's knots in units of the Coulomb step it estimates
STICK_LAGS = (3, 4)
STICK_KNOTS = (0.5, 1.0, 2.0)
#: most refinement iterations (``refinement.ITERATIONS`` for the others): least squares sets the stick threshold by
#: noise, its start lies far from its simulation-error fit, and the blocks still chose the last of 15
FAR_ITERATIONS = 40


def dictionary(spec: Spec, x: np.ndarray) -> Dictionary:
    """y(k+1) - y(k) from the bias, the output increments, the inputs, and the dead zone of the friction-free
    next increment (:func:`_dead_zone_terms`)."""
    built, read, _ = linear_increments(spec, x)
    _dead_zone_terms(built, x, read)
    return built.build(increment=True)


#: samples whose increment is beyond this share of the increments' spread count as moving
MOVING = 0.1


def _dead_zone_terms(built: Builder, x: np.ndarray, read: list[int]) -> None:
    """relu(p - c), relu(-p - c): the dead zone of p, the next increment as it would be without Coulomb friction.

    From the training record's own lags: the increment v = y(k) - y(k-1) is regressed,
    over the samples moving before it, on the increment before it, each input one lag
    back, a sign of that increment (tanh, sharp: the Coulomb friction) and a bias. The
    friction-free next increment is p = a v + sum b_i u_i(k) + bias, and the sign's
    weight is the Coulomb step c. Sampled Coulomb friction is then exactly: the body
    moves on by p less c beyond the dead zone [-c, c] and stands still within it. The
    knots are STICK_KNOTS times c (the estimate is rough; the refinement sets the weights).
    """
    now, before = x[:, 0] - x[:, 1], x[:, 1] - x[:, 2]
    spread = float(np.std(before))
    moving = np.abs(before) > MOVING * spread
    regressors = np.column_stack(
        [before, *(x[:, start + 1] for start in read), np.tanh(before / (0.05 * spread or 1.0)), np.ones(len(x))]
    )
    if spread == 0.0 or np.count_nonzero(moving) < 10 * regressors.shape[1]:
        return
    c = np.linalg.lstsq(regressors[moving], now[moving], rcond=None)[0]
    step = abs(float(c[-2]))
    if not step > 0.0:
        return
    w = np.zeros(built.n)
    w[0], w[1] = c[0], -c[0]
    for start, b in zip(read, c[1:-2], strict=True):
        w[start] = b
    for knot in STICK_KNOTS:
        built.add(None, "relu", w, float(c[-1]) - knot * step)
        built.add(None, "relu", -w, -float(c[-1]) - knot * step)

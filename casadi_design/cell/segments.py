"""The distance between two segments, smooth for the NLP (CasADi) and exact for the checks (numpy).

A capsule is a segment ``[a, b]`` and a radius; two capsules are apart by at least ``c`` when
``dist([a1, b1], [a2, b2]) - r1 - r2 - c >= 0``. :func:`segment_distance` is that distance,
smoothed as ``sqrt(D^2 + delta^2) - delta`` (m) so that it is differentiable where the segments
touch; :func:`segment_distance_np` is its numpy twin.
"""

from __future__ import annotations

from types import SimpleNamespace

import casadi as ca
import numpy as np

#: ``delta`` of the smoothed distance ``sqrt(D^2 + delta^2) - delta`` (m): differentiable where
#: the segments touch, below the exact distance by at most ``delta``.
SMOOTHING_M = 1e-6
#: Segments are treated as parallel when ``sin^2`` of their angle is below this.
PARALLEL_TOL = 1e-10
def _clamp01(x, fmin, fmax):
    return fmin(fmax(x, 0.0), 1.0)


def _segment_distance_sq(p0, p1, q0, q1, ops) -> object:
    """``D^2 = min_{s, t in [0, 1]} |p0 + s d1 - q0 - t d2|^2`` (m^2), ``d1 = p1 - p0``,
    ``d2 = q1 - q0``.

    The minimum of a convex quadratic over the square: the stationary point when it lies
    inside and the segments are not parallel, otherwise the smallest of the four
    endpoint-to-segment distances (the minima on the square's sides). Written once for
    CasADi and numpy (``ops``: dot, fmin, fmax, if_else).
    """
    dot, fmin, fmax, if_else = ops.dot, ops.fmin, ops.fmax, ops.if_else
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a, e, b = dot(d1, d1), dot(d2, d2), dot(d1, d2)
    c, f = dot(d1, r), dot(d2, r)

    def to_segment(p, s0, d, dd):
        t = _clamp01(dot(p - s0, d) / fmax(dd, 1e-300), fmin, fmax)
        w = s0 + t * d - p
        return dot(w, w)

    sides = fmin(fmin(to_segment(p0, q0, d2, e), to_segment(p1, q0, d2, e)),
                 fmin(to_segment(q0, p0, d1, a), to_segment(q1, p0, d1, a)))
    denom = a * e - b * b
    crossing = denom > PARALLEL_TOL * a * e
    safe = if_else(crossing, denom, 1.0)
    s, t = (b * f - c * e) / safe, (a * f - b * c) / safe
    w = r + s * d1 - t * d2
    inside = ops.logical_and(crossing, ops.logical_and(ops.logical_and(s > 0, s < 1),
                                                       ops.logical_and(t > 0, t < 1)))
    return if_else(inside, dot(w, w), sides)


CASADI_OPS = SimpleNamespace(dot=ca.dot, fmin=ca.fmin, fmax=ca.fmax, sqrt=ca.sqrt, if_else=ca.if_else,
                      logical_and=ca.logic_and)
NUMPY_OPS = SimpleNamespace(dot=np.dot, fmin=np.minimum, fmax=np.maximum, sqrt=np.sqrt,
                      if_else=lambda c, x, y: x if c else y, logical_and=lambda x, y: bool(x and y))


def segment_distance(p0, p1, q0, q1, smoothing_m: float = SMOOTHING_M) -> ca.SX:
    """Distance (m) between the segments ``[p0, p1]`` and ``[q0, q1]`` (CasADi, 3-vectors).

    Returns ``sqrt(D^2 + delta^2) - delta`` with ``D`` the exact distance and
    ``delta = smoothing_m``: within ``delta`` below ``D``, defined everywhere.

    Smoothness: ``D^2`` is the minimum over ``(s, t)`` of a convex quadratic; where the
    minimiser is unique its gradient is that of the quadratic at the minimiser (Danskin), and
    the branches (interior point, clamped sides) meet with equal values and gradients. ``D^2``
    is therefore continuously differentiable except for parallel segments whose projections
    overlap (a whole set of closest pairs), where it is continuous but has a kink; near that
    set (``sin^2`` of the angle ~ ``PARALLEL_TOL``) the gradient is computed through an
    ill-conditioned stationary point and loses digits. Degenerate segments (points) are
    exact. No branch divides by zero, so no NaN is produced.
    """
    p0, p1, q0, q1 = (ca.SX(v) if not isinstance(v, ca.SX) else v for v in (p0, p1, q0, q1))
    D2 = _segment_distance_sq(p0, p1, q0, q1, CASADI_OPS)
    return ca.sqrt(D2 + smoothing_m**2) - smoothing_m


def segment_distance_np(p0, p1, q0, q1, smoothing_m: float = SMOOTHING_M) -> float:
    """Numpy twin of :func:`segment_distance` (same formula, m)."""
    p0, p1, q0, q1 = (np.asarray(v, dtype=float) for v in (p0, p1, q0, q1))
    D2 = max(float(_segment_distance_sq(p0, p1, q0, q1, NUMPY_OPS)), 0.0)
    return float(np.sqrt(D2 + smoothing_m**2) - smoothing_m)


# ---------------------------------------------------------------------------------------------
# capsules from geometry

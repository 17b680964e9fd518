"""The tracker frame in closed form: the rigid motion that best maps model points onto measured
points (Kabsch / Umeyama without scale), before the iterated fit refines it.

    min over R, t of  sum_i |R a_i + t - b_i|^2,   R a rotation

Centre both point sets (``a_i - a_bar``, ``b_i - b_bar``), ``H = sum (a_i - a_bar)(b_i -
b_bar)^T = U S V^T``, ``R = V diag(1, .., det(V U^T)) U^T``, ``t = b_bar - R a_bar``. With only
x and y measured (a planar arm) the motion is planar: a rotation about z and a translation in x, y.
"""

from __future__ import annotations

import numpy as np

#: A point set spans a plane (3-D) or a line (2-D) when its second singular value exceeds
#: this fraction of its first; otherwise the rotation about that line is not determined.
SPREAD_RTOL = 1e-6


def rigid_fit(A: np.ndarray, B: np.ndarray, axes: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray] | None:
    """``(R, t)`` (3 x 3, 3; m) minimising ``sum |R a_i + t - b_i|^2`` over the components
    ``axes`` (all three, or x and y: then ``R`` is a rotation about z and ``t_z = 0``).

    Parameters
    ----------
    A, B : ndarray, shape (N, 3), m: model and measured points (only ``axes`` are used).

    Returns None when the points do not determine the motion (fewer than 3 points, or all on a
    line in 3-D, or all at one point in 2-D).
    """
    a, b = np.asarray(A, float)[:, axes], np.asarray(B, float)[:, axes]
    dim = len(axes)
    if len(a) < dim or dim not in (2, 3):
        return None
    a_bar, b_bar = a.mean(axis=0), b.mean(axis=0)
    sv = np.linalg.svd(a - a_bar, compute_uv=False)
    if not sv[0] > 0 or sv[dim - 2] <= SPREAD_RTOL * sv[0]:
        return None
    U, _, Vt = np.linalg.svd((a - a_bar).T @ (b - b_bar))
    D = np.eye(dim)
    D[-1, -1] = np.sign(np.linalg.det(Vt.T @ U.T))
    r = Vt.T @ D @ U.T
    R, t = np.eye(3), np.zeros(3)
    R[np.ix_(axes, axes)] = r
    t[list(axes)] = b_bar - r @ a_bar
    return R, t

"""What is known before a design: experiments already measured and a prior on the parameters.

A campaign of k measured experiments and m new ones, with a prior of covariance ``C`` on the
physical parameters (SI units), has the information matrix

    M = M_held + sum_i B_i^T B_i,   M_held = sum_k B_k^T B_k + diag(1/c) sigma^2 C^-1 diag(1/c)

in the problem's scaled parameters ``c X`` (:class:`~casadi_design.calibration.models.CalibrationModel`'s
``column_scale``), so that ``cov(X) = sigma^2 M^-1`` as for a plan alone. The prior is
``[calibration.prior]`` (a standard deviation per group of parameters, e.g. a factory
calibration's accuracy) plus the covariance of an earlier identification (``--prior``), which
is marginal: its parameters this problem does not have are integrated out (the covariance's
sub-block is kept), and this problem's parameters it does not name have no prior. Every
criterion, the bound and the identifiability of a plan use ``M``.
"""

from __future__ import annotations

import numpy as np

from ..errors import ProblemError
from ..problem_file.calibration import PriorSpec
from ..problem_file.read import HeldSpec
from ..robot.robots import Robot


def prior_std(robot: Robot, prior: PriorSpec | None, names: tuple[str, ...]) -> np.ndarray:
    """The standard deviation (physical units; inf: none) of each parameter ``names`` under
    ``[calibration.prior]`` (:class:`~casadi_design.problem_file.calibration.PriorSpec`): ``length_m`` for
    translations and prismatic offsets, ``angle_rad`` for rotations, ``offset_rad`` for revolute
    offsets, ``compliance_rad_per_Nm`` for ``k.<joint>``; the tracker frame and the measured
    points (``base.*``, ``tool.*``) have none."""
    std = np.full(len(names), np.inf)
    for i, name in enumerate(names):
        owner, _, e = name.rpartition(".")
        if prior is None or owner in ("base", "tool"):
            continue
        if owner == "k":
            value = prior.compliance_rad_per_Nm
        elif e == "offset":
            prismatic = owner in robot.joints and robot.is_prismatic(robot.joints.index(owner))
            value = prior.length_m if prismatic else prior.offset_rad
        else:
            value = prior.length_m if e.startswith("t") else prior.angle_rad
        std[i] = np.inf if value is None else value
    return std


def prior_information(names: tuple[str, ...], prior: PriorSpec | None, held: HeldSpec | None,
                      robot: Robot, sigma_m: float, where: str) -> np.ndarray | None:
    """``sigma^2 C^-1`` (L x L, physical units) of the prior on ``names``: the group standard
    deviations of ``prior`` on the diagonal plus the marginal information of ``held``'s
    covariance on the parameters it shares with ``names``; None without either.

    Raises
    ------
    ProblemError
        When ``held``'s covariance names none of ``names`` (a prior of another problem) or is not
        a covariance (not symmetric positive definite).
    """
    std = prior_std(robot, prior, names)
    has_groups = bool(np.isfinite(std).any())
    has_file = held is not None and held.prior_covariance is not None
    if not has_groups and not has_file:
        return None
    P = np.diag(sigma_m**2 / std**2)  # 0 where there is no prior (std inf)
    if has_file:
        source = held.prior_file or "--prior"
        shared = [n for n in held.prior_names if n in names]
        if not shared:
            raise ProblemError(
                f"{where}: --prior {source} names none of this problem's parameters "
                f"({', '.join(names)}); give the identification of this robot and model")
        C = np.asarray(held.prior_covariance, dtype=float)
        i = [held.prior_names.index(n) for n in shared]
        Cs = C[np.ix_(i, i)]
        try:
            chol = np.linalg.cholesky((Cs + Cs.T) / 2)
        except np.linalg.LinAlgError:
            raise ProblemError(f"{where}: --prior {source}: the covariance of {', '.join(shared)} is not "
                               "positive definite; give an identification whose parameters were all "
                               "identified") from None
        Ci = np.linalg.inv(chol)
        j = [names.index(n) for n in shared]
        P[np.ix_(j, j)] += sigma_m**2 * (Ci.T @ Ci)
    return P

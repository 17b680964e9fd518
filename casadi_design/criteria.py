"""The design criteria: one registry entry each, read by the NLP, the scores, plots and the CLI.

For a plan with information matrix ``M = sum_i B_i^T B_i`` (``cov(X) = sigma^2 M^-1``):

* test-pose (paper eq. 12 and 15): minimise ``max_j rho_j``, ``rho_j = sigma^2 trace(B0_j M^-1 B0_j^T)``;
* D: maximise ``log det M``; A: minimise ``trace M^-1``; E (the paper's "SVD approach"):
  maximise ``s_L``, the smallest singular value of the stacked B; T: maximise ``trace M``;
  condition: minimise ``s_1 / s_L``.

Each entry holds the field of :class:`casadi_design.measures.Scores` that holds its numeric
value, its labels and line style, a fixed seed id (adding a criterion never changes the starts
of another) and, for E and condition, the powers of their smooth surrogates.

Every criterion is solved by the reduced-space NLP of :mod:`casadi_design.reduced` (test-pose
as the epigraph ``min t`` s.t. ``trace(B0_j M^-1 B0_j^T) <= t``). E and condition are not
smooth in the plan (a repeated eigenvalue at the optimum): they are solved through the log
power means of the eigenvalues of M, ``l_{-r} -> log lambda_min`` and ``l_r -> log
lambda_max``, for the rising powers r of ``powers``, each run starting where the last stopped;
their scores stay the exact ``s_L`` and ``s_1 / s_L``.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Relative tolerance within which two starts count as reaching the same optimum (on the
#: criterion's value; for D on det M, i.e. absolute on log det M).
SAME_OPTIMUM_RTOL = 1e-6
#: Powers r of the surrogates of E and condition: ``l_{-r}`` is within ``log(L) / r`` of
#: ``log lambda_min``.
SURROGATE_POWERS = (4.0, 16.0, 64.0, 256.0)


@dataclass(frozen=True, eq=False)
class Criterion:
    """One design criterion.

    Attributes
    ----------
    name : the name used in problem files, options and results.
    sense : "min" or "max", the better direction of the score.
    score : the field of :class:`~casadi_design.measures.Scores` holding its value.
    label : description for tables, with units.
    legend : name in figure legends.
    style : matplotlib line style of its curves.
    seed_id : third entry of the seed of its starts (fixed forever).
    polished : nearly singular starts first get a few D-optimal iterations (see solve.py).
    log_value : the value is a logarithm (same optimum: absolute tolerance on it).
    powers : the powers r of the surrogate of a non-smooth criterion, one NLP run each.
    """

    name: str
    sense: str
    score: str
    label: str
    legend: str
    style: dict
    seed_id: int
    polished: bool = False
    log_value: bool = False
    powers: tuple[float, ...] = ()

    def better(self, a: float, b: float) -> bool:
        """Whether value ``a`` is strictly better than ``b``."""
        return a < b if self.sense == "min" else a > b

    def same_optimum(self, value: float, best: float) -> bool:
        """Whether ``value`` reaches the optimum ``best`` within ``SAME_OPTIMUM_RTOL`` relative."""
        scale = 1.0 if self.log_value else abs(best)
        return abs(value - best) <= SAME_OPTIMUM_RTOL * scale


CRITERIA: dict[str, Criterion] = {
    c.name: c
    for c in (
        Criterion("test-pose", "min", "max_rms_error_m", "max over test poses of sqrt(rho) (m)",
                  "Test-pose approach", {"color": "tab:red", "ls": "-", "lw": 2.0}, 0),
        Criterion("D", "max", "log_det_M", "log det M (D-optimality)", "D-optimality",
                  {"color": "tab:blue", "ls": "--", "lw": 1.5}, 1, log_value=True),
        Criterion("A", "min", "trace_M_inv", "trace M^-1 (A-optimality)", "A-optimality",
                  {"color": "tab:green", "ls": "-.", "lw": 1.5}, 2),
        Criterion("E", "max", "s_min", "smallest singular value s_L (E-optimality, SVD approach)",
                  "SVD approach (E-optimality)", {"color": "tab:purple", "ls": ":", "lw": 2.0}, 3,
                  polished=True, powers=SURROGATE_POWERS),
        Criterion("T", "max", "trace_M", "trace M (T-optimality)", "T-optimality",
                  {"color": "tab:brown", "ls": (0, (5, 1, 1, 1)), "lw": 1.5}, 4),
        Criterion("condition", "min", "condition", "condition number s_1/s_L", "Condition number",
                  {"color": "tab:gray", "ls": (0, (3, 1)), "lw": 1.5}, 5, polished=True,
                  powers=SURROGATE_POWERS),
    )
}

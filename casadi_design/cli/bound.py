"""``casadi-design bound``: what no plan of m experiments can beat."""

from __future__ import annotations

import argparse

from ..optimisation.bound import bound
from ..execution.campaign import Settings, aim, approximate, check_m_values
from ..reports.tables import format_bounds
from . import common
from ..errors import ProblemError

HELP = "certified lower bound of the test-pose error (and upper bound of log det M)"
DESCRIPTION = ("From the approximate design over single experiments, print per m the certified lower "
               "bound of the max error along the test poses (mm) that no plan of m experiments can "
               "beat, the relaxation's value, and the upper bound of log det M. No design NLP is solved; "
               "the approximate designs of test-pose and D run at the same time, one per worker (--jobs).")


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bound", help=HELP, description=DESCRIPTION)
    p.add_argument("problem", help="problem file (TOML), e.g. problems/paper_planar_2r.toml")
    p.add_argument("--m", type=common.m_values, metavar="RANGE",
                   help="numbers of experiments, e.g. 1:10 or 1,5 (default: the smallest "
                        "identifiable m to the largest [experiments].m)")
    common.add_held(p)
    common.add_workers(p)
    common.add_bound_steps(p, minimum=1)
    common.add_common(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    spec = common.read_spec(args, artefact=True)  # a malformed file fails before any worker starts
    if spec.measurement.artefact is not None:
        return run_artefact(args, spec)
    with common.executor(args) as ex:  # the two approximate designs at the same time, one per worker
        problem = common.load(args, check_solver=False, spec=spec)
        if problem.field is not None:
            source = ("[calibration.model_error]" if problem.spec.calibration.model_error is not None
                      else f"the field of --prior {problem.spec.held.prior_file}")
            raise ProblemError(f"{problem.path}: the test-pose measure holds the robot's unmodelled error ({source}), "
                               "which correlates the experiments: the approximate design's bound assumes independent "
                               "ones and does not hold; bound the paper's measure without the field (remove it)")
        ms = args.m or list(range(problem.m_min, max(problem.m_values) + 1))
        check_m_values(problem, ms)
        settings = Settings.of(problem, bound_steps=args.bound_steps, bound_pool=args.bound_pool)
        approx = approximate(problem, ("test-pose", "D"), ms, settings, ex)
    print(common.case_line(problem, args.quiet))
    print(format_bounds([bound(problem, m, approx[aim(problem, "test-pose", m)]) for m in ms],
                        [bound(problem, m, approx[aim(problem, "D", m)]) for m in ms]))
    for a in approx.values():
        common.say(args, f"{a.criterion}: {len(a.weights)} support points, pool {a.pool_size}, "
                         f"{common.count(len(a.history), 'exchange step')}, {common.count(len(a.checked), 'independent check')}, "
                         f"{a.wall_s:.2f} s" + (" (read back from the cache: the time of the run that "
                                                "computed it)" if a.kept else ""))
    return 0


def run_artefact(args: argparse.Namespace, spec) -> int:
    """``bound`` of a problem measured at an artefact's points: for every set of ``clamps``
    placements of the problem file (where the plans record), the approximate design over the
    configurations seated there (:func:`~casadi_design.plan.seated.seated_configurations`), each
    at most once, with those placements' poses beside X
    (:func:`~casadi_design.optimisation.artefact_pool.artefact_pool`). Each bounds every choice
    of m of its configurations; the least test-pose bound and the largest log det bound over the
    sets bound every choice of m of these configurations (the exchange's plans of ``solve``; the
    NLP that then moves a plan along the seated configurations,
    :mod:`~casadi_design.optimisation.seated_nlp`, leaves them and is not bound by them)."""
    from itertools import combinations

    import numpy as np

    from ..measures.measures import information_matrices
    from ..optimisation.artefact_pool import artefact_pool
    from ..optimisation.bound import pool_design
    from ..plan.seated import seated_configurations

    problem = common.load(args, check_solver=False, spec=spec)
    seated = seated_configurations(problem)
    clamps = spec.measurement.artefact.clamps
    pools = []
    for S in combinations(range(len(seated.names)), clamps):
        rows = np.flatnonzero(np.isin(seated.placement, S))
        pools.append((rows, artefact_pool(problem, seated.Q[rows], seated.point[rows], seated.placement[rows])))
    L = min(pool.B.shape[2] for _, pool in pools)  # X and the placements' poses
    m_min = max(1, -(-L // problem.d_independent))
    ms = args.m or list(range(m_min, max(problem.m_values) + 1))
    if min(ms) < m_min:
        raise ProblemError(f"{problem.path}: --m {min(ms)} is too small: the {L} unknowns (X and the placements' "
                           f"poses) need m >= {m_min} configurations; start the range at {m_min}")
    per_set = []
    for rows, pool in pools:
        idx = rows[pool.kept]
        A, F = information_matrices(pool.B[pool.kept]), np.zeros((len(idx), problem.model.nF))
        per_set.append({c: [bound(problem, m, pool_design(problem, c, seated.Q[idx], F, A, m, pool.B0), pool.B.shape[2])
                            for m in ms] for c in ("test-pose", "D")})
    print(f"{problem.name}: {len(seated.Q)} configurations seated by the nominal robot at {', '.join(seated.names)}, "
          f"each at most once, recorded at {common.count(clamps, 'placement')}: the bounds of any m of them over every "
          "set (the NLP that moves solve's plan along the seated configurations is not bound by them)")
    print(format_bounds([min((b["test-pose"][i] for b in per_set), key=lambda b: b.value) for i in range(len(ms))],
                        [max((b["D"][i] for b in per_set), key=lambda b: b.value) for i in range(len(ms))]))
    return 0

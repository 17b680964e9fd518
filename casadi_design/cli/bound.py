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
    spec = common.read_spec(args)  # a malformed file fails before any worker starts
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

"""Command line: ``casadi-design solve problems/<case>.toml --out DIR``.

Errors in the input or a design that cannot be produced print one line and exit with code 2;
no output file is written unless the whole case was solved.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

from .errors import DesignError, ProblemError


def _solve(args: argparse.Namespace) -> int:
    from .nlp import B0_at_test_poses
    from .plotting import fig1, save_figure
    from .problem import load_problem
    from .results import format_solver_lines, format_table, write_results
    from .solve import solve_design

    t0 = time.perf_counter()
    problem = load_problem(args.problem)
    m_values = args.m or list(problem.m_values)
    criteria = args.criteria or list(problem.criteria)
    B0 = B0_at_test_poses(problem)
    designs = [solve_design(problem, c, m, B0, starts=args.starts, verbose=args.verbose)
               for m in m_values for c in criteria]
    wall = time.perf_counter() - t0
    print(f"{problem.name}: {problem.model.case} calibration of {', '.join(problem.model.parameter_names)}; "
          f"{problem.test_poses.s} test poses; sigma = {problem.sigma_m * 1e3:g} mm; seed {problem.solver.seed}")
    print(format_table(designs))
    print()
    print(format_solver_lines(designs))
    print(f"total {wall:.2f} s for {len(designs)} designs (after imports)")
    if args.out:
        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        write_results(out / "results.json", problem, designs)
        panels = [m for m in m_values][:2] if len(m_values) > 2 else m_values
        fig = fig1(problem.test_poses.position_m, designs, panels)
        for suffix in ("png", "pdf"):
            save_figure(fig, out / f"fig1.{suffix}")
        print(f"wrote {out / 'results.json'}, {out / 'fig1.png'}, {out / 'fig1.pdf'}")
    return 0


def _m_list(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--m takes integers separated by commas, got '{text}'")
    if any(v < 1 for v in values):
        raise argparse.ArgumentTypeError(f"--m takes positive integers, got '{text}'")
    return values


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="casadi-design", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    solve = sub.add_parser("solve", help="design the optimal plans of a problem file and compare criteria")
    solve.add_argument("problem", help="problem file (TOML), e.g. problems/paper_planar_2r.toml")
    solve.add_argument("--out", help="folder for results.json, fig1.png and fig1.pdf (created if missing)")
    solve.add_argument("--m", type=_m_list, help="numbers of experiments, e.g. 1,5 (default: [experiments].m)")
    solve.add_argument("--criteria", type=lambda s: s.split(","),
                       help="criteria, e.g. test-pose,D,E (default: [design].criteria)")
    solve.add_argument("--starts", type=int, help="IPOPT starts per design (default: [solver].starts)")
    solve.add_argument("--verbose", action="store_true", help="show IPOPT's own output")
    solve.set_defaults(run=_solve)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.run(args)
    except (ProblemError, DesignError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2

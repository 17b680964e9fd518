"""Speed of the paper's example: wall time and IPOPT iterations per design, after imports.

    python scripts/benchmark.py [problems/paper_planar_2r.toml] [--repeat 3]

Goal (issue 2): the whole example (test-pose, D, E at m = 1 and 5, multi-start) under 10 s on
a 2-core machine, against about 100 s for a derivative-free scipy multi-start.
"""

import argparse
import statistics
import time

from casadi_design.nlp import B0_at_test_poses
from casadi_design.problem import load_problem
from casadi_design.solve import solve_design


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("problem", nargs="?", default="problems/paper_planar_2r.toml")
    parser.add_argument("--repeat", type=int, default=3, help="runs of the whole case (median reported)")
    args = parser.parse_args()
    totals = []
    for r in range(args.repeat):
        t0 = time.perf_counter()
        problem = load_problem(args.problem)
        B0 = B0_at_test_poses(problem)
        designs = [solve_design(problem, c, m, B0) for m in problem.m_values for c in problem.criteria]
        totals.append(time.perf_counter() - t0)
        if r == 0:
            for d in designs:
                print(f"{d.criterion:<10} m = {d.m:<3} {d.wall_s:7.3f} s  {d.iterations:6d} IPOPT iterations "
                      f"over {len(d.starts)} starts ({d.iterations / len(d.starts):.0f} per start), "
                      f"max error {d.scores.max_rms_error_m * 1e3:.4f} mm")
    print(f"whole case (load + {len(designs)} designs): median {statistics.median(totals):.2f} s "
          f"over {args.repeat} runs (min {min(totals):.2f} s, max {max(totals):.2f} s)")


if __name__ == "__main__":
    main()

"""Speed of a case: `casadi-design solve` run several times, median wall time (after imports).

    python scripts/benchmark.py [problems/paper_planar_2r.toml] [--repeat 3] [--jobs 1] [solve options]

The first run prints the solve command's table and per-design lines (wall time, IPOPT
iterations); later runs are silent. Goal (issue 2): the whole example (test-pose, D, E at m = 1
and 5, multi-start) under 10 s on a 2-core machine, against about 100 s for a derivative-free
scipy multi-start.
"""

import argparse
import contextlib
import io
import statistics
import sys
import time

from casadi_design.cli import main


def benchmark(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("problem", nargs="?", default="problems/paper_planar_2r.toml")
    parser.add_argument("--repeat", type=int, default=3, help="runs of the whole case (median reported)")
    parser.add_argument("--jobs", default="1", help="worker processes (default 1: serial, comparable)")
    args, rest = parser.parse_known_args(argv)
    totals = []
    for r in range(args.repeat):
        out = contextlib.nullcontext() if r == 0 else contextlib.redirect_stdout(io.StringIO())
        t0 = time.perf_counter()
        with out:
            rc = main(["solve", args.problem, "--jobs", args.jobs, *rest])
        totals.append(time.perf_counter() - t0)
        if rc:
            return rc
    print(f"whole case (load + designs, jobs {args.jobs}): median {statistics.median(totals):.2f} s "
          f"over {args.repeat} runs (min {min(totals):.2f} s, max {max(totals):.2f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(benchmark())

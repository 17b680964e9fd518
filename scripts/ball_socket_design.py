"""Which configurations to record, judged on MUKCa's real recordings: from the recordings of one
placement, m chosen by test-pose and by D (``casadi-design solve --candidates``, the same
functions), each plan identified (``identify``'s fit and model choice) and judged by the
consistency at another placement, where the test poses are; beside them the median of random
m-subsets.

    python scripts/ball_socket_design.py [--data ../shared/real_data/mukca] [--m 16] [--random 20]

Cases: panda_2 from ``front_center``, test poses at ``mid_left`` (those of
problems/panda_ball_socket.toml); panda_4 from ``front``, test poses at ``right`` (every third
recording there).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from casadi_design.identification.artefact_fit import calibrate_artefact  # noqa: E402
from casadi_design.identification.recordings import read_recordings  # noqa: E402
from casadi_design.optimisation.artefact_pool import artefact_pool, choose_recordings, chosen_rows  # noqa: E402
from casadi_design.problem.build import build_problem  # noqa: E402
from casadi_design.problem_file.poses import TestPoseSpec  # noqa: E402
from casadi_design.problem_file.read import read_problem  # noqa: E402

#: robot -> (candidates' placement, test poses' placement, test poses from the problem file)
CASES = {"panda_2": ("front_center", "mid_left", True), "panda_4": ("front", "right", False)}


def judged(problem, rec, rows, test) -> float:
    """Consistency (mm) at the test placement of the robot identified from the recordings ``rows``."""
    cal = calibrate_artefact(problem, rec.subset(np.sort(rows)), test, with_field=False)
    return cal.validation[0].consistency_m * 1e3


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=str(ROOT.parent / "shared" / "real_data" / "mukca"))
    parser.add_argument("--m", type=int, default=16)
    parser.add_argument("--random", type=int, default=20)
    args = parser.parse_args()
    data = Path(args.data) / "data"
    print(f"m = {args.m}: consistency (mm) at the test poses' placement after identifying each plan")
    for robot, (cand, test, shipped) in CASES.items():
        spec = read_problem(ROOT / "problems" / "panda_ball_socket.toml")
        problem = build_problem(spec)
        trec = read_recordings(problem, [str(data / robot / test)], "--validation")
        if not shipped:
            q = tuple(map(tuple, trec.Q[::3]))
            problem = build_problem(dataclasses.replace(spec, test_poses=TestPoseSpec(("x", "y", "z"), "joints",
                                                                                        joints_rad=q)))
        rec = read_recordings(problem, [str(data / robot / cand)], "--candidates")
        pool = artefact_pool(problem, rec.Q, rec.point, rec.placement)
        line = [f"{robot} from {cand} ({rec.N}), test poses at {test}:"]
        for criterion in ("test-pose", "D"):
            t0 = time.perf_counter()
            d = choose_recordings(problem, pool, criterion, args.m, problem.solver.starts_for(criterion))
            line.append(f"{criterion} {judged(problem, rec, chosen_rows(pool, d), trec):.3f} "
                        f"(max sqrt(rho) {d.scores.max_rms_error_m * 1e3:.3f}, {time.perf_counter() - t0:.0f} s)")
        rng = np.random.default_rng(0)
        random = [judged(problem, rec, rng.choice(rec.N, args.m, replace=False), trec) for _ in range(args.random)]
        line.append(f"random median {np.median(random):.3f} (quartiles {np.percentile(random, 25):.3f}, "
                    f"{np.percentile(random, 75):.3f})")
        line.append(f"all {rec.N}: {judged(problem, rec, np.arange(rec.N), trec):.3f}")
        print("\n    ".join(line))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

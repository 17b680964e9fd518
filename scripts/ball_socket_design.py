"""Which configurations to record, judged on MUKCa's real recordings: from the recordings of one
placement, m chosen by test-pose and by D (``casadi-design solve --candidates``, the same
functions), each plan identified (``identify``'s fit and model choice) and judged by the
consistency at another placement, where the test poses are (every third recording there);
beside them the median of random m-subsets. Every other placement of the robot is a test
placement in turn: plans are judged over that set, not one by one.

    python scripts/ball_socket_design.py [--data ../shared/real_data/mukca] [--robots panda_2,...] [--m 16]
        [--random 20] [--model auto]

``--model``: the model every plan is identified with (identify's ``--model``; auto: its choice,
made on each plan's own rows).

Cases: every robot of the data, its candidates at the placement identify is trained on in
scripts/ball_socket_real_data.py (panda_2's ``front_center``, panda_4's ``front``, the first
folder for the others); the summary is over every test placement and over the two Pandas'.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from casadi_design.identification.artefact_fit import ARTEFACT_MODELS, calibrate_artefact  # noqa: E402
from casadi_design.identification.recordings import read_recordings  # noqa: E402
from casadi_design.optimisation.artefact_pool import artefact_pool, choose_recordings, chosen_rows  # noqa: E402
from casadi_design.problem.build import build_problem  # noqa: E402
from casadi_design.problem_file.poses import TestPoseSpec  # noqa: E402
from casadi_design.problem_file.read import read_problem  # noqa: E402
from ball_socket_real_data import ROBOTS, robot_case  # noqa: E402

#: The Pandas whose training placements the authors' calibrated URDFs were fitted on (the
#: summary's second line: the cases scripts/ball_socket_real_data.py compares with theirs).
PANDAS = ("panda_2", "panda_4")


def judged(problem, rec, rows, test, model: str) -> float:
    """Consistency (mm) at the test placement of the robot identified (``model``) from the recordings ``rows``."""
    cal = calibrate_artefact(problem, rec.subset(np.sort(rows)), test, model=model, with_field=False)
    return cal.validation[0].consistency_m * 1e3


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=str(ROOT.parent / "shared" / "real_data" / "mukca"))
    parser.add_argument("--m", type=int, default=16)
    parser.add_argument("--random", type=int, default=20)
    parser.add_argument("--model", default="auto", choices=ARTEFACT_MODELS)
    parser.add_argument("--robots", default=",".join(ROBOTS))
    args = parser.parse_args()
    data = Path(args.data)
    print(f"m = {args.m}: consistency (mm) at the test poses' placement after identifying each plan (model {args.model})")
    print(f"{'robot':19s} {'candidates':14s} {'test poses':12s} {'test-pose':>9s} {'D':>7s} {'random median':>13s} "
          f"{'(quartiles)':>15s} {'all':>7s}")
    wins, ratios, robots = {"D": [], "random": []}, [], []
    for robot in args.robots.split(","):
        path, cand, places = robot_case(data, robot)
        spec = read_problem(path)
        base = build_problem(spec)  # the test poses' recordings are read with it
        for test in [p for p in places if p != cand]:
            trec = read_recordings(base, [str(data / "data" / robot / test)], "--validation")
            problem = build_problem(dataclasses.replace(spec, test_poses=TestPoseSpec(
                ("x", "y", "z"), "joints", joints_rad=tuple(map(tuple, trec.Q[::3])))))
            rec = read_recordings(problem, [str(data / "data" / robot / cand)], "--candidates")
            pool = artefact_pool(problem, rec.Q, rec.point, rec.placement)
            got = {c: judged(problem, rec, chosen_rows(pool, choose_recordings(
                problem, pool, c, args.m, problem.solver.starts_for(c))), trec, args.model) for c in ("test-pose", "D")}
            rng = np.random.default_rng(0)
            random = [judged(problem, rec, rng.choice(rec.N, args.m, replace=False), trec, args.model) for _ in range(args.random)]
            robots.append(robot)
            wins["D"].append(got["test-pose"] < got["D"])
            ratios.append(got["test-pose"] / got["D"])
            wins["random"].append(got["test-pose"] < np.median(random))
            print(f"{robot:19s} {cand:14s} {test:12s} {got['test-pose']:9.3f} {got['D']:7.3f} {np.median(random):13.3f} "
                  f"  ({np.percentile(random, 25):.3f}, {np.percentile(random, 75):.3f}) "
                  f"{judged(problem, rec, np.arange(rec.N), trec, args.model):7.3f}")
    for title, sel in (("every robot", [True] * len(robots)), ("panda_2 and panda_4", [r in PANDAS for r in robots])):
        sel = np.array(sel, dtype=bool)
        if sel.any():
            d, r = np.array(wins["D"])[sel], np.array(wins["random"])[sel]
            print(f"{title}: test-pose below D at {d.sum()} of {d.size} test placements (geometric mean of the ratios "
                  f"{np.exp(np.mean(np.log(np.array(ratios)[sel]))):.3f}), below the random median at {r.sum()} of {r.size}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

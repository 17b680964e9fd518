"""The two-round flow with the robot's unmodelled error as a field, on IPA's UR10 (docs/model-error.md).

    python scripts/model_error_flow.py [--m 10,20] [--first 20] [--random 5] [--pool 500] [--out DIR]

A compact test region: the 200 mm cube of the series' measured points that holds the most rows
(the nominal robot's points); 27 of its rows are the test poses, the others are held out near
it. The pool: ``--pool`` rows outside the cube. Round 1: ``--first`` random rows of the pool,
identified (``identify``: the field estimated). Round 2, for each m: ``solve --candidates POOL
--prior id1/identification.json`` with test-pose (the field) and D, test-pose with the same prior
less its field (the paper's measure), and ``--random`` random subsets of the pool; each plan's rows (their real measurements) identified with round 1's
(``identify --measurements r1 --measurements r2 --same-frame --validation NEAR``). Printed per
plan: the held-out RMS near the test region calibrated, and compensated with the field, its
max over the rows, the predicted max sqrt(rho) at the test poses (with the field), and the floor
of a geometric model: the problem's whole base set fitted to the held-out rows themselves.
Every step is the command a user runs, in this process; the files are in ``--out``.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from casadi_design.runtime.threads import fixed_blas  # noqa: E402

fixed_blas()  # one BLAS thread, as every command (before numpy loads)

import numpy as np  # noqa: E402

from casadi_design.cli import main as cli  # noqa: E402
from casadi_design.cli.identify import load_without_cell  # noqa: E402
from casadi_design.identification.calibrate import calibrate  # noqa: E402
from casadi_design.identification.fit import model_points  # noqa: E402
from casadi_design.identification.measurements import FileFormat, read_measurements  # noqa: E402
from casadi_design.runtime.interrupt import EXIT_INTERRUPTED  # noqa: E402

DATA = ROOT / "tests" / "data" / "ipa_ur10"
FORMAT = FileFormat(units="mm", columns=(("measurement_x", "meas_x"), ("measurement_y", "meas_y"),
                                         ("measurement_z", "meas_z")))
HALF_M = 0.1  # the test region: a 200 mm cube
TEST_POSES = 27
SEED = 3


def rows_csv(path: Path, lines: list[str], rows) -> Path:
    """The header and the ``rows`` (0-based data rows) of the series, as published."""
    path.write_text("\n".join([lines[0], *(lines[i + 1] for i in rows)]) + "\n")
    return path


def run(args: list[str], log: Path) -> None:
    """One command, its printout appended to ``log``."""
    with open(log, "a") as f, contextlib.redirect_stdout(f):
        print(f"$ casadi-design {' '.join(args)}")
        if cli(args) != 0:
            raise SystemExit(f"failed: casadi-design {' '.join(args)} (its printout: {log})")


def identify(out: Path, problem: Path, files: list[Path], valid: Path) -> dict:
    run(["identify", str(problem), *sum((["--measurements", str(f)] for f in files), []),
         "--same-frame", "--validation", str(valid), "--units", "mm", "--columns",
         "measurement_x=meas_x,measurement_y=meas_y,measurement_z=meas_z", "--out", str(out), "--force", "-q"],
        out.parent / "commands.log")
    return json.loads((out / "identification.json").read_text())


@dataclass(frozen=True)
class Flow:
    """The flow's files and rows: the problem of the test region, the series (``series``, its CSV
    ``lines``), round 1's CSV, the rows held out near the region and their CSV, the pool's rows
    (``rest``, written to ``pool.csv``) and the seeded generator the random plans draw from."""

    base: object
    series: object
    lines: list[str]
    problem: Path
    r1: Path
    near: np.ndarray
    near_csv: Path
    rest: np.ndarray
    rng: np.random.Generator


def set_up(out: Path, first: int, pool: int) -> Flow:
    """The test region, its problem file, the pool (``pool`` rows outside the region, less
    round 1's ``first``) and round 1's rows, written to ``out`` (module docstring)."""
    out.mkdir(parents=True, exist_ok=True)
    lines = (DATA / "measurements_random_poses_xyz.csv").read_text().splitlines()
    base = load_without_cell(str(DATA / "ipa_ur10.toml"))
    series = read_measurements(base, str(DATA / "measurements_random_poses_xyz.csv"), FORMAT)
    P = model_points(base.model, series.Q, series.F, np.zeros(base.model.L))[:, 0]
    inside = [np.all(np.abs(P - c) < HALF_M, axis=1) for c in P]
    region = np.flatnonzero(inside[int(np.argmax([r.sum() for r in inside]))])
    rng = np.random.default_rng(SEED)
    region = rng.permutation(region)
    test, near = np.sort(region[:TEST_POSES]), np.sort(region[TEST_POSES:])
    others = np.setdiff1d(np.arange(series.m), region)
    chosen = np.sort(rng.choice(others, pool, replace=False))
    r1 = np.sort(rng.choice(chosen, first, replace=False))
    rest = np.setdiff1d(chosen, r1)
    text = (DATA / "ipa_ur10.toml").read_text()
    joints = "joints_rad = [\n" + "".join("  [" + ", ".join(f"{v:.6f}" for v in series.Q[i]) + "],\n" for i in test) + "]"
    start = text.index("joints_rad = [")
    end = text.index("\n]\n", start) + 2
    text = text[:start] + joints + text[end:]
    problem = out / "ipa_region.toml"
    problem.write_text(text.replace('name = "ipa_ur10"', 'name = "ipa_ur10_region"'))
    header = ",".join(f"{j}_rad" for j in base.robot.joints)
    (out / "pool.csv").write_text("\n".join([header, *(",".join(f"{v:.9g}" for v in series.Q[i]) for i in rest)]) + "\n")
    return Flow(base, series, lines, problem, rows_csv(out / "r1.csv", lines, r1), near,
                rows_csv(out / "near.csv", lines, near), rest, rng)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--m", default="10,20", help="round 2's new experiments, comma-separated")
    p.add_argument("--first", type=int, default=20, help="round 1's random rows of the pool")
    p.add_argument("--random", type=int, default=5, help="random subsets of the pool per m")
    p.add_argument("--pool", type=int, default=500, help="rows of the pool (outside the test region)")
    p.add_argument("--out", default="out/model_error_flow", help="folder of the files")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    out = Path(args.out)
    flow = set_up(out, args.first, args.pool)
    base, series, lines, problem, r1, near, near_csv, rest, rng = (
        flow.base, flow.series, flow.lines, flow.problem, flow.r1, flow.near, flow.near_csv, flow.rest, flow.rng)
    first = args.first
    identify(out / "id1", problem, [r1], near_csv)
    record = json.loads((out / "id1" / "identification.json").read_text())
    without_field = out / "id1" / "identification_without_field.json"
    without_field.write_text(json.dumps({**record, "model_error": None}))
    print(f"test region: {TEST_POSES + len(near)} rows in a 200 mm cube ({TEST_POSES} test poses, {len(near)} held "
          f"out near it); pool {len(rest)} rows outside it; round 1: {first} random rows of the pool", flush=True)
    # the floor of a geometric model: the problem's base set fitted to the held-out rows themselves
    region_problem = load_without_cell(str(problem))
    floor_cal = calibrate(region_problem, read_measurements(region_problem, str(near_csv), FORMAT), model="identifiable",
                          threshold=1e9)
    floor = float(np.sqrt(np.mean(floor_cal.residual_rms_m ** 2)))
    print(f"geometric floor near the test region (the base set fitted to the {len(near)} rows themselves): "
          f"{floor * 1e3:.3f} mm RMS\n")
    print("| round 2 | m | held out near the region: calibrated | compensated (the field where it does) | "
          "predicted | measured / predicted | predicted max sqrt(rho) at the test poses |")
    print("|---|---|---|---|---|---|---|")
    index = {tuple(np.round(series.Q[i], 9)): i for i in rest}
    for m in (int(v) for v in args.m.split(",")):
        solved = out / f"solve_m{m}"
        run(["solve", str(problem), "--candidates", str(out / "pool.csv"), "--prior",
             str(out / "id1" / "identification.json"), "--m", str(m), "--criteria", "test-pose,D",
             "--out", str(solved), "--force", "-q"], out / "commands.log")
        plans = {c: np.genfromtxt(solved / "plans" / f"{c}_m{m}.csv", delimiter=",", names=True)
                 for c in ("test-pose", "D")}
        blind = solved.parent / f"solve_nofield_m{m}"  # the same prior without its field: the paper's measure
        run(["solve", str(problem), "--candidates", str(out / "pool.csv"), "--prior", str(without_field),
             "--m", str(m), "--criteria", "test-pose", "--out", str(blind), "--force", "-q"], out / "commands.log")
        plans["test-pose without the field"] = np.genfromtxt(blind / "plans" / f"test-pose_m{m}.csv", delimiter=",",
                                                             names=True)
        picks = {c: [index[tuple(np.round([row[f"{j}_rad"] for j in base.robot.joints], 9))] for row in np.atleast_1d(t)]
                 for c, t in plans.items()}
        picks |= {f"random {k + 1}": list(rng.choice(rest, m, replace=False)) for k in range(args.random)}
        results = {}
        for name, rows in picks.items():
            r2 = rows_csv(out / f"r2_{name.replace(' ', '')}_m{m}.csv", lines, sorted(rows))
            rec = identify(out / f"id2_{name.replace(' ', '')}_m{m}", problem, [r1, r2], near_csv)
            v, tp = rec["validation"], rec["test_poses"]
            field = v.get("field_rms_m") is not None
            results[name] = (v["calibrated_rms_m"], v["field_rms_m"] if field else v["calibrated_rms_m"],
                             v["predicted_field_rms_m"] if field else v["predicted_rms_m"],
                             max(tp["predicted_with_field_rms_m"] or tp["predicted_rms_m"]))
        randoms = [r for n, r in results.items() if n.startswith("random")]
        rows = [(n, r) for n, r in results.items() if not n.startswith("random")]
        rows.append((f"random, median of {len(randoms)}",
                     tuple(statistics.median(r[k] for r in randoms) for k in range(4))))
        for name, (cal, comp, pred, worst) in rows:
            print(f"| {name} | {m} | {cal * 1e3:.3f} | {comp * 1e3:.3f} | {pred * 1e3:.3f} | {comp / pred:.2f} | "
                  f"{worst * 1e3:.3f} |", flush=True)
    print(f"\nmm; {time.perf_counter() - t0:.0f} s; files in {out}")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:  # the rows printed are the finished plans
        print("interrupted", file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)

"""The speed of the flow with the robot's error as a field, on IPA's UR10 (docs/benchmarks.md).

    python scripts/field_benchmark.py [--out DIR] [--skip round2,identify,nlp]

Prints, each the command a user runs, in this process, timed after the imports:

- **round 2**: ``solve --candidates pool.csv --prior id1/identification.json --m 20 --criteria
  test-pose,D`` of ``scripts/model_error_flow.py`` (round 1: 20 random rows; a pool of 480 real
  postures): the command's wall, each design's, the exchange's passes and swaps and the
  test-pose plan's predicted max sqrt(rho) at the test poses (with the field);
- **identify**: ``identify`` with the field on 300 rows of the pool, its wall;
- **NLP with the field**: the free design ``solve --prior id100/identification.json --m 10
  --criteria test-pose`` (a first round of 100 rows of the pool), its wall and the start of the
  NLP with the field's.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from model_error_flow import identify, rows_csv, run, set_up  # noqa: E402 (fixes one BLAS thread first)

from casadi_design.optimisation import pool  # noqa: E402

NLP_WALL: list[float] = []


def timed_field_nlp(problem, design):
    """:func:`~casadi_design.optimisation.pool.field_nlp`, its wall kept in :data:`NLP_WALL`."""
    t0 = time.perf_counter()
    try:
        return FIELD_NLP(problem, design)
    finally:
        NLP_WALL.append(time.perf_counter() - t0)


FIELD_NLP, pool.field_nlp = pool.field_nlp, timed_field_nlp


def timed(f) -> float:
    t0 = time.perf_counter()
    f()
    return time.perf_counter() - t0


def designs(folder: Path) -> list[dict]:
    return json.loads((folder / "results.json").read_text())["designs"]


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="out/field_benchmark", help="folder of the files")
    p.add_argument("--skip", default="", help="parts not run: round2, identify, nlp (comma-separated)")
    args = p.parse_args(argv)
    out, skip = Path(args.out), set(filter(None, args.skip.split(",")))
    flow = set_up(out, 20, 500)
    log = out / "commands.log"
    identify(out / "id1", flow.problem, [flow.r1], flow.near_csv)
    print("| step | wall (s) | detail |\n|---|---|---|")
    if "round2" not in skip:
        solved = out / "round2"
        wall = timed(lambda: run(["solve", str(flow.problem), "--candidates", str(out / "pool.csv"), "--prior",
                                  str(out / "id1" / "identification.json"), "--m", "20", "--criteria", "test-pose,D",
                                  "--out", str(solved), "--force", "-q"], log))
        for d in designs(solved):
            ex = d["solver"]["exchange"]
            print(f"| round 2, {d['criterion']} (m = 20) | {d['solver']['wall_s']:.1f} | {ex['passes']} passes, "
                  f"{ex['swaps']} swaps; max sqrt(rho) with the field {d['max_rms_error_m'] * 1e3:.4f} mm |")
        print(f"| round 2, the command | {wall:.1f} | both designs, results, plots and viewer |", flush=True)
    rows = rows_csv(out / "r300.csv", flow.lines, sorted(flow.rng.choice(flow.rest, 300, replace=False)))
    r100 = rows_csv(out / "r100.csv", flow.lines, sorted(flow.rng.choice(flow.rest, 100, replace=False)))
    if "identify" not in skip:
        wall = timed(lambda: identify(out / "id300", flow.problem, [rows], flow.near_csv))
        field = json.loads((out / "id300" / "identification.json").read_text())["model_error"]
        print(f"| identify, the field on 300 rows | {wall:.1f} | restricted log-likelihood "
              f"{field['restricted_log_likelihood']:.2f} |", flush=True)
    if "nlp" not in skip:
        identify(out / "id100", flow.problem, [r100], flow.near_csv)
        solved = out / "free"
        wall = timed(lambda: run(["solve", str(flow.problem), "--prior", str(out / "id100" / "identification.json"),
                                  "--m", "10", "--criteria", "test-pose", "--out", str(solved), "--force", "-q"], log))
        d = designs(solved)[0]
        nlp = [s for s in d["solver"]["per_start"] if s["origin"].startswith("NLP with the field")]
        print(f"| free design with the field (100 held, m = 10) | {wall:.1f} | max sqrt(rho) "
              f"{d['max_rms_error_m'] * 1e3:.4f} mm; NLP with the field: "
              + (f"{nlp[0]['status']}, {nlp[0]['iterations']} iterations, {sum(NLP_WALL):.1f} s |" if nlp
                 else "not run |"), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

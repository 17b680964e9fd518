"""Speed and memory of the design NLPs: one table, and benchmark.json.

    python scripts/benchmark.py [--cases paper,ur10,ur10-50,abb] [--criteria test-pose,D] [--starts N]
                                [--compare-with DIR | --compare-vm] [--studies] [--out benchmark.json]

Each (case, criterion, m) runs in a fresh process (so its peak memory is its own): build the
design solver, then the seeded starts of `casadi-design solve` one after the other. Printed per
design: build time (s), time per start (s), IPOPT iterations, ms per iteration, peak memory
(MB, the child's maximum resident set), best max error (mm), best criterion value and the
number of starts that reach it (the registry's same-optimum rule), and for a cell the IPOPT
runs per start and the capsule rows the last run held (of all rows of the plan); with a
comparison, the old/new ratios and whether every start's value and iterations are the same.
``--studies`` also times each case's whole study as shipped. Case ``ur10-50``: the UR10
with a grid of 50 drilling points as test poses, m = 20, 16 starts.

``--compare-with DIR`` runs the same designs with the package found in DIR (another checkout,
e.g. a worktree of an older commit) and adds the old/new ratios of time per start and memory;
``--compare-vm`` compares instead with this checkout in CasADi's virtual machine
(``CASADI_DESIGN_COMPILE=0``: no compiled functions, :mod:`casadi_design.robot.compiled`). The first
line says whether the functions are compiled and where their cache is; build times include
compiling what the cache does not hold yet. Figures are for the machine at hand; compare
ratios, not absolutes.

Choosing from pools (``--candidates``)::

    python scripts/benchmark.py --pools ipa-500,ipa-2773,ur10-12000 [--compare-with DIR --old-pools ipa-500]

runs ``solve CASE --candidates POOL --criteria test-pose,D --jobs 1`` on each pool of
:data:`POOLS` in a fresh process and prints each design's time, gap to the pool's bound, score
and exchanges, the command's wall time and peak memory; with ``--compare-with``, the same
command with the other checkout on the pools of ``--old-pools``.

Plan quality over the benchmark set (the rule of issue 47)::

    python scripts/benchmark.py --run-set DIR                     # the set's runs, in DIR/<run>
    python scripts/benchmark.py --quality BASELINE_DIR --candidate DIR

The set (:data:`QUALITY_SET`): both studies as shipped, the UR10 sweep m = 9..20 of test-pose
and D, and the paper's Table 4. For each design, ``r`` = new / old on its own criterion, so that
``r > 1`` is worse: the max error for test-pose and I, tr M^-1 for A, 1 / s_min for E, the
condition number, tr M for T (inverted), ``exp((log det M_old - log det M_new) / L)`` for D.
Accepted when the geometric mean of r is at most 1 and no r exceeds ``R_MAX``, the fixed
targets hold (:data:`TARGETS_MM`, Table 4 to its printed digits) and every approximate design's
certificate was checked and is within ``CERTIFICATE_GAP`` of its relaxation.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: case -> (problem file, m values, starts, test poses: None for the file's own, or
#: (x values, y values, z), m, of a grid of drilling points)
CASES = {
    "paper": ("problems/paper_planar_2r.toml", (1, 5), 4, None),
    "ur10": ("problems/ur10_drilling.toml", (9, 12), 4, None),
    "ur10-50": ("problems/ur10_drilling.toml", (20,), 16,
                (tuple(0.55 + 0.05 * i for i in range(10)), (-0.3, -0.15, 0.0, 0.15, 0.3), 0.1)),
    "abb": ("problems/abb_irb6640_machining.toml", (6, 8), 4, None),
}


def run_one(problem_file: str, criterion: str, m: int, starts: int, grid: tuple | None) -> dict:
    """In the child: build the design solver and run the seeded starts; plain figures."""
    import inspect
    import tomllib

    build_problem = module("casadi_design.problem.build").build_problem
    CRITERIA = module("casadi_design.measures.criteria").CRITERIA
    parse_problem = module("casadi_design.problem_file.read").parse_problem
    solve = module("casadi_design.optimisation.solve")
    random_plan = module("casadi_design.plan.sampling").random_plan
    start_rng = solve.start_rng
    if "B0" in inspect.signature(solve.make_design_solver).parameters:  # a checkout that passed B0
        B0 = module("casadi_design.optimisation.nlp").B0_at_test_poses

        def make_design_solver(problem, criterion, m):
            return solve.make_design_solver(problem, criterion, m, B0(problem))

        def solve_start(problem, solver, Q0, F0):
            return solve.solve_start(problem, solver, solver.B0, Q0, F0)
    else:
        make_design_solver, solve_start = solve.make_design_solver, solve.solve_start

    raw = tomllib.loads(Path(problem_file).read_text())
    if grid is not None:
        xs, ys, z = grid
        raw["test_poses"]["path"] = {"kind": "points", "points_m": [[x, y, z] for x in xs for y in ys]}
    problem = build_problem(parse_problem(raw, problem_file))
    rng = start_rng(problem.solver.seed, criterion, m)
    plans = [random_plan(problem, m, rng) for _ in range(starts)]
    t0 = time.perf_counter()
    solver = make_design_solver(problem, criterion, m)
    build_s = time.perf_counter() - t0
    records, times = [], []
    for Q0, F0 in plans:
        t0 = time.perf_counter()
        rec, _, _, _ = solve_start(problem, solver, Q0, F0)
        times.append(time.perf_counter() - t0)
        records.append(rec)
    ok = [r for r in records if r.converged] or records
    sense = {"min": 1.0, "max": -1.0}
    best = min(ok, key=lambda r: sense[CRITERIA[criterion].sense] * r.value)
    iterations = sum(r.iterations for r in records)
    return {"build_s": build_s, "start_s": times, "iterations": [r.iterations for r in records],
            "ms_per_iteration": 1e3 * sum(times) / max(iterations, 1),
            "converged": sum(r.converged for r in records), "best_value": best.value,
            "at_best": sum(r.converged and CRITERIA[criterion].same_optimum(r.value, best.value)
                           for r in records),
            "best_max_error_mm": best.max_rms_error_m * 1e3,
            "values": [r.value for r in records],
            # a checkout from before the rows where they can bind: one run holding every row
            "runs": [getattr(r, "runs", 1) for r in records],
            "rows_held": [getattr(r, "rows_held", None) for r in records],
            "rows": m * _capsule_rows(problem),
            "peak_MB": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def _capsule_rows(problem) -> int:
    """Capsule rows of one experiment (0 without a cell); a checkout from before
    ``problem.rules`` (--compare-with) has ``plan.rules.pose_constraints``."""
    pose = (problem.rules.pose if hasattr(problem, "rules") else
            module("casadi_design.plan.rules").pose_constraints(problem))
    collision = getattr(pose, "collision", None)
    return 0 if collision is None else len(collision.inputs)


def module(layered: str):
    """``casadi_design.<room>.<name>`` of the checkout imported, in the layout that checkout has
    (--compare-with): today's rooms, the older one where the robot, cell, problem file and
    calibration model all lived in ``model/`` (``problem_file.read`` was ``model.problem``), or
    the flat ``casadi_design.<name>``. Told by its folders, since an editable install would
    otherwise resolve today's names in this checkout."""
    import importlib

    import casadi_design

    root = Path(casadi_design.__file__).parent
    name = layered.rsplit(".", 1)[1]
    if not (root / "problem_file").is_dir() and layered.split(".")[1] in ("problem", "problem_file", "robot", "cell",
                                                                          "calibration"):
        name = "problem" if layered.endswith("problem_file.read") else name
        layered = f"casadi_design.model.{name}" if (root / "model").is_dir() else f"casadi_design.{name}"
    elif not (root / "model").is_dir() and not (root / "problem_file").is_dir():
        layered = "casadi_design." + name
    return importlib.import_module(layered)


def study(problem_file: str, jobs: int) -> dict:
    """Wall time of the whole case study, ``casadi-design solve CASE --jobs N`` as shipped, and
    from its results.json the time of each approximate design and of each design (s; on
    workers these overlap: the study is one pipeline)."""
    import tempfile

    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "casadi_design", "solve", str(ROOT / problem_file),
                               "--jobs", str(jobs), "--out", out], capture_output=True, text=True)
        wall = time.perf_counter() - t0
        results = Path(out) / "results.json"
        record = json.loads(results.read_text()) if results.exists() else {}
    return {"wall_s": wall, "returncode": proc.returncode, "stdout": proc.stdout,
            "approximate_wall_s": {a["criterion"]: a["wall_s"] for a in record.get("approximate_designs", [])},
            "design_wall_s": {f"{d['criterion']} m={d['m']}": d["solver"]["wall_s"] for d in record.get("designs", [])}}


def child(package_dir: Path, problem_file: str, criterion: str, m: int, starts: int,
          grid: tuple | None, env: dict | None = None) -> dict:
    """Run one design in a fresh process with the package of ``package_dir`` (its own peak
    memory), with the environment variables ``env`` besides this one's."""
    env = {**os.environ, "OMP_NUM_THREADS": "1", **(env or {})}
    # the package first on sys.path, before an installed (editable) copy; this script's helpers after
    code = ("import json, sys; sys.path[:0] = [%r, %r]; from benchmark import run_one; "
            "print(json.dumps(run_one(%r, %r, %d, %d, %r)))"
            % (str(package_dir), str(ROOT / "scripts"), str(ROOT / problem_file), criterion, m, starts,
               grid))
    proc = subprocess.run([sys.executable, "-c", code], cwd=package_dir, env=env, capture_output=True, text=True)
    if proc.returncode:
        return {"error": (proc.stderr.strip().splitlines() or ["failed"])[-1]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


#: The benchmark set: run name -> the command's arguments (its output folder appended).
QUALITY_SET = {
    "paper": ["solve", "problems/paper_planar_2r.toml"],
    "ur10": ["solve", "problems/ur10_drilling.toml"],
    "abb": ["solve", "problems/abb_irb6640_machining.toml"],
    "sweep": ["sweep", "problems/ur10_drilling.toml", "--m", "9:20", "--criteria", "test-pose,D"],
}
#: Largest r of one design, and the fixed targets: (run, criterion, m) -> largest max error (mm).
R_MAX = 1.02
TARGETS_MM = {("ur10", "test-pose", 9): 0.0238, ("ur10", "test-pose", 12): 0.0194,
              ("abb", "test-pose", 6): 0.0397, ("abb", "test-pose", 8): 0.0205}
#: The paper's Table 4 (mm): (criterion, m) -> value, held within ``TABLE_4_TOL_MM`` (its last
#: printed digit, as tests/optimisation/test_design.py holds it).
TABLE_4_MM = {("test-pose", 1): 0.137, ("test-pose", 5): 0.055, ("D", 1): 0.170, ("D", 5): 0.069,
              ("E", 1): 0.240}
TABLE_4_TOL_MM = 0.002
#: Largest relative distance of a certificate from its relaxation.
CERTIFICATE_GAP = 0.005


def run_set(out: Path) -> None:
    """Run the benchmark set as shipped, each run in ``out/<run>`` (its time printed)."""
    out.mkdir(parents=True, exist_ok=True)
    for name, command in QUALITY_SET.items():
        t0 = time.perf_counter()
        proc = subprocess.run([sys.executable, "-m", "casadi_design", *command, "--out", str(out / name),
                               "--force", "--quiet"], cwd=ROOT)
        print(f"{name}: {time.perf_counter() - t0:.1f} s" + (f", exit {proc.returncode}" if proc.returncode else ""))


def _designs(folder: Path) -> tuple[dict, dict, int]:
    """The designs of a run folder ``{(criterion, m): record}``, its approximate designs and L."""
    path = folder / "results.json" if (folder / "results.json").exists() else folder / "sweep.json"
    record = json.loads(path.read_text())
    return ({(d["criterion"], d["m"]): d for d in record["designs"]},
            {a["criterion"]: a for a in record.get("approximate_designs", [])},
            len(record["calibration"]["parameters"]))


def ratio(criterion: str, old: dict, new: dict, L: int) -> float:
    """``r`` of one design (module docstring): new over old on its own criterion, > 1 worse."""
    so, sn = old["scores"], new["scores"]
    if criterion in ("test-pose", "I"):
        return new["max_rms_error_m"] / old["max_rms_error_m"]
    if criterion == "D":
        return float(np.exp((so["log_det_M"] - sn["log_det_M"]) / L))
    if criterion == "A":
        return sn["trace_M_inv"] / so["trace_M_inv"]
    if criterion == "E":
        return so["s_min"] / sn["s_min"]
    if criterion == "condition":
        return sn["condition"] / so["condition"]
    if criterion == "T":
        return so["trace_M"] / sn["trace_M"]
    raise ValueError(f"no quality ratio for criterion {criterion}")


def quality(base: Path, candidate: Path) -> bool:
    """Print the table of r over the benchmark set, the targets and the verdict."""
    rows, problems = [], []
    for name in QUALITY_SET:
        if not ((base / name).is_dir() and (candidate / name).is_dir()):
            problems.append(f"{name}: not run in both folders (--run-set runs the whole set)")
            continue
        old, _, _ = _designs(base / name)
        new, approx, L = _designs(candidate / name)
        for key in sorted(set(old) & set(new), key=lambda k: (k[1], k[0])):
            rows.append((name, *key, ratio(key[0], old[key], new[key], L)))
        missing = sorted(set(old) ^ set(new))
        if missing:
            problems.append(f"{name}: designs in only one of the two runs: {missing}")
        for (run, c, m), limit in TARGETS_MM.items():
            if run == name and (c, m) in new and new[c, m]["max_rms_error_m"] * 1e3 > limit:
                problems.append(f"{name} {c} m = {m}: {new[c, m]['max_rms_error_m'] * 1e3:.4f} mm > {limit} mm")
        if name == "paper":
            for (c, m), printed in TABLE_4_MM.items():
                got = new[c, m]["max_rms_error_m"] * 1e3
                if abs(got - printed) > TABLE_4_TOL_MM:
                    problems.append(f"paper {c} m = {m}: {got:.4f} mm is not Table 4's {printed} "
                                    f"within {TABLE_4_TOL_MM} mm")
        for c, a in approx.items():
            gap = abs(a["certified"] - a["relaxation"]) / abs(a["relaxation"])
            if not a.get("independent_checks") or gap > CERTIFICATE_GAP:
                problems.append(f"{name} {c}: certificate {a['certified']:.6g} is {gap * 100:.2f} % from the "
                                f"relaxation {a['relaxation']:.6g} ({a.get('independent_checks')} checks)")
    print(f"{'run':<7}{'criterion':<11}{'m':>4}{'r':>10}")
    for name, c, m, r in rows:
        print(f"{name:<7}{c:<11}{m:>4}{r:>10.4f}" + ("  > R_MAX" if r > R_MAX else ""))
    r = np.array([row[3] for row in rows])
    gmean = float(np.exp(np.mean(np.log(r))))
    print(f"{len(r)} designs: geometric mean of r {gmean:.4f}, largest {r.max():.4f} (accepted: <= 1 and <= {R_MAX})")
    problems += [f"geometric mean of r {gmean:.4f} > 1"] if gmean > 1 + 1e-12 else []
    problems += [f"largest r {r.max():.4f} > {R_MAX}"] if r.max() > R_MAX else []
    print("\n".join(problems) if problems else "all fixed targets and certificates hold")
    print("verdict:", "accepted" if not problems else "refused")
    return not problems


#: Pools of ``--pools``: name -> (problem file, where the postures come from, size, --m values
#: or None for the case's own): "ipa", a seeded subset of IPA's series (tests/data/ipa_ur10,
#: all of it at 2773); "cell", random feasible experiments of the case's cell (seeded).
POOLS = {
    "ipa-500": ("tests/data/ipa_ur10/ipa_ur10.toml", "ipa", 500, "20,30"),
    "ipa-2773": ("tests/data/ipa_ur10/ipa_ur10.toml", "ipa", 2773, "30"),
    "ur10-12000": ("problems/ur10_drilling.toml", "cell", 12000, None),
}
IPA_SERIES = "tests/data/ipa_ur10/measurements_random_poses_xyz.csv"


def pool_file(name: str, folder: Path) -> Path:
    """The pool of ``name`` (:data:`POOLS`) written as a CSV in ``folder``."""
    problem_file, source, size, _ = POOLS[name]
    path = folder / f"{name}.csv"
    if source == "ipa":
        head, *rows = (ROOT / IPA_SERIES).read_text().splitlines()
        keep = np.sort(np.random.default_rng(0).choice(len(rows), size=size, replace=False))
        path.write_text("\n".join([head] + [rows[i] for i in keep]) + "\n")
    else:
        sys.path.insert(0, str(ROOT))
        from casadi_design.plan.sampling import random_plan
        from casadi_design.problem.build import load_problem
        from casadi_design.records.export import csv_text, plan_table

        problem = load_problem(ROOT / problem_file)
        path.write_text(csv_text(*plan_table(problem, *random_plan(problem, size, np.random.default_rng(0)))))
    return path


def pool_run(package_dir: Path, name: str, pool: Path, out: Path) -> dict:
    """``solve CASE --candidates POOL --criteria test-pose,D --jobs 1`` with the package of
    ``package_dir`` in a fresh process: its wall time (s), peak memory (MB) and each design's
    time, score, max error and gap to the pool's bound from its results.json."""
    problem_file, _, _, ms = POOLS[name]
    argv = ["solve", str(ROOT / problem_file), "--candidates", str(pool), "--criteria", "test-pose,D",
            "--jobs", "1", "--out", str(out), "--force", "--quiet"] + (["--m", ms] if ms else [])
    code = ("import json, resource, sys; sys.path[:0] = [%r]; from casadi_design.cli import main; rc = main(%r); "
            "print(json.dumps({'rc': rc, 'peak_MB': resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))"
            % (str(package_dir), argv))
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", code], cwd=package_dir, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode:
        return {"error": (proc.stderr.strip().splitlines() or ["failed"])[-1]}
    record = json.loads((out / "results.json").read_text())
    return {"wall_s": wall, **json.loads(proc.stdout.strip().splitlines()[-1]),
            "designs": {f"{d['criterion']} {d['m']}": {
                "wall_s": d["solver"]["wall_s"], "value": d["scores"][CRITERIA_SCORE[d["criterion"]]],
                "max_error_mm": d["max_rms_error_m"] * 1e3,
                "gap_percent": (d.get("bound") or {}).get("gap_percent"),
                "exchange": d["solver"].get("exchange")} for d in record["designs"]}}


#: The score key of the criteria the pool runs compare.
CRITERIA_SCORE = {"test-pose": "max_rms_error_m", "D": "log_det_M"}


def pools(names: list[str], old_dir: Path | None, old_names: list[str]) -> dict:
    """The pool runs of ``names`` (and with ``old_dir``, those of ``old_names`` with that
    checkout too): one line per design."""
    import tempfile

    runs = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        head = (f"{'pool':<12}{'k':>6}{'criterion':>11}{'m':>4}{'design s':>10}{'gap %':>8}{'max mm':>9}"
                f"{'value':>12}{'exchanges/passes/swaps':>24}" + (f"{'old s':>9}{'old gap %':>10}{'old value':>12}"))
        print(head)
        print("-" * len(head))
        for name in names:
            pool = pool_file(name, tmp)
            new = pool_run(ROOT, name, pool, tmp / f"{name}-new")
            old = pool_run(old_dir, name, pool, tmp / f"{name}-old") if old_dir and name in old_names else None
            runs[name] = {"new": new, "old": old}
            if "error" in new:
                print(f"{name:<12} failed: {new['error']}")
                continue
            for key, d in new["designs"].items():
                criterion, m = key.split()
                ex = d["exchange"] or {}
                line = (f"{name:<12}{POOLS[name][2]:>6}{criterion:>11}{m:>4}{d['wall_s']:>10.1f}"
                        f"{d['gap_percent'] if d['gap_percent'] is not None else float('nan'):>8.2f}"
                        f"{d['max_error_mm']:>9.4f}{d['value']:>12.6g}"
                        f"{'/'.join(str(ex.get(k, '-')) for k in ('starts', 'passes', 'swaps')):>24}")
                if old and "error" not in old and key in old["designs"]:
                    o = old["designs"][key]
                    line += f"{o['wall_s']:>9.1f}{o['gap_percent'] or float('nan'):>10.2f}{o['value']:>12.6g}"
                print(line, flush=True)
            print(f"{name}: the command {new['wall_s']:.1f} s wall, peak {new['peak_MB']:.0f} MB"
                  + (f"; with the old checkout {old['wall_s']:.1f} s, peak {old['peak_MB']:.0f} MB"
                     if old and "error" not in old else ""), flush=True)
    return runs


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="paper,ur10,abb", help=f"among {', '.join(CASES)}")
    parser.add_argument("--criteria", default="test-pose,D,A,E,condition")
    parser.add_argument("--m", help="numbers of experiments, e.g. 9,12 (default: per case)")
    parser.add_argument("--starts", type=int, help="seeded starts per design (default: per case)")
    parser.add_argument("--compare-with", metavar="DIR", help="another checkout to compare with")
    parser.add_argument("--compare-vm", action="store_true",
                        help="compare with this checkout in CasADi's virtual machine (nothing compiled)")
    parser.add_argument("--out", default="benchmark.json", help="JSON file of all figures")
    parser.add_argument("--run-set", metavar="DIR", help="run the benchmark set as shipped into DIR and stop")
    parser.add_argument("--quality", metavar="BASELINE_DIR",
                        help="judge the runs of --candidate DIR against those of BASELINE_DIR (--run-set folders)")
    parser.add_argument("--candidate", metavar="DIR", help="the runs judged by --quality")
    parser.add_argument("--studies", action="store_true",
                        help="also time each case's whole study, `casadi-design solve CASE --jobs 2`")
    parser.add_argument("--pools", metavar="NAMES",
                        help=f"time `solve --candidates` on pools instead, among {', '.join(POOLS)}")
    parser.add_argument("--old-pools", metavar="NAMES", default="ipa-500",
                        help="the pools also run with the --compare-with checkout (default ipa-500)")
    args = parser.parse_args(argv)
    if args.pools:
        runs = pools(args.pools.split(","), Path(args.compare_with) if args.compare_with else None,
                     args.old_pools.split(","))
        Path(args.out).write_text(json.dumps({"units": {"wall_s": "s", "peak_MB": "MB", "max_error_mm": "mm"},
                                              "pools": runs}, indent=2) + "\n")
        print(f"wrote {args.out}")
        return 0
    if args.run_set:
        run_set(Path(args.run_set))
        return 0
    if args.quality:
        if not args.candidate:
            parser.error("--quality needs --candidate DIR (a --run-set folder of the change)")
        return 0 if quality(Path(args.quality), Path(args.candidate)) else 1
    if args.compare_with and args.compare_vm:
        parser.error("--compare-with and --compare-vm: choose one")
    sys.path.insert(0, str(ROOT))
    from casadi_design.robot import compiled

    print(f"compiled CasADi functions: on, cache {compiled.cache_dir()}" if compiled.enabled() else
          "compiled CasADi functions: off (CASADI_DESIGN_COMPILE=0 or no C compiler): the virtual machine")
    compare = args.compare_with or args.compare_vm
    old_dir = Path(args.compare_with) if args.compare_with else ROOT
    old_env = {"CASADI_DESIGN_COMPILE": "0"} if args.compare_vm else None
    rows = []
    head = (f"{'case':<8}{'criterion':<11}{'m':>3}{'build s':>9}{'s/start':>9}{'iter':>7}"
            f"{'ms/iter':>9}{'peak MB':>9}{'best mm':>9}{'best value':>13}{'at best':>8}{'runs':>6}"
            f"{'rows held':>11}" + (f"{'old/new time':>14}{'old/new MB':>12}{'starts':>8}" if compare else ""))
    print(head)
    print("-" * len(head))
    for case in args.cases.split(","):
        problem_file, ms, starts, grid = CASES[case]
        starts = args.starts or starts
        for m in ([int(v) for v in args.m.split(",")] if args.m else ms):
            for criterion in args.criteria.split(","):
                new = child(ROOT, problem_file, criterion, m, starts, grid)
                old = child(old_dir, problem_file, criterion, m, starts, grid, old_env) if compare else None
                rows.append({"case": case, "criterion": criterion, "m": m, "starts": starts,
                             "new": new, "old": old})
                if "error" in new:
                    print(f"{case:<8}{criterion:<11}{m:>3}  failed: {new['error']}")
                    continue
                per_start = sum(new["start_s"]) / len(new["start_s"])
                line = (f"{case:<8}{criterion:<11}{m:>3}{new['build_s']:>9.2f}{per_start:>9.2f}"
                        f"{sum(new['iterations']):>7d}{new['ms_per_iteration']:>9.2f}{new['peak_MB']:>9.0f}"
                        f"{new['best_max_error_mm']:>9.4f}{new['best_value']:>13.7g}{new['at_best']:>8d}"
                        f"{sum(new['runs']) / len(new['runs']):>6.1f}"
                        + (f"{sum(new['rows_held']) / len(new['rows_held']):>6.0f}/{new['rows']:<4d}" if new["rows"]
                           else f"{'-':>11}"))
                if old and "error" not in old:
                    old_per_start = (old["build_s"] + sum(old["start_s"])) / len(old["start_s"])
                    new_per_start = (new["build_s"] + sum(new["start_s"])) / len(new["start_s"])
                    same = old["values"] == new["values"] and old["iterations"] == new["iterations"]
                    line += (f"{old_per_start / new_per_start:>14.1f}{old['peak_MB'] / new['peak_MB']:>12.1f}"
                             f"{'same' if same else 'differ':>8}")
                elif old:
                    line += f"{'old failed':>14}"
                print(line, flush=True)
    studies = {}
    if args.studies:
        for case in args.cases.split(","):
            studies[case] = study(CASES[case][0], jobs=2)
            st = studies[case]
            print(f"study {case}: casadi-design solve {CASES[case][0]} --jobs 2: "
                  f"{st['wall_s']:.0f} s wall (exit {st['returncode']}); approximate designs "
                  + ", ".join(f"{c} {t:.1f} s" for c, t in st["approximate_wall_s"].items()), flush=True)
    Path(args.out).write_text(json.dumps({"units": {"build_s": "s", "start_s": "s", "peak_MB": "MB",
                                                    "best_max_error_mm": "mm", "wall_s": "s"},
                                          "rows": rows, "studies": studies}, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""identify's defaults on the real files shipped in tests/data: the table of docs/identify.md.

    python scripts/real_data.py [--rows 20,40,80] [--seeds 5] [--validation FILE ...]

IPA's UR10 (laser tracker, Series C): ``identify`` with its defaults on N random rows of the
series (seeds 0, 1, ...), judged on the other rows of the series; with ``--validation`` on
those files instead (another series of the same robot, in its own tracker frame or not: the
errors that count are printed). FIGAROH's TIAGo (motion capture): its frozen protocol, 37
training postures and 62 held-out. Printed per case (medians over the seeds, mm, RMS over the
rows): training, cross-validated, held out (calibrated and registration only), predicted, their
ratio, the rows excluded, the models chosen.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from casadi_design.runtime.threads import fixed_blas  # noqa: E402

fixed_blas()  # one BLAS thread, as every command (before numpy loads)

import numpy as np  # noqa: E402

from casadi_design.cli.identify import load_without_cell  # noqa: E402
from casadi_design.identification.calibrate import calibrate  # noqa: E402
from casadi_design.identification.measurements import FileFormat, read_measurements  # noqa: E402
from casadi_design.runtime.interrupt import EXIT_INTERRUPTED  # noqa: E402

IPA = ROOT / "tests" / "data" / "ipa_ur10"
TIAGO = ROOT / "tests" / "data" / "tiago_mocap"
IPA_FORMAT = FileFormat(units="mm", columns=(("measurement_x", "meas_x"), ("measurement_y", "meas_y"),
                                             ("measurement_z", "meas_z")))


def figures(cal) -> dict:
    """The figures of one identification (m, and the rows excluded)."""
    v = cal.validation
    nominal, registration, calibrated = v.counted
    chosen = next(c for c in cal.candidates if c.name == cal.model)
    return {"training": float(np.sqrt(np.mean(cal.residual_rms_m[cal.fit.used] ** 2))), "cv": chosen.cv_rms_m,
            "held": v.rms(calibrated), "registration": v.rms(registration), "predicted": v.rms("predicted"),
            "excluded": len(cal.outliers), "rows": cal.measurements.m, "model": cal.model, "moved": v.moved}


def line(label: str, runs: list[dict]) -> str:
    med = {k: statistics.median(r[k] for r in runs) for k in ("training", "cv", "held", "registration", "predicted")}
    ratio = statistics.median(r["predicted"] / r["held"] for r in runs)
    excluded = statistics.median(r["excluded"] for r in runs)
    models = ", ".join(sorted({r["model"] for r in runs}))
    moved = " (tracker moved: re-registered)" if any(r["moved"] for r in runs) else ""
    return (f"| {label}{moved} | {med['training'] * 1e3:.3f} | {med['cv'] * 1e3:.3f} | {med['held'] * 1e3:.3f} | "
            f"{med['registration'] * 1e3:.3f} | {med['predicted'] * 1e3:.3f} | {ratio:.2f} | "
            f"{excluded:g} of {runs[0]['rows']} | {models} |")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rows", default="20,40,80", help="training rows of IPA's series, comma-separated")
    p.add_argument("--seeds", type=int, default=5, help="random subsets per number of rows")
    p.add_argument("--validation", nargs="*", default=[], metavar="FILE",
                   help="other series of the UR10 (IPA's format) to judge on, instead of the series' other rows")
    args = p.parse_args(argv)
    t0 = time.perf_counter()
    print("| case | training | cross-validated | held out | registration only, held out | predicted | "
          "predicted / held out | rows excluded | models chosen |")
    print("|---|---|---|---|---|---|---|---|---|")
    problem = load_without_cell(str(IPA / "ipa_ur10.toml"))
    series = read_measurements(problem, str(IPA / "measurements_random_poses_xyz.csv"), IPA_FORMAT)
    others = [read_measurements(problem, path, IPA_FORMAT) for path in args.validation]
    for n in (int(k) for k in args.rows.split(",")):
        runs = {}
        for seed in range(args.seeds):
            rows = np.random.default_rng(seed).permutation(series.m)
            training = series.subset(np.sort(rows[:n]))
            for valid in others or [series.subset(np.sort(rows[n:]))]:
                label = f"IPA UR10, {n} random rows" + (f", on {Path(valid.path).name}" if others else "")
                runs.setdefault(label, []).append(figures(calibrate(problem, training, validation=valid)))
        for label, r in runs.items():
            print(line(label, r), flush=True)
    tiago = load_without_cell(str(TIAGO / "tiago_mocap.toml"))
    cal = calibrate(tiago, read_measurements(tiago, str(TIAGO / "qualisys_2021-11-30_static_postures.csv")),
                    validation=read_measurements(tiago, str(TIAGO / "qualisys_2021-11-26_static_postures.csv")))
    print(line("TIAGo, FIGAROH's protocol", [figures(cal)]))
    print(f"\nmm, RMS over the rows (medians over {args.seeds} seeds for IPA); {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except KeyboardInterrupt:  # the rows printed are the finished cases
        print("interrupted", file=sys.stderr)
        sys.exit(EXIT_INTERRUPTED)

"""A virtual calibration for people and files: the text report and ``validation.json``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np

from ..records.files import write_atomic
from .statistics import CONFIDENCE, rankings
from .validation import PlanValidation, Validation


def plan_record(pv: PlanValidation) -> dict:
    """One plan's validation as plain data (m)."""
    j = int(np.argmax(pv.empirical_rms_m))
    return {
        "criterion": pv.plan.criterion,
        "m": pv.plan.m,
        "predicted_rms_m": pv.predicted_rms_m.tolist(),
        "empirical_rms_m": pv.empirical_rms_m.tolist(),
        "ci_low_m": pv.ci_low_m.tolist(),
        "ci_high_m": pv.ci_high_m.tolist(),
        "dof": pv.dof.tolist(),
        "max": {"predicted_m": float(np.max(pv.predicted_rms_m)),
                "empirical_m": float(pv.empirical_rms_m[j]), "node": j,
                "ci_low_m": float(pv.ci_low_m[j]), "ci_high_m": float(pv.ci_high_m[j]),
                "ratio": pv.max_ratio},
        "worst_relative_error": pv.worst_relative_error,
        "coverage": pv.coverage,
        "identification": pv.identification.as_dict(),
        "compensation_residual_m": pv.compensation_residual_m,
        "compensation_failed": pv.compensation_failed,
        "wall_s": pv.wall_s,
    }


def validation_record(validation: Validation, study: list[tuple[float, Validation]] = ()) -> dict:
    """The whole ``validation.json`` record (SI units); ``study`` from :func:`linearisation_study`."""
    problem = validation.problem
    return {
        "problem": problem.name,
        "problem_file": problem.path,
        "plans_from": validation.source,
        "case": problem.model.case,
        "parameters": list(problem.model.parameter_names),
        "sigma_m": problem.sigma_m,
        "seed": validation.seed,
        "trials": validation.trials,
        "confidence": CONFIDENCE,
        "spreads": validation.spreads.as_dict(),
        "test_pose_positions_m": problem.test_poses.position_m.tolist(),
        "plans": [plan_record(p) for p in validation.plans],
        "rankings": {str(m): r for m, r in rankings(validation.plans).items()},
        "wall_s": validation.wall_s,
        "linearisation": [
            {"scale": scale, "spreads": v.spreads.as_dict(), "wall_s": v.wall_s,
             "plans": [{"criterion": p.plan.criterion, "m": p.plan.m, "max_ratio": p.max_ratio,
                        "worst_relative_error": p.worst_relative_error,
                        "non_converged": p.identification.non_converged,
                        "compensation_failed": p.compensation_failed} for p in v.plans]}
            for scale, v in study
        ],
    }


def write_validation(path: Path, validation: Validation,
                     study: list[tuple[float, Validation]] = ()) -> dict:
    """Write ``validation.json`` atomically; returns the record."""
    record = validation_record(validation, study)
    write_atomic(Path(path), (json.dumps(record, indent=2) + "\n").encode())
    return record


def format_report(validation: Validation, study: list[tuple[float, Validation]] = ()) -> str:
    """Per plan: max predicted and simulated RMS error (mm) with the interval, node agreement;
    the rankings; the wall time; and the linearisation study when given."""
    v, sp = validation, validation.spreads
    names = v.problem.model.parameter_names
    errors = ([f"length {sp.length_m * 1e3:g} mm, angle {math.degrees(sp.angle_rad):g} deg"]
              if any(not n.startswith("k.") for n in names) else [])
    errors += [f"k {sp.k_nominal:g} (log-std {sp.k_log_spread:g})"] if any(n.startswith("k.") for n in names) else []
    lines = [
        (f"virtual calibration of {v.problem.name} ({v.problem.model.case}): {v.trials} trials, "
         f"seed {v.seed}, {v.problem.test_poses.s} test poses; errors: {', '.join(errors)}"),
        (f"{'criterion':<10} {'m':>3} {'max sqrt(rho)':>14} {'max simulated':>14} "
         f"{f'{round(100 * CONFIDENCE)}% interval':>18} {'worst node':>11} {'covered':>8}  identification"),
    ]
    for p in v.plans:
        mx, ident = plan_record(p)["max"], p.identification
        notes = "" if not ident.non_converged else f", {ident.non_converged} trials NOT CONVERGED"
        if p.compensation_failed:
            notes += f"; {p.compensation_failed} (trial, pose) cases NOT COMPENSATED, left out"
        lines.append(
            f"{p.plan.criterion:<10} {p.plan.m:>3} {mx['predicted_m'] * 1e3:>11.4f} mm "
            f"{mx['empirical_m'] * 1e3:>11.4f} mm {mx['ci_low_m'] * 1e3:>8.4f}..{mx['ci_high_m'] * 1e3:.4f} "
            f"{100 * p.worst_relative_error:>10.2f}% {100 * p.coverage:>7.0f}%  "
            f"{ident.method}, {ident.iterations} it.{notes}"
        )
    for m, r in rankings(v.plans).items():
        same = "same" if r["by_measure"] == r["by_simulation"] else "DIFFERENT"
        lines.append(f"m = {m}: ranking by the measure {r['by_measure']}, "
                     f"by simulation {r['by_simulation']} ({same})")
    lines.append(f"wall time {v.wall_s:.2f} s for {len(v.plans)} plans x {v.trials} trials")
    if study:
        lines.append("linearisation, every spread times scale: max simulated / max sqrt(rho), "
                     "worst node |simulated / sqrt(rho) - 1|, (trial, pose) cases not compensated")
        names = [f"{p.plan.criterion} m={p.plan.m}" for p in study[0][1].plans]
        lines.append(f"{'scale':>8}" + "".join(f"{n:>20}" for n in names))
        for scale, s in study:
            cells = [f"{p.max_ratio:.3f} {100 * p.worst_relative_error:4.1f}% {p.compensation_failed}"
                     for p in s.plans]
            lines.append(f"{scale:>8g}" + "".join(f"{c:>20}" for c in cells))
    return "\n".join(lines)

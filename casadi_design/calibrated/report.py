"""What ``casadi-design identify`` prints and writes: the summary, ``identification.json`` (SI
units, field names with their unit), ``compensated_test_poses.csv`` and ``identification.md``."""

from __future__ import annotations

import math

import numpy as np

from ..records.export import CONVERGED_COLUMN, change_columns, csv_text, is_prismatic, joint_scales, plan_table
from ..identification.calibrate import CORRELATION_LIMIT, Calibration
from ..identification.fit import ABSORB_SEED, FRAME_PARAMETERS, error_placement
from ..identification.measurements import file_sha256

#: Step (m, rad) of the finite differences of the tracker frame's entries in its parameters.
FRAME_STEP = 1e-7


def parameter_unit(calibration: Calibration, name: str) -> str:
    """SI unit of parameter ``name``: m, rad, rad/(N m) or m/N (a joint's compliance ``k.<joint>``;
    a bearing's tilt ``k.<joint>.<axis>``: rad/(N m)); under the seating push, whose size is not
    known, a compliance is that of a 1 N push (:data:`~casadi_design.identification.fit.SEATING_N`)."""
    robot = calibration.problem.robot
    owner, what = name.split(".", 1)
    prismatic = owner in robot.joints and is_prismatic(calibration.problem, robot.joints.index(owner))
    if owner == "k":
        joint, _, tilt = what.partition(".")
        unit = "m/N" if not tilt and is_prismatic(calibration.problem, robot.joints.index(joint)) else "rad/(N m)"
        return unit + (", at a 1 N push" if calibration.fit.fit.model.seating_N is not None else "")
    if what in ("tx", "ty", "tz") or (what == "offset" and prismatic):
        return "m"
    return "rad"


def frame_delta(f, values: np.ndarray) -> np.ndarray:
    """The 6 placement errors of a tracker frame from the fit's kept frame parameters ``values``."""
    delta = np.zeros(6)
    for name, value in zip(f.fit.frame_names, values):
        delta[FRAME_PARAMETERS.index(name)] = value
    return delta


def tracker_std(calibration: Calibration) -> np.ndarray:
    """Standard deviations (4 x 4, m) of the entries of ``tracker_from_base``:
    ``sqrt(diag(G C G^T))``, ``G`` the finite-difference derivative of ``T0 E(delta)`` in the
    frame's parameters and ``C`` their covariance."""
    f = calibration.fit
    nf = len(f.fit.frame_names)
    if nf == 0:
        return np.zeros((4, 4))
    C = (calibration.std[:, None] * calibration.correlation * calibration.std[None, :])[:nf, :nf]
    delta = np.zeros(6)
    for name, value in zip(f.fit.frame_names, f.X):
        delta[FRAME_PARAMETERS.index(name)] = value
    G = []
    for name in f.fit.frame_names:
        step = delta.copy()
        step[FRAME_PARAMETERS.index(name)] += FRAME_STEP
        G.append(((f.T0 @ error_placement(step)) - (f.T0 @ error_placement(delta))).ravel() / FRAME_STEP)
    G = np.array(G).T
    return np.sqrt(np.maximum(np.einsum("ia,ab,ib->i", G, C, G), 0.0)).reshape(4, 4)


def compensated_table(calibration: Calibration) -> tuple[list[str], list[list]]:
    """``compensated_test_poses.csv``: the plan columns of the compensated test poses, then the
    change from the nominal joint values (deg, mm for prismatic joints)."""
    problem = calibration.problem
    tp = problem.test_poses
    header, rows = plan_table(problem, calibration.q_compensated, tp.F)
    header = header[: len(rows[0])]  # no clearance columns: the test poses were not checked
    changes = change_columns(problem)
    scale = joint_scales(problem)
    delta = (calibration.q_compensated - tp.q) / scale
    return (header + changes + [CONVERGED_COLUMN],
            [r + list(d) + [bool(c)] for r, d, c in zip(rows, delta, calibration.compensation_converged)])


def compensated_csv(calibration: Calibration) -> str:
    return csv_text(*compensated_table(calibration))


def identification_record(calibration: Calibration, files: dict) -> dict:
    """``identification.json`` (module docstring)."""
    c, f = calibration, calibration.fit
    meas, problem = c.measurements, c.problem
    valid = c.validation
    return {
        "problem": problem.path,
        "measurements": meas.path,
        "measurements_sha256": [file_sha256(path) for path in meas.paths or (meas.path,)],
        "frame": f.fit.frame,
        "absorb_seed": ABSORB_SEED,
        "sigma_m": problem.sigma_m,
        "parameters": [{"name": n, "value": float(x), "std": float(s), "unit": parameter_unit(c, n),
                        "of": "tracker frame" if n in f.fit.frame_names else "robot"}
                       for n, x, s in zip(c.names, f.X, c.std)],
        "covariance": (c.std[:, None] * c.correlation * c.std[None, :]).tolist(),
        "covariance_unit": "SI: the product of the two parameters' units (the order of 'parameters')",
        "absorbed": [{"name": n, "why": why} for n, why in f.fit.absorbed],
        "tracker_from_base": f.tracker_from_base.tolist(),
        "tracker_from_base_std": tracker_std(c).tolist(),
        "tracker_from_base_unit": "m (4 x 4 homogeneous: base-frame points to tracker-frame points)",
        **({"rounds": [{"file": path, "rows": int(np.sum(meas.rounds == k))} for k, path in enumerate(meas.paths)],
            "tracker_frames": "one per round" if meas.frames > 1 else "one, shared by every round (--same-frame)",
            "tracker_from_base_per_round": [f.tracker_from_base.tolist(), *(
                (f.T0s[k + 1] @ error_placement(frame_delta(f, d))).tolist() for k, d in enumerate(f.frames))]
            if f.frames is not None else [f.tracker_from_base.tolist()]} if meas.paths else {}),
        "least_squares": {**f.identification.as_dict(), "converged": f.identification.non_converged == 0},
        "model": c.model,
        "model_choice": "leave-one-out cross-validation, one-standard-error rule" if c.model_chosen else "given (--model)",
        "candidates": [k.as_dict() for k in c.candidates],
        "notes": list(c.measurements.notes) + list(c.notes),
        "noise": {"sigma_m": problem.sigma_m, "sigma_estimated_m": c.sigma_hat_m, "chi2": c.chi2,
                  "dof": c.dof, "chi2_interval": list(c.chi2_interval), "confidence": 0.95,
                  "consistent": c.noise_consistent},
        "error_per_value": {**c.scale.as_dict(),
                            "meaning": "the fit's errors per measured value: the tracker's sigma (the problem's, "
                                       "kept for designs) and the robot's unmodelled error (cross-validated, 0 when "
                                       "the residuals are the tracker's noise); std, covariance and predictions use "
                                       "their sum, outliers are judged against the robust outlier scale"},
        "model_error": None if c.field is None else {
            **c.field.estimate.as_dict(),
            "lengths_unit": "rad (m for a prismatic joint), per joint in the order of 'joints'",
            "compensates": c.field_compensates,
            "leave_one_out_rms_m": {"with_the_field": c.field.loo_rms(), "least_squares_alone": c.field.loo_rms(False)},
            "joints": list(problem.robot.joints),
            "meaning": "the robot's unmodelled error as a Gaussian process over the joint configurations: of the "
                       "joint angles, seen through each joint's Jacobian column (angles_rad), or per base axis "
                       "(scale_m) (REML on the residuals of the model identified); --prior designs with it, and "
                       "with the poses below, which it correlates new poses with",
            "poses": {"q": c.field.Q.tolist(), "F": meas.F[f.used].tolist(), "unit": "rad (m), N"}},
        "correlation_limit": CORRELATION_LIMIT,
        "correlated_pairs": [{"a": a, "b": b, "correlation": r} for a, b, r in c.correlated_pairs()],
        "outliers": [{"row": line, "residual_in_scales": r, "scale_m": scale} for line, r, scale in c.outliers],
        "experiments": [{"row": line, "used": bool(u), "residual_rms_m": float(r), "residual_max_m": float(x),
                         "residual_xyz_m": np.where(np.isfinite(a), a, None).tolist()}
                        for line, u, r, x, a in zip(meas.lines, f.used, c.residual_rms_m, c.residual_max_m,
                                                    c.residual_axes_m)],
        "residual_rms_m": float(np.sqrt(np.mean(c.residual_rms_m[f.used] ** 2))),
        "test_poses": {"predicted_rms_m": c.predicted_rms_m.tolist(),
                       "max_predicted_rms_m": float(np.max(c.predicted_rms_m)),
                       "predicted_parameters_rms_m": c.predicted_parameters_m.tolist(),
                       "predicted_unmodelled_rms_m": float(np.sqrt(np.max(
                           c.predicted_rms_m**2 - c.predicted_parameters_m**2, initial=0.0))),
                       "predicted_is": "sqrt(s^2 trace(B0 M^-1 B0^T) + d tau^2): the parameters' error "
                                       "(tracker and unmodelled error through the fit) and the pose's own "
                                       "unmodelled error, which compensation cannot remove",
                       "predicted_with_field_rms_m": None if c.predicted_field_m is None else c.predicted_field_m.tolist(),
                       "q_compensated_is": "the calibrated robot on the nominal targets" + (
                           "" if c.field is None else ", corrected by the field's kriging mean at the pose"),
                       "q_compensated": c.q_compensated.tolist(),
                       "compensation_converged": c.compensation_converged.tolist()},
        "validation": None if valid is None else {
            "file": c.validation_path, "rows": list(valid.lines),
            "frame": "nominal, registration and calibrated: the tracker frame fitted on the training rows; "
                     "*_reregistered: each model's own best rigid fit to the validation rows",
            "tracker_moved": valid.moved,
            "counted": list(valid.counted),
            **{f"{k}_m": getattr(valid, f"{k}_m").tolist() for k in VALIDATION_ERRORS},
            "out_of_range": valid.out_of_range.tolist(),
            **{f"{k}_rms_m": valid.rms(k) for k in VALIDATION_ERRORS},
            **{f"{k}_out_of_range_rms_m": none_if_nan(valid.rms(k, valid.out_of_range)) for k in VALIDATION_ERRORS},
            **{f"{k}_max_m": float(np.max(getattr(valid, f"{k}_m"))) for k in VALIDATION_ERRORS},
            **({} if valid.field_m is None else {
                f"{k}_{w}": v for k in FIELD_ERRORS for w, v in (
                    ("m", getattr(valid, f"{k}_m").tolist()), ("rms_m", valid.rms(k)),
                    ("out_of_range_rms_m", none_if_nan(valid.rms(k, valid.out_of_range))))})},
        "files": files,
    }


#: The validation errors of :class:`~.calibrate.PoseErrors`, in the order of the tables.
VALIDATION_ERRORS = ("nominal", "registration", "calibrated", "nominal_reregistered",
                     "registration_reregistered", "calibrated_reregistered", "predicted")
VALIDATION_LABELS = {"nominal": "nominal", "registration": "registration only",
                     "calibrated": "calibrated", "nominal_reregistered": "nominal, re-registered",
                     "registration_reregistered": "registration only, re-registered",
                     "calibrated_reregistered": "calibrated, re-registered", "predicted": "predicted"}
#: The validation errors with the field's correction (with a field), in the order of the tables.
FIELD_ERRORS = ("field", "field_reregistered", "predicted_field")
VALIDATION_LABELS |= {"field": "calibrated + field", "field_reregistered": "calibrated + field, re-registered",
                      "predicted_field": "predicted with the field"}
#: The validation errors in the training rows' tracker frame: not counted when the tracker moved.
TRAINING_FRAME = ("nominal", "registration", "calibrated")


def none_if_nan(v: float) -> float | None:
    return None if math.isnan(v) else v


def _value_for_people(value: float, unit: str) -> tuple[float, str]:
    return {"m": (value * 1e3, "mm"), "rad": (math.degrees(value), "deg")}.get(unit, (value, unit))


def summary_lines(calibration: Calibration) -> list[str]:
    """The lines ``identify`` prints (mm, deg for people)."""
    c, f = calibration, calibration.fit
    used = f.used

    def label(name: str) -> str:
        return f"tracker frame correction {name[len('base.'):]}" if name in f.fit.frame_names else name  # to its closed form

    lines = [f"note: {n}" for n in (*c.measurements.notes, *c.notes)]
    lines.append("models (leave-one-out cross-validation on the rows without the outliers of the "
                 "richest model; RMS of the rows left out, mm):")
    for k in c.candidates:
        cv = "not cross-validated: " + k.why if math.isnan(k.cv_rms_m) else f"{k.cv_rms_m * 1e3:8.4f} +- {k.cv_se_m * 1e3:.4f}"
        size = f"{k.L:3d} parameters" + ("" if k.size == k.L else f" ({k.size:.1f} effective)")
        lines.append(f"  {'*' if k.name == c.model else ' '} {k.name:16s} {size}, training "
                     f"{k.training_rms_m * 1e3:8.4f}, cross-validated {cv}")
    lines += [(f"identified {len(c.names)} parameters ({c.model} model, "
               f"{'chosen by cross-validation' if c.model_chosen else 'given by --model'}) from "
               f"{int(used.sum())} of {c.measurements.m} rows "
               f"({int(f.mask[used].sum())} values), frame: {f.fit.frame}; "
               f"{'least squares' if f.prior_information is None else 'MAP under [calibration.prior]'}, loss "
               f"{f.identification.loss}, {f.identification.iterations} evaluations"),
             f"{'parameter':28s} {'value':>12s} {'std':>10s}  unit"]
    for n, x, s in zip(c.names, f.X, c.std):
        (v, unit), (sd, _) = _value_for_people(x, parameter_unit(c, n)), _value_for_people(s, parameter_unit(c, n))
        lines.append(f"{label(n):28s} {v:12.5g} {sd:10.3g}  {unit}")
    lines += [f"absorbed {n}: {why}" for n, why in f.fit.absorbed if not n.startswith("base.")]
    scale = c.scale
    lines.append(f"residual RMS {np.sqrt(np.mean(c.residual_rms_m[used] ** 2)) * 1e3:.4f} mm, max "
                 f"{np.max(c.residual_max_m[used]) * 1e3:.4f} mm; noise sigma estimated "
                 f"{c.sigma_hat_m * 1e3:.4f} mm vs {c.problem.sigma_m * 1e3:g} mm of the problem (chi2 "
                 f"{c.chi2:.1f}, {c.dof} dof, 95 % interval {c.chi2_interval[0]:.1f}..{c.chi2_interval[1]:.1f}: "
                 + ("consistent)" if c.noise_consistent else "more than the tracker's noise)" if scale.tau_m
                    else "NOT consistent: check sigma or the model)"))
    if scale.tau_m:
        lines.append(f"error per measured value {scale.s_m * 1e3:.4f} mm: the tracker's sigma {scale.sigma_m * 1e3:.4g} mm "
                     f"({scale.tracker_share:.1%} of the variance) and the robot's unmodelled error "
                     f"{scale.tau_m * 1e3:.4f} mm (cross-validated); the std, the predictions and the outlier test "
                     "hold it, the designs keep sigma")
    if c.field is not None:
        fld = c.field.field
        lines.append(f"field of the unmodelled error (REML on {c.field.estimate.rows} rows): {fld.describe()}"
                     + ("; the compensation adds its kriging mean" if c.field_compensates else ""))
    lines += [f"correlated beyond {CORRELATION_LIMIT}: {label(a)} / {label(b)} ({r:+.3f})"
              for a, b, r in c.correlated_pairs()]
    lines += [f"outlier excluded: row {line} ({r:.1f} x the other rows' error {s * 1e3:.4g} mm per value)" for line, r, s in c.outliers]
    lines.append(f"predicted accuracy at the {len(c.predicted_rms_m)} test poses: max sqrt(rho) "
                 f"{np.max(c.predicted_rms_m) * 1e3:.4f} mm"
                 + (f" (the parameters' error alone {np.max(c.predicted_parameters_m) * 1e3:.4f} mm; the rest the "
                    "robot's unmodelled error at the pose)" if scale.tau_m else "")
                 + ("" if c.predicted_field_m is None else
                    f"; compensated with the field {np.max(c.predicted_field_m) * 1e3:.4f} mm"))
    if c.validation is None:
        lines.append("warning: no validation set (--validation): the accuracy of the calibrated model "
                     "is predicted, not checked on poses outside the fit")
    else:
        v = c.validation
        out = int(v.out_of_range.sum())
        lines.append(f"validation, {len(v.lines)} rows ({out} out of the training range), RMS (max) mm"
                     + (" (the tracker moved: re-registered only)" if v.moved else "") + ":")
        for k in VALIDATION_ERRORS + (() if v.field_m is None else FIELD_ERRORS):
            if v.moved and k in TRAINING_FRAME + ("field",):
                continue
            rest = f", out of range {v.rms(k, v.out_of_range) * 1e3:.4f}" if out else ""
            lines.append(f"  {VALIDATION_LABELS[k]:34s} {v.rms(k) * 1e3:8.4f} ({np.max(getattr(v, f'{k}_m')) * 1e3:.4f}){rest}")
    if not c.compensation_converged.all():
        lines.append(f"warning: {int((~c.compensation_converged).sum())} test poses could not be "
                     "compensated (the calibrated robot cannot reach their targets)")
    return lines


def report_markdown(calibration: Calibration, figures: list[str], files: list[str]) -> str:
    """``identification.md``: the summary, the figure, the files."""
    c = calibration
    lines = [f"# Identification: {c.problem.name}", "",
             f"Problem `{c.problem.path}`, measurements `{c.measurements.path}`"
             + (f", validation `{c.validation_path}`" if c.validation is not None else "") + ".", "",
             "```", *summary_lines(c), "```", ""]
    lines += [f"![residuals, validation and test poses]({name})" for name in figures[:1]] + [""]
    lines += ["Per row (residual RMS over its points, mm):", "", "| row | used | residual RMS mm | max mm |",
              "|---|---|---|---|"]
    lines += [f"| {line} | {'yes' if u else 'outlier'} | {r * 1e3:.4f} | {x * 1e3:.4f} |"
              for line, u, r, x in zip(c.measurements.lines, c.fit.used, c.residual_rms_m, c.residual_max_m)]
    lines += ["", "## Files", "", *[f"- `{name}`" for name in files], ""]
    return "\n".join(lines)


"""What ``identify`` says and writes of an artefact's recordings (:mod:`.artefact_fit`): the
summary for people (mm) and ``identification.json`` (SI units; the judged figures in mm, named so)."""

from __future__ import annotations

import math

import numpy as np

from ..identification.artefact_fit import ArtefactCalibration, Judged
from .report import none_if_nan, parameter_unit


def placement_means(judged: tuple[Judged, ...]) -> dict:
    """Means over placements of the consistency (measured, predicted, nominal) and the median of
    the spacing errors, mm (None without placements)."""
    if not judged:
        return {}
    mean = {k: float(np.mean([getattr(j, f"{k}_m") for j in judged])) * 1e3
            for k in ("consistency", "predicted_consistency", "nominal_consistency", "relocated_consistency")}
    median = {k: float(np.median([getattr(j, f"{k}_m") for j in judged])) * 1e3
              for k in ("spacing", "predicted_spacing", "nominal_spacing")}
    return {"consistency_mm": mean["consistency"], "predicted_consistency_mm": mean["predicted_consistency"],
            "nominal_consistency_mm": mean["nominal_consistency"],
            "relocated_consistency_mm": mean["relocated_consistency"], "median_spacing_mm": median["spacing"],
            "predicted_median_spacing_mm": median["predicted_spacing"],
            "nominal_median_spacing_mm": median["nominal_spacing"]}


def artefact_record(cal: ArtefactCalibration, files: dict) -> dict:
    """``identification.json`` of an artefact's recordings."""
    f, rec = cal.fit, cal.recordings
    return {
        "problem": cal.problem.path,
        "measurement": "points fixed in an artefact",
        "artefact_points_m": cal.problem.artefact.points_m.tolist(),
        "placements": list(rec.names),
        "configurations": int(rec.N),
        "sigma_m": cal.problem.sigma_m,
        "model": cal.model,
        "model_choice": "leave-one-configuration-out cross-validation, one-standard-error rule; the compliances "
                        "under a load (the robot's weight, or on a robot without masses the seating push) by "
                        "one standard error of the paired differences",
        "candidates": [c.as_dict() for c in cal.candidates],
        "parameters": parameters(cal),
        "covariance": cal.C.tolist(),
        "covariance_unit": "SI units of the parameters, squared",
        "absorbed": [{"name": n, "why": why} for n, why in cal.absorbed],
        "placement_poses": [{"placement": name, "R": f.R[g].tolist(), "t_m": f.t[g].tolist()}
                            for g, name in enumerate(rec.names)],
        "error_per_value": cal.scale.as_dict(),
        "outliers": outliers(cal),
        "notes": list(cal.notes),
        "residual_rms_m": float(np.sqrt(np.mean(np.sum(f.r[f.used] ** 2, axis=1)))),
        **judged_record(cal),
        "calibrated_urdf": {"model": cal.in_urdf.model, "parameters": parameters(cal.in_urdf),
                            "why": ("the chosen model" if cal.urdf is None else
                                    "the model without the chosen model's compliances (a URDF cannot hold them), "
                                    "identified and judged alike on the same recordings"),
                            "outliers": outliers(cal.in_urdf),
                            "notes": list(cal.in_urdf.notes), **judged_record(cal.in_urdf)},
        "files": files,
    }


def parameters(cal: ArtefactCalibration) -> list[dict]:
    """The identified parameters: name, value, standard deviation and unit (SI)."""
    return [{"name": n, "value": float(x), "std": float(s), "unit": parameter_unit(cal, n)}
            for n, x, s in zip(cal.names, cal.fit.X, cal.std)]


def outliers(cal: ArtefactCalibration) -> list[dict]:
    """The configurations left out as outliers (a ball not seated) and their scores."""
    return [{"configuration": where, "score": score} for where, score in cal.outliers]


def recorded_well(judged: tuple[Judged, ...]) -> tuple[list[str], dict]:
    """The names of the placements recorded badly (:attr:`Judged.recorded_badly`) and the
    :func:`placement_means` of the others; ([], {}) when none or all are."""
    bad = [j.name for j in judged if j.recorded_badly]
    well = tuple(j for j in judged if not j.recorded_badly)
    return (bad, placement_means(well)) if bad and well else ([], {})


def judged_record(cal: ArtefactCalibration) -> dict:
    """``training`` and ``validation``: per placement the figures (mm) and their means; the
    held-out means over the placements recorded well too (``recorded_well``, None when every
    placement or none was)."""
    bad, well = recorded_well(cal.validation)
    return {"training": {"placements": [j.as_dict() for j in cal.training], **placement_means(cal.training)},
            "validation": ({"placements": [j.as_dict() for j in cal.validation], **placement_means(cal.validation),
                            "recorded_well": {"without": bad, **well} if bad else None}
                           if cal.validation else None)}


def artefact_summary(cal: ArtefactCalibration) -> list[str]:
    """The summary for people: the model, the parameters not told, the error scale, and per
    placement the consistency and spacing (mm), measured, predicted and nominal."""
    f, rec = cal.fit, cal.recordings
    lines = [f"{rec.N} configurations in {rec.P} placement(s) of the artefact ({', '.join(rec.names)}); "
             f"model {cal.model}: {len(cal.names)} parameters, with {f.placement_parameters} of the placements' poses",
             "candidates (leave-one-configuration-out RMS point error, mm): " + ", ".join(
                 f"{c.name} ({c.L}) {c.cv_rms_m * 1e3:.3f}" if not math.isnan(c.cv_rms_m) else f"{c.name} ({c.why})"
                 for c in cal.candidates)]
    if cal.absorbed:
        lines.append(f"not told by the recordings (absorbed): {', '.join(n for n, _ in cal.absorbed)}")
    s = cal.scale
    lines.append(f"error per value {s.s_m * 1e3:.4f} mm (seating repeatability {s.sigma_m * 1e3:.4f} mm, "
                 f"unmodelled {s.tau_m * 1e3:.4f} mm)")
    if cal.outliers:
        lines.append(f"outliers (a ball not seated): {', '.join(f'{w} ({z:.1f})' for w, z in cal.outliers)}")
    lines += cal.notes
    lines.append("placement        consistency mm (predicted, nominal)   spacing error mm (predicted, nominal)")
    for title, judged in (("trained on", cal.training), ("held out", cal.validation)):
        for j in judged:
            lines.append(f"{j.name[:16]:16s} {j.consistency_m * 1e3:7.3f} ({j.predicted_consistency_m * 1e3:.3f}, "
                         f"{j.nominal_consistency_m * 1e3:.2f})          {j.spacing_m * 1e3:7.3f} "
                         f"({none_if_nan(j.predicted_spacing_m * 1e3) or 0:.3f}, {j.nominal_spacing_m * 1e3:.2f})"
                         f"   {title}")
    if cal.validation:
        lines.append(f"held out: {held_out(cal)}")
    if cal.urdf is not None:
        u = cal.urdf
        lines.append(f"calibrated.urdf holds the {u.model} model ({len(u.names)} parameters, identified alike: a URDF "
                     "cannot hold the joints' compliances): trained on, mean consistency "
                     f"{placement_means(u.training)['consistency_mm']:.3f} mm" +
                     (f"; held out, {held_out(u)}" if u.validation else ""))
    return lines


def held_out(cal: ArtefactCalibration) -> str:
    """The held-out placements' mean consistency and median spacing error, measured and predicted
    (mm); the same over the placements recorded well where some were not."""
    def means(m: dict) -> str:
        return (f"mean consistency {m['consistency_mm']:.3f} mm (predicted {m['predicted_consistency_mm']:.3f}, "
                f"nominal {m['nominal_consistency_mm']:.2f}), median spacing error {m['median_spacing_mm']:.3f} mm "
                f"(predicted {m['predicted_median_spacing_mm']:.3f})")
    bad, well = recorded_well(cal.validation)
    return means(placement_means(cal.validation)) + (
        f"; without {', '.join(bad)} (recorded badly), {means(well)}" if bad else "")

"""``[calibration]``: what is identified (the case, the parameters, the compliant joints and the
wrench components), the prior on the parameters and the robot's unmodelled error as a field."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .fields import WRENCH_ROWS, TableReader

CASES = ("geometric", "elastostatic", "both")

#: The keys allowed in each table of this section (None: any key).
KEYS: dict[str, set[str] | None] = {
    "calibration": {"case", "parameters", "compliant_joints", "wrench_components", "prior", "model_error"},
    "calibration.prior": {"length_m", "angle_rad", "offset_rad", "compliance_rad_per_Nm"},
    "calibration.model_error": {"scale_m", "angle_rad", "length_rad", "nugget_m", "shares"},
}


@dataclass(frozen=True)
class PriorSpec:
    """What is known of the robot's parameters before measuring (``[calibration.prior]``): the
    standard deviation of a zero-mean normal prior per group (None: no prior on the group),
    e.g. a factory calibration's accuracy. Groups: the joint placement errors' translations
    (``length_m``, m; also the zero offsets of prismatic joints) and rotations (``angle_rad``,
    rad), the zero offsets of revolute joints (``offset_rad``, rad), the joint compliances
    (``compliance_rad_per_Nm``, rad/(N m)). The tracker frame and the measured points (``tool.*``)
    have none: registration places them."""

    length_m: float | None = None
    angle_rad: float | None = None
    offset_rad: float | None = None
    compliance_rad_per_Nm: float | None = None


@dataclass(frozen=True)
class ModelErrorSpec:
    """The robot's unmodelled error as a random field over its configurations
    (``[calibration.model_error]``, :mod:`casadi_design.measures.field`): either ``angle_rad``
    the std of each joint's angle error (rad; an error of the joint angles, seen through each
    joint's Jacobian column) or ``scale_m`` its std per base axis (m, 0 with ``angle_rad``);
    ``length_rad`` its correlation length per joint (rad; m for a prismatic joint), ``nugget_m``
    the part no neighbouring pose tells (m), ``shares`` each joint's share of the variance of a
    field of the base axes additive over the joints (sum 1; empty: the squared exponential over
    all joints at once)."""

    scale_m: float
    length_rad: tuple[float, ...]
    nugget_m: float = 0.0
    shares: tuple[float, ...] = ()
    angle_rad: tuple[float, ...] = ()


@dataclass(frozen=True)
class CalibrationSpec:
    """What is identified. ``parameters`` is a tuple of names or ``"identifiable"``;
    ``compliant_joints`` None means every joint of the chain; ``prior``: ``[calibration.prior]``
    (None without one)."""

    case: str
    parameters: tuple[str, ...] | str = ()
    compliant_joints: tuple[str, ...] | None = None
    wrench_components: tuple[str, ...] = ()
    prior: PriorSpec | None = None
    model_error: ModelErrorSpec | None = None


def read_calibration(cal: TableReader) -> CalibrationSpec:
    case = cal.get("case", str, hint=f"allowed: {', '.join(CASES)}")
    if case not in CASES:
        raise cal.error(f"'{case}' is not a calibration case", f"allowed: {', '.join(CASES)}", "case")
    elastic = case in ("elastostatic", "both")
    for key, used in (("parameters", case != "elastostatic"), ("compliant_joints", elastic),
                      ("wrench_components", elastic)):
        if key in cal.table and not used:
            raise cal.error(f"is not used by case '{case}'", "remove it or change the case", key)
    parameters: tuple[str, ...] | str = ()
    if case != "elastostatic":
        value = cal.get("parameters", (list, str), hint="a list of names, e.g. [\"joint1.offset\"], or \"identifiable\"")
        if isinstance(value, str):
            if value != "identifiable":
                raise cal.error(f"'{value}'", "give a list of names or \"identifiable\"", "parameters")
            parameters = value
        else:
            parameters = cal.names("parameters", hint="e.g. [\"joint1.offset\", \"tool.tx\"]")
    return CalibrationSpec(
        case, parameters,
        cal.names("compliant_joints", default=None, hint="joint names, e.g. [\"joint1\", \"joint2\"]",
                  noun="joints") if elastic else None,
        cal.names("wrench_components", WRENCH_ROWS, hint="the wrench components of F, e.g. [\"fx\", \"fy\"]") if elastic else (),
        _prior(cal.sub("prior")),
        _model_error(cal.sub("model_error")),
    )


def _model_error(table: TableReader | None) -> ModelErrorSpec | None:
    """``[calibration.model_error]``: the joints' angle errors (rad) or the field's scale per base
    axis (m), its correlation length (rad, one for every joint or one per joint; checked against
    the robot's joints when it is built), its nugget (m) and, of the base axes' field, the joints'
    shares."""
    if table is None:
        return None
    joints = table.get("angle_rad", (int, float, list), None,
                       hint="each joint's angle error std in rad, e.g. 3e-4, or one per joint")
    angles = () if joints is None else _positive_list(table, "angle_rad", joints,
                                                       "give a positive angle in rad, e.g. 3e-4, or one per joint")
    if angles and table.get("scale_m", (int, float), None) is not None:
        raise table.error("and angle_rad are both given", "give angle_rad (an error of the joint angles) or scale_m "
                          "(an error of each base axis), not both", "scale_m")
    scale = 0.0 if angles else table.number("scale_m", hint="the unmodelled error's std per axis in m, e.g. 2.5e-4",
                                            positive=True)
    value = table.get("length_rad", (int, float, list), hint="a correlation length in rad, e.g. 0.5, or one per joint")
    lengths = _positive_list(table, "length_rad", value, "give a positive length in rad, e.g. 0.5, or a list of one "
                             "per joint")
    nugget = table.number("nugget_m", 0.0, hint="the uncorrelated unmodelled error's std in m, e.g. 2e-5")
    if not nugget >= 0:
        raise table.error(f"is {nugget:g}", "give a std >= 0 in m", "nugget_m")
    value = table.get("shares", (list,), [], hint="each joint's share of the variance, e.g. [0.5, 0.5, 0, 0, 0, 0]")
    try:
        shares = np.asarray(value, dtype=float).ravel()
    except (TypeError, ValueError):
        shares = np.array([np.nan])
    if shares.size and angles:
        raise table.error("is given with angle_rad", "shares split the base axes' scale_m over the joints; with "
                          "angle_rad each joint has its own angle, leave shares out", "shares")
    if shares.size and not (np.all(np.isfinite(shares) & (shares >= 0)) and abs(shares.sum() - 1.0) < 1e-6):
        raise table.error(f"is {value!r}", "give one share >= 0 per joint, summing to 1 (an additive field), "
                          "or leave it out", "shares")
    return ModelErrorSpec(scale, lengths, nugget, tuple(float(v) for v in shares), angles)


def _positive_list(table: TableReader, key: str, value, fix: str) -> tuple[float, ...]:
    """``value``, one positive number or a list of them, as a tuple; else the error naming ``key``."""
    try:
        v = np.atleast_1d(np.asarray(value, dtype=float)) if not isinstance(value, bool) else np.array([np.nan])
    except (TypeError, ValueError):
        v = np.array([np.nan])
    if v.ndim != 1 or not v.size or not np.all(np.isfinite(v) & (v > 0)):
        raise table.error(f"is {value!r}", fix, key)
    return tuple(float(x) for x in v)


def _prior(prior: TableReader | None) -> PriorSpec | None:
    """``[calibration.prior]``: one positive standard deviation per group given."""
    if prior is None:
        return None
    hints = {"length_m": "a std in m, e.g. 1e-3", "angle_rad": "a std in rad, e.g. 1e-3",
             "offset_rad": "a std in rad, e.g. 0.01", "compliance_rad_per_Nm": "a std in rad/(N m), e.g. 1e-6"}
    values = {k: prior.number(k, None, hint=h, positive=True) for k, h in hints.items()}
    if all(v is None for v in values.values()):
        raise prior.error("gives no standard deviation", f"give one or more of {', '.join(hints)}, "
                          "or remove the table")
    return PriorSpec(**values)

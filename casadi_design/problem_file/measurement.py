"""``[measurement]``: what each experiment measures (components, markers) and with which noise
(one std, per axis, or a full covariance); with ``[measurement.artefact]``, no tracker: the
measured point seated at points fixed in an artefact (:mod:`casadi_design.calibration.artefact`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .fields import TWIST_ROWS, Mat, TableReader, to_mat, to_vec

#: Relative asymmetry accepted in a covariance matrix.
SYMMETRY_RTOL = 1e-9
#: Largest measurement noise std (m) and calibration load (N, N m) accepted: beyond them the
#: value is a typing error (no tracker is that noisy, no rig that strong), and its square
#: overflows the arithmetic.
MAX_SIGMA_M = 1.0

#: The keys allowed in each table of this section (None: any key).
KEYS: dict[str, set[str] | None] = {
    "measurement": {"components", "sigma_m", "sigma_rad", "sigma_axes_m", "covariance", "markers_m", "artefact"},
    "measurement.artefact": {"points_m", "placements", "tilt_max_deg", "clamps"},
    "measurement.artefact.placements": {"name", "xyz_m", "rpy_deg"},
}
#: Largest distance (m) of an artefact's point from its first: beyond it the value is in mm.
MAX_ARTEFACT_M = 5.0
#: The largest tilt (deg) of the measured frame's z axis from the artefact's -z (into the
#: socket) a seated configuration may have, by default: MUKCa's Panda recordings reach 54 deg
#: (the hand's stem leaves the socket's rim beyond).
TILT_MAX_DEG = 55.0


@dataclass(frozen=True)
class PlacementSpec:
    """Where an artefact is clamped: its frame's position ``xyz_m`` (m) and orientation
    ``rpy_rad`` (roll, pitch, yaw, rad; ``R = Rz Ry Rx``) in the robot's base frame."""

    name: str
    xyz_m: tuple[float, float, float]
    rpy_rad: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ArtefactSpec:
    """``[measurement.artefact]``: the points fixed in the artefact, in its frame (m, K x 3),
    and the placements it is clamped at (for the designs that plan configurations; recordings
    bring their own placements, each an unknown pose)."""

    points_m: Mat
    placements: tuple[PlacementSpec, ...] = ()
    #: the largest tilt of the measured frame's z axis from the artefact's -z, rad, of a
    #: configuration planned with the ball seated
    tilt_max_rad: float = float(np.radians(TILT_MAX_DEG))
    #: how many of the placements the plans record at (where to clamp: the best set of
    #: ``clamps`` placements)
    clamps: int = 1


@dataclass(frozen=True)
class MeasurementSpec:
    """What each experiment measures and with which noise.

    ``whitening`` is ``sigma * Sigma^-1/2`` (d x d) for the per-value noise of one experiment,
    None when every value has std ``sigma_m``. Values are ordered as measured: the position
    components of each marker, then the orientation components.
    """

    components: tuple[str, ...]
    sigma_m: float
    markers_m: Mat | None = None
    whitening: Mat | None = None
    artefact: ArtefactSpec | None = None


def read_measurement(meas: TableReader) -> MeasurementSpec:
    measured = meas.names("components", TWIST_ROWS, hint="e.g. components = [\"x\", \"y\", \"z\"]")
    sigma = meas.number("sigma_m", hint="the measurement noise std in m, e.g. 1e-4", positive=True)
    if sigma > MAX_SIGMA_M:
        raise meas.error(f"is {sigma:g} m, above {MAX_SIGMA_M:g} m (no tracker is that noisy)",
                         "give the noise std in m, e.g. 1e-4 for 0.1 mm", "sigma_m")
    markers = meas.array("markers_m", (None, 3), None, hint="one row (x, y, z) in m per marker, in the measured frame")
    if markers is not None and len(markers) == 0:
        raise meas.error("is empty", "give one row (x, y, z) in m per marker, or remove it", "markers_m")
    if markers is not None and not any(c in ("x", "y", "z") for c in measured):
        raise meas.error("markers need position components", "measure x, y or z, or remove markers_m", "markers_m")
    artefact = _artefact(meas, measured, markers)
    return MeasurementSpec(measured, sigma, to_mat(markers), to_mat(_whitening(meas, measured, markers, sigma)),
                           artefact)


def _artefact(meas: TableReader, measured: tuple[str, ...], markers) -> ArtefactSpec | None:
    """``[measurement.artefact]``: the ball's seating points and the placements; the measured
    point is then one point (the measured frame's origin or its tool point), all of x, y, z,
    with one std (the seating repeatability)."""
    table = meas.sub("artefact")
    if table is None:
        return None
    if tuple(sorted(measured)) != ("x", "y", "z") or markers is not None:
        raise meas.error("an artefact's points are met by one point in x, y and z", "give components = "
                         "[\"x\", \"y\", \"z\"] and no markers_m (the ball centre: [robot] frame or tool_xyz_m)",
                         "components")
    for key in ("sigma_axes_m", "sigma_rad", "covariance"):
        if key in meas.table:
            raise meas.error("is not used with an artefact", "give sigma_m, the seating repeatability in m", key)
    points = table.array("points_m", (None, 3), hint="one row (x, y, z) in m per point, in the artefact's frame, "
                         "e.g. [[0, 0, 0], [0.05, 0, 0]]")
    if len(points) < 2:  # every configuration at one unknown point: the robot scaled about its base is as consistent
        raise table.error("has one point, which tells no length: the robot's scale would not be told", "give two "
                          "or more points a known distance apart, e.g. [[0, 0, 0], [0.05, 0, 0]] for sockets 50 mm "
                          "apart", "points_m")
    far = float(np.max(np.linalg.norm(points - points[0], axis=1)))
    if far > MAX_ARTEFACT_M:
        raise table.error(f"has points {far:g} m apart", "give them in m, e.g. [[0, 0, 0], [0.05, 0, 0]] for "
                          "sockets 50 mm apart", "points_m")
    if len(np.unique(np.round(points, 9), axis=0)) < len(points):
        raise table.error("has a point twice", "give each point once", "points_m")
    placements = []
    for k, row in enumerate(table.get("placements", list, [])):
        if not isinstance(row, dict):
            raise table.error(f"entry {k + 1} is not a table", "write { name = \"front\", xyz_m = [x, y, z], "
                              "rpy_deg = [r, p, y] }", "placements")
        r = table.row(row, "measurement.artefact.placements", f"measurement.artefact.placements[{k + 1}]")
        name = r.get("name", str, hint="a name, e.g. name = \"front\"")
        if not name.strip() or name in [p.name for p in placements]:
            raise r.error(f"'{name}' is empty or repeated", "give each placement its own name", "name")
        xyz = r.array("xyz_m", (3,), hint="the artefact frame's origin in the robot's base frame, m")
        rpy = r.array("rpy_deg", (3,), np.zeros(3), hint="roll, pitch, yaw of the artefact frame in deg")
        placements.append(PlacementSpec(name, to_vec(xyz), to_vec(np.radians(rpy))))
    tilt = table.number("tilt_max_deg", TILT_MAX_DEG, hint="the largest angle in deg between the measured frame's z "
                        "axis and the artefact's -z, e.g. 55", positive=True)
    if tilt > 180:
        raise table.error(f"is {tilt:g} deg", "give an angle in deg up to 180", "tilt_max_deg")
    clamps = table.integer("clamps", 1, hint="how many placements the plans record at, e.g. 1", low=1,
                           high=max(1, len(placements)))
    return ArtefactSpec(to_mat(points), tuple(placements), float(np.radians(tilt)), clamps)


def _whitening(meas: TableReader, measured: tuple[str, ...], markers, sigma: float) -> np.ndarray | None:
    """``sigma * Sigma^-1/2`` for the per-value noise of one experiment (None: all values sigma).

    ``sigma_axes_m`` gives a std per x, y, z axis, ``sigma_rad`` the orientation std,
    ``covariance`` the full d x d covariance (m^2, rad^2).
    """
    k = 1 if markers is None else len(markers)
    pos = [c for c in measured if c in ("x", "y", "z")]
    rot = [c for c in measured if c in ("rx", "ry", "rz")]
    d = k * len(pos) + len(rot)
    if rot and "sigma_rad" not in meas.table and "covariance" not in meas.table:
        raise meas.error("orientation is measured but its noise is not given", "add sigma_rad (rad)", "sigma_rad")
    if "covariance" in meas.table:
        if "sigma_axes_m" in meas.table or "sigma_rad" in meas.table:
            raise meas.error("give either covariance or sigma_axes_m / sigma_rad", "not both", "covariance")
        C = meas.array("covariance", (d, d), hint=f"a {d} x {d} symmetric positive definite matrix (m^2, rad^2)")
        asym = float(np.max(np.abs(C - C.T)))
        if asym > SYMMETRY_RTOL * float(np.max(np.abs(C))):
            raise meas.error(f"is not symmetric (largest |C - C^T| = {asym:.3g})",
                             "give a symmetric covariance (m^2, rad^2)", "covariance")
        try:
            Lc = np.linalg.cholesky((C + C.T) / 2)
        except np.linalg.LinAlgError:
            raise meas.error("is not positive definite", "give a valid covariance (m^2, rad^2)", "covariance") from None
        return sigma * np.linalg.inv(Lc)
    axes = meas.array("sigma_axes_m", (3,), None, hint="std of x, y, z in m")
    srad = meas.number("sigma_rad", None, hint="the orientation noise std in rad", positive=True)
    if axes is None and srad is None:
        return None
    if axes is not None and not np.all((axes > 0) & (axes <= MAX_SIGMA_M)):
        raise meas.error(f"must be positive and at most {MAX_SIGMA_M:g} m, got {axes.tolist()}",
                         "give standard deviations in m", "sigma_axes_m")
    std = [axes["xyz".index(c)] if axes is not None else sigma for _ in range(k) for c in pos] + [srad] * len(rot)
    return np.diag(sigma / np.array(std, dtype=float))

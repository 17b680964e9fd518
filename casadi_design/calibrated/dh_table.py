"""The DH table of a calibrated DH robot (``calibrated_dh.toml``), in closed form from its axes.

A DH table (:func:`casadi_design.robot.robots.dh_arm`, both conventions) is the chain

    base [link_0] prod_i [ Rz(theta_i + q_i) Tz(d_i) link_i ] flange,   link = Tx(a) Rx(alpha) Ry(beta)

(``link_0``: the modified convention's first row; ``link_n``: the standard convention's last
row). The calibrated chain (:func:`.urdf.calibrated_chain`) gives every joint's axis at
``q = 0``, world frame ``W_k = M_1' ... M_k'``. Walking from the base, the frame ``P_k`` before
joint k's ``Rz(theta_k)`` is on axis k, and the next axis, point ``p`` and direction ``u`` in
``P_k``, gives that joint's ``theta_k, d_k`` and the link's ``a, alpha, beta``:

* **DH** (the nominal axes are not parallel): the common normal. Its foot on axis k is at
  height ``d = p_z + u_z t``, ``t = (u_z p_z - u.p) / (1 - u_z^2)``, the foot on the next axis at
  ``c = p + t u``; its direction ``n = +/- (e_z x u) / |e_z x u|`` (defined for intersecting axes
  too), ``theta = atan2(n_y, n_x)``, ``a = n.(c - d e_z)``, ``beta = 0``.
* **Hayati** (nominal axes within :data:`HAYATI_BELOW_DEG` of parallel, e.g. the ABB's axes 2
  and 3, where the common normal's foot slides away and ``d`` blows up): ``d`` keeps its
  nominal value, the next frame's origin is where the next axis crosses the plane ``z = d``,
  ``c = p + (d - p_z) / u_z u``, ``n = +/- (c_x, c_y, 0) / |.|``, ``a = n.c``.

In both, with ``u' = Rz(-theta) u = Rx(alpha) Ry(beta) e_z``: ``alpha = atan2(-u'_y, u'_z)``,
``beta = asin(u'_x)``; the sign of ``n`` is the one that puts ``theta`` nearest its nominal
value. The rotation about and the shift along axis 1 of the base, and those along the last
axis of the flange, are free: they go to ``theta_1, d_1`` and ``theta_n, d_n``, chosen so that
the base placement ``P_1 link_0^-1`` and the flange are nearest their nominal values (a
joint-zero error of joint 1 or n is then a change of its ``theta_offset``). The last joint
keeps its nominal link.

Every joint frame of the table then lies on the calibrated axis (it differs from ``W_k`` by a
rotation about and a shift along that axis, which commute with the joint's motion), so the
table reproduces the calibrated kinematics at every ``q`` (in the model's own joint angles).
"""

from __future__ import annotations

import math
from dataclasses import replace
from itertools import accumulate

import numpy as np
import pinocchio as pin

from ..problem_file.robot import DHRow, RobotSpec
from ..robot.robots import dh_joint, dh_link, placement_from_xyz_rpy
from .urdf import CalibratedChain

#: Consecutive axes whose nominal directions are within this angle of parallel (or
#: antiparallel) get Hayati's beta instead of the common normal's d (deg).
HAYATI_BELOW_DEG = 1.0


def _near(angle: float, nominal: float) -> float:
    """``angle`` shifted by a multiple of 2 pi to within pi of ``nominal`` (rad)."""
    return nominal + math.remainder(angle - nominal, 2 * math.pi)


def is_hayati(link: DHRow) -> bool:
    """Whether the link of ``link`` (its ``alpha``, ``beta``) joins nearly parallel axes:
    the angle between them is ``acos(|cos alpha cos beta|) < HAYATI_BELOW_DEG``."""
    return abs(math.cos(link.alpha_rad) * math.cos(link.beta_rad)) > math.cos(math.radians(HAYATI_BELOW_DEG))


def _about_z(Y: pin.SE3) -> tuple[float, float]:
    """``(theta, s)`` of the ``Rz(theta) Tz(s)`` nearest ``Y`` (rad, m): ``theta`` maximises
    ``trace(Rz(theta)^T R_Y)``, ``theta = atan2(R_10 - R_01, R_00 + R_11)``, ``s = t_z``."""
    R = Y.rotation
    return math.atan2(R[1, 0] - R[0, 1], R[0, 0] + R[1, 1]), float(Y.translation[2])


def _next_axis(P: pin.SE3, W: pin.SE3, joint: DHRow, link: DHRow) -> tuple[float, ...]:
    """``(theta, d, a, alpha, beta)`` (rad, m) from frame ``P`` on one axis to the axis of
    the joint frame ``W`` (module docstring); ``joint`` / ``link`` hold the nominal values."""
    p = P.actInv(W.translation)
    u = P.rotation.T @ W.rotation[:, 2]
    hayati = is_hayati(link)
    if hayati:
        d = joint.d_m
        c = p + (d - p[2]) / u[2] * u
        n = np.array([c[0], c[1], 0.0])
    else:
        t = (u[2] * p[2] - u @ p) / (1.0 - u[2] ** 2)
        d, c = p[2] + u[2] * t, p + t * u
        n = np.cross([0.0, 0.0, 1.0], u)
    theta = math.atan2(n[1], n[0])
    if abs(math.remainder(theta - joint.theta_offset_rad, 2 * math.pi)) > math.pi / 2:
        theta, n = theta + math.pi, -n
    n = n / np.linalg.norm(n)
    a = float(n @ (c - [0.0, 0.0, d]))
    v = dh_joint(theta, 0.0).rotation.T @ u
    alpha = _near(math.atan2(-v[1], v[2]), link.alpha_rad)
    beta = math.atan2(v[0], math.hypot(v[1], v[2])) if hayati else 0.0
    return _near(theta, joint.theta_offset_rad), float(d), a, alpha, beta


def has_dh_table(robot: RobotSpec) -> bool:
    """Whether :func:`calibrated_dh` applies: a DH robot measured at its ``flange`` (a tool
    after it or not). A joint frame cannot take the calibrated tool."""
    return robot.source == "dh" and robot.frame == "flange"


def calibrated_dh(robot: RobotSpec, chain: CalibratedChain) -> RobotSpec:
    """The DH robot ``robot`` with the table (rows, base, flange) of the calibrated ``chain``.

    ``robot`` is a DH robot measured at its frame ``flange`` (with or without a tool after
    it), ``chain`` its :func:`.urdf.calibrated_chain` (one placement per row). The rows keep
    their names, types and limits; ``beta_rad`` is nonzero only for Hayati rows
    (:func:`is_hayati` of the nominal row).
    """
    rows, standard = robot.dh_rows, robot.dh_convention == "standard"
    if not has_dh_table(robot):
        raise ValueError(f"calibrated_dh: a DH robot measured at its flange, got frame '{robot.frame}'")
    links = rows if standard else rows[1:]  # links[k] joins axis k to axis k+1
    W = list(accumulate(chain.joints, lambda a, b: a * b))  # the joint frames at q = 0
    tool = (pin.SE3.Identity() if robot.tool_xyz_m is None
            else placement_from_xyz_rpy(robot.tool_xyz_m, robot.tool_rpy_rad))
    first = pin.SE3.Identity() if standard else dh_link(rows[0].a_m, rows[0].alpha_rad, rows[0].beta_rad)
    # P_1 on axis 1: W_1 Rz(phi) Tz(s) nearest the nominal P_1 = base link_0
    phi, s = _about_z(W[0].inverse() * placement_from_xyz_rpy(robot.base_xyz_m, robot.base_rpy_rad) * first)
    P = W[0] * dh_joint(phi, s)
    base = P * first.inverse()
    joints, link_values = [], []
    for k in range(len(rows) - 1):
        theta, d, a, alpha, beta = _next_axis(P, W[k + 1], rows[k], links[k])
        joints.append((theta, d))
        link_values.append((a, alpha, beta))
        P = P * dh_joint(theta, d) * dh_link(a, alpha, beta)
    last = rows[-1]
    last_link = dh_link(last.a_m, last.alpha_rad, last.beta_rad) if standard else pin.SE3.Identity()
    # P_n -> flange is Rz(theta_n) Tz(d_n) last_link flange: the Rz Tz nearest it with the nominal flange
    X = P.inverse() * W[-1] * chain.tool * tool.inverse()
    nominal_flange = placement_from_xyz_rpy(robot.flange_xyz_m, robot.flange_rpy_rad)
    theta, d = _about_z(X * (last_link * nominal_flange).inverse())
    joints.append((_near(theta, last.theta_offset_rad), d))
    flange = (dh_joint(theta, d) * last_link).inverse() * X
    if standard:
        link_values.append((last.a_m, last.alpha_rad, last.beta_rad))
    else:
        link_values.insert(0, (rows[0].a_m, rows[0].alpha_rad, rows[0].beta_rad))
    new_rows = tuple(replace(row, theta_offset_rad=theta, d_m=d, a_m=a, alpha_rad=alpha, beta_rad=beta)
                     for row, (theta, d), (a, alpha, beta) in zip(rows, joints, link_values))
    return replace(robot, dh_rows=new_rows,
                   base_xyz_m=tuple(float(v) for v in base.translation),
                   base_rpy_rad=tuple(float(v) for v in pin.rpy.matrixToRpy(base.rotation)),
                   flange_xyz_m=tuple(float(v) for v in flange.translation),
                   flange_rpy_rad=tuple(float(v) for v in pin.rpy.matrixToRpy(flange.rotation)))

"""Robot programs as text: URScript, ABB RAPID, KUKA KRL, the ROS robot_calibration poses YAML
and a JSON joint trajectory.

The vendor formats (URScript, RAPID, KRL) are in the controller's joint convention:
``q_controller = sign * q + offset`` per joint (:class:`Controller`, from ``[robot.controller]``;
identity by default). The YAML and the JSON are in the model's angles (the URDF's, as ROS uses
them). Every format lists the points in program order; a measurement pose carries its
experiment number of the plan (``experiment 5`` in a comment, ``e05`` as a RAPID name), a via
point is marked as such, and a load change stops the program with a message naming the load.

* URScript: ``movej`` in rad with the speed (rad/s) and acceleration (rad/s^2) of the joint
  that sets the move's time, ``sleep`` for the measurement, a blocking ``popup`` for a load.
* RAPID: a module with a ``CONST jointtarget`` per point (deg) and ``MoveAbsJ`` with a ``fine``
  zone and the move's time (``\\T``), ``WaitTime`` for the measurement, ``TPWrite`` and ``Stop``
  for a load.
* KRL: ``PTP {AXIS: A1 ..}`` (deg), ``WAIT SEC`` for the measurement, a comment and ``HALT``
  for a load.
* YAML (robot_calibration): one entry per measurement pose in program order, ``joints`` and
  ``positions`` (rad); robot_calibration moves between them itself.
* JSON: ``{"joint_names", "points": [{"positions", "time_from_start_s", "experiment", "kind",
  "stop_before", "stop_after"}], "moves": [...]}``, the shape of a ROS ``JointTrajectory``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import ProblemError
from ..problem.build import Problem
from ..records.export import joint_scales
from ..records.files import json_ready
from .sequence import Point, Program

#: Digits written: 1e-9 deg and 1e-12 rad, far below any controller's resolution.
DEG_DIGITS = 9
RAD_DIGITS = 12
#: The program file of each format (``--format``).
FILES = {"urscript": "program.script", "rapid": "program.mod", "krl": "program.src", "yaml": "program.yaml",
         "json": "program.json"}
#: Joints a format's controller drives: (fewest, most).
AXES = {"urscript": (6, 6), "rapid": (1, 6), "krl": (1, 6), "yaml": (1, None), "json": (1, None)}


@dataclass(frozen=True)
class Controller:
    """``q_controller = sign * q + offset`` (n,), rad (m for prismatic joints)."""

    sign: np.ndarray
    offset: np.ndarray

    def __call__(self, q: np.ndarray) -> np.ndarray:
        return self.sign * np.asarray(q, dtype=float) + self.offset


def controller(problem: Problem) -> Controller:
    """The joint convention of ``[robot.controller]`` (identity when not given), checked
    against the chain."""
    robot, spec = problem.robot, problem.spec.robot.controller
    n = robot.n
    sign, offset = np.ones(n), np.zeros(n)
    for key, given in (("signs", spec and spec.signs), ("offsets_deg", spec and spec.offsets_deg)):
        if given is not None and len(given) != n:
            raise ProblemError(f"{problem.path}: [robot.controller].{key}: has {len(given)} values, the chain "
                               f"has {n} joints ({', '.join(robot.joints)}); give one per joint")
    if spec is not None and spec.signs is not None:
        sign = np.array(spec.signs, dtype=float)
    if spec is not None and spec.offsets_deg is not None:
        offset = np.array(spec.offsets_deg) * joint_scales(problem)
    return Controller(sign, offset)


def check_format(problem: Problem, fmt: str, option: str = "--format") -> None:
    """Refuse a format unknown or whose controller drives another number of joints (``option``:
    the command-line option that gave it)."""
    if fmt not in FILES:
        raise ProblemError(f"{option}: unknown format '{fmt}'; allowed: {', '.join(FILES)}")
    low, high = AXES[fmt]
    n = problem.robot.n
    if n < low or high is not None and n > high:
        raise ProblemError(f"{option} {fmt}: the controller drives {low if low == high else f'{low} to {high}'} "
                           f"joints, the robot has {n} ({', '.join(problem.robot.joints)}); use --format json or yaml")


def _label(p: Point, index: dict[int, int]) -> str:
    """A point's name for people: home, experiment k, or via i."""
    return "home" if p.kind == "home" else f"experiment {p.experiment}" if p.kind == "experiment" else \
        f"via {index[id(p)]}"


def _vias(program: Program) -> dict[int, int]:
    return {id(p): k for k, p in enumerate((p for p in program.points if p.kind == "via"), start=1)}


def _header(problem: Problem, program: Program, comment: str, plan: str) -> list[str]:
    return [f"{comment} casadi-design program of {problem.name} ({problem.path}), plan {plan}",
            (f"{comment} {len(program.order)} experiment{'s' if len(program.order) != 1 else ''} in the order "
             f"{', '.join(map(str, program.order))}: "
            f"{program.time_s:.1f} s with {program.measure_s:g} s per measurement (file order "
            f"{program.file_time_s:.1f} s); {program.load_changes} load change(s)"),
            f"{comment} joint speeds: {program.times.source}"]


def _lead(program: Program, a: Point, b: Point) -> tuple[float, float]:
    """Speed (rad/s) and acceleration (rad/s^2) of the joint that sets the move's time."""
    k = program.times.lead_joint(a.q, b.q)
    return float(program.times.speed[k]), float(program.times.acceleration[k])


def urscript(problem: Problem, program: Program, plan: str) -> str:
    ctrl, vias = controller(problem), _vias(program)
    lines = [f"def {_identifier(problem.name)}_calibration():"]
    lines += ["  " + h for h in _header(problem, program, "#", plan)]
    lines.append("  # joint values in rad (controller convention); movej: speed and acceleration of the leading joint")
    v0, a0 = float(program.times.speed.min()), float(program.times.acceleration.min())
    for prev, p in zip([None, *program.points[:-1]], program.points):
        v, a = (v0, a0) if prev is None else _lead(program, prev, p)
        q = ", ".join(f"{x:.{RAD_DIGITS}f}" for x in ctrl(p.q))
        lines.append(f"  movej([{q}], a={a:.6g}, v={v:.6g})  # {_label(p, vias)}")
        lines += _stops(p, lambda text: f"  popup(\"{text}\", \"Calibration\", blocking=True)",
                        f"  sleep({program.measure_s:g})  # measure experiment {p.experiment}")
    lines.append("end")
    lines.append(f"{_identifier(problem.name)}_calibration()")
    return "\n".join(lines) + "\n"


def _stops(p: Point, stop, measure: str) -> list[str]:
    """The lines at a point: the stop before the measurement, the measurement, the stop after."""
    if p.kind != "experiment":
        return []
    return ([stop(f"experiment {p.experiment}: {p.stop_before}")] if p.stop_before else []) + [measure] + \
        ([stop(f"experiment {p.experiment}: {p.stop_after}")] if p.stop_after else [])


def _name(p: Point, vias: dict[int, int]) -> str:
    return "home" if p.kind == "home" else f"e{p.experiment:02d}" if p.kind == "experiment" else f"v{vias[id(p)]:02d}"


def rapid(problem: Problem, program: Program, plan: str) -> str:
    ctrl, vias = controller(problem), _vias(program)
    people = joint_scales(problem)
    lines = ["MODULE Calibration"] + ["  " + h for h in _header(problem, program, "!", plan)]
    lines.append("  ! jointtarget in deg (controller convention); unused axes 0, no external axes (9E9)")
    seen = set()
    for p in program.points:
        name = _name(p, vias)
        if name in seen:
            continue
        seen.add(name)
        axes = [f"{x / s:.{DEG_DIGITS}f}" for x, s in zip(ctrl(p.q), people)] + ["0"] * (6 - problem.robot.n)
        lines.append(f"  CONST jointtarget {name} := [[{','.join(axes)}],[9E9,9E9,9E9,9E9,9E9,9E9]];")
    lines += ["", "  PROC main()"]
    for prev, p in zip([None, *program.points[:-1]], program.points):
        speed = "v100" if prev is None else f"v1000\\T:={program.times.move_time(prev.q, p.q):.3f}"
        lines.append(f"    MoveAbsJ {_name(p, vias)}\\NoEOffs, {speed}, fine, tool0;  ! {_label(p, vias)}")
        lines += _stops(p, lambda text: f"    TPWrite \"{text}\";\n    Stop;",
                        f"    WaitTime {program.measure_s:g};  ! measure experiment {p.experiment}")
    lines += ["  ENDPROC", "ENDMODULE"]
    return "\n".join(lines) + "\n"


def krl(problem: Problem, program: Program, plan: str, file: str = FILES["krl"]) -> str:
    """KRL: its ``DEF`` names the file (``file``'s stem), as a KUKA controller requires."""
    ctrl, vias = controller(problem), _vias(program)
    people = joint_scales(problem)
    name = _identifier(Path(file).stem)[:24]
    lines = [f"DEF {name}()"] + ["  " + h for h in _header(problem, program, ";", plan)]
    lines += ["  ; axis values in deg (controller convention); PTP at the axis speeds BAS(#INITMOV) sets",
              "  BAS(#INITMOV, 0)"]
    for p in program.points:
        axes = ", ".join(f"A{k + 1} {x / s:.{DEG_DIGITS}f}" for k, (x, s) in enumerate(zip(ctrl(p.q), people)))
        lines.append(f"  PTP {{AXIS: {axes}}}  ; {_label(p, vias)}")
        lines += _stops(p, lambda text: f"  ; {text}\n  HALT", f"  WAIT SEC {program.measure_s:g}  ; measure experiment "
                                                                f"{p.experiment}")
    lines.append("END")
    return "\n".join(lines) + "\n"


def poses_yaml(problem: Problem, program: Program, plan: str) -> str:
    lines = _header(problem, program, "#", plan)
    lines.append("# robot_calibration capture poses (rad, the URDF's angles), in program order; the checked via "
                 "points between them are in the JSON program (--format json)")
    names = "[" + ", ".join(json.dumps(j) for j in program.joints) + "]"
    for p in program.points:
        if p.kind == "experiment":
            lines += [f"# experiment {p.experiment}" + (f": {p.stop_before}" if p.stop_before else ""),
                      f"- joints: {names}",
                      "  positions: [" + ", ".join(f"{x:.{RAD_DIGITS}f}" for x in p.q) + "]"]
    return "\n".join(lines) + "\n"


def trajectory_json(problem: Problem, program: Program, plan: str) -> str:
    record = {
        "format": "casadi-design program", "problem": problem.name, "plan_file": plan,
        "units": {"positions": "rad (m for prismatic joints), model angles", "time": "s", "clearance": "mm"},
        "joint_names": list(program.joints),
        "points": [{"positions": p.q.tolist(), "time_from_start_s": p.time_s, "experiment": p.experiment,
                    "kind": p.kind, "stop_before": p.stop_before, "stop_after": p.stop_after} for p in program.points],
        "order": list(program.order), "measure_s": program.measure_s, "time_s": program.time_s,
        "file_order_time_s": program.file_time_s, "file_order_straight_time_s": program.file_straight_s,
        "file_order_blocked_moves": program.file_blocked, "load_changes": program.load_changes,
        "moves": [{"to": "home" if k == len(program.order) else program.order[k], "vias": path.vias,
                   "time_s": path.time_s, "clearance_mm": path.clearance_m * 1e3,
                   "mesh_clearance_mm": path.mesh_m * 1e3, "beam_broken": path.beam}
                  for k, path in enumerate(program.paths)],
    }
    return json.dumps(json_ready(record), indent=2, allow_nan=False) + "\n"


WRITERS = {"urscript": urscript, "rapid": rapid, "krl": krl, "yaml": poses_yaml, "json": trajectory_json}


def _identifier(name: str) -> str:
    """``name`` as a program identifier (letters, digits, underscores; a letter first)."""
    out = "".join(c if c.isalnum() else "_" for c in name)
    return out if out[:1].isalpha() else f"p_{out}"


def program_text(problem: Problem, program: Program, fmt: str, plan: str, file: str | None = None) -> str:
    """The program in format ``fmt`` (:data:`FILES`); ``plan`` names the plan file in its
    header; ``file``: the file it is written to (None: ``FILES[fmt]``), whose name KRL's
    ``DEF`` repeats."""
    check_format(problem, fmt)
    if fmt == "krl":
        return krl(problem, program, plan, file or FILES[fmt])
    return WRITERS[fmt](problem, program, plan)

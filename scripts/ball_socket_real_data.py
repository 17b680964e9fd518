"""identify on MUKCa's real ball-in-socket recordings: every robot trained on one placement, every
other placement held out; the figures docs/ball-socket.md gives.

    python scripts/ball_socket_real_data.py [--data ../shared/real_data/mukca] [--robots panda_2,panda_4]

For each robot (the problem file of its kind in examples/, the placement trained on: panda_2's
``front_center`` and panda_4's ``front`` as the authors', the first folder for the others):
held-out consistency and median spacing error (mm) of the nominal model, of the calibration
(what ``casadi-design identify`` prints, the same function) and its prediction, the consistency
with the ball relocated on the hand at each placement, what calibrated.urdf holds where the chosen
model's compliances have no place in it, and where the authors' calibrated URDF is published,
theirs on the same placements (Pinocchio, their ``ball_link``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pinocchio as pin

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from casadi_design.calibrated.artefact_report import placement_means  # noqa: E402
from casadi_design.identification.artefact_fit import calibrate_artefact, figures, relocated  # noqa: E402
from casadi_design.identification.recordings import read_recordings  # noqa: E402
from casadi_design.problem.build import load_problem  # noqa: E402

#: robot folder -> (problem file, placement trained on)
ROBOTS = {"panda_2": ("panda_ball_socket", "front_center"), "panda_4": ("panda_ball_socket", "front"),
          "panda_1_with_sensor": ("panda_bota_ball_socket", None), "kuka_14": ("iiwa14_ball_socket", None),
          "dinova_1": ("gen3lite_ball_socket", None), "dinova_2": ("gen3lite_ball_socket", None)}


def robot_case(data: Path, robot: str) -> tuple[Path, str, list[str]]:
    """``robot``'s problem file, the placement trained on (:data:`ROBOTS`; else its first folder)
    and every placement of it in MUKCa's folder ``data``."""
    name, train = ROBOTS[robot]
    places = sorted(p.name for p in (data / "data" / robot).iterdir() if p.is_dir())
    return ROOT / ("problems" if name == "panda_ball_socket" else "examples") / f"{name}.toml", train or places[0], places


def authors(urdf: Path, problem, rec) -> np.ndarray:
    """Consistency, spacing error and consistency with the ball relocated on the hand (m) of the
    authors' calibrated URDF at each of ``rec``'s placements, (P, 3) (their ``ball_link``, the
    chain's joints first)."""
    model = pin.buildModelFromUrdf(str(urdf))
    data, fid = model.createData(), model.getFrameId("ball_link")
    out = []
    for g in range(rec.P):
        rows = rec.placement == g
        P, R = [], []
        for q in rec.Q[rows]:
            full = pin.neutral(model)
            full[:len(q)] = q
            pin.framesForwardKinematics(model, data, full)
            P.append(data.oMf[fid].translation.copy())
            R.append(data.oMf[fid].rotation.copy())
        k = rec.point[rows]
        moved = relocated(np.array(R), np.array(P), k, np.eye(3 * len(k)))[1]
        out.append((*figures(problem.artefact, np.array(P), k), moved))
    return np.array(out)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default=str(ROOT.parent / "shared" / "real_data" / "mukca"))
    parser.add_argument("--robots", default=",".join(ROBOTS))
    args = parser.parse_args()
    data = Path(args.data)
    print("robot                train          held out  nominal  calibrated (predicted)  authors | "
          "median spacing: calibrated  authors | ball relocated: calibrated  authors   model  time")
    for robot in args.robots.split(","):
        path, train, places = robot_case(data, robot)
        problem = load_problem(path)
        t0 = time.perf_counter()
        rec = read_recordings(problem, [str(data / "data" / robot / train)])
        valid = read_recordings(problem, [str(data / "data" / robot / p) for p in places if p != train], "--validation")
        cal = calibrate_artefact(problem, rec, valid)
        wall = time.perf_counter() - t0
        v = cal.validation
        mean = placement_means(v)  # mm, as identification.json's "validation"
        theirs = data / "calibrated_urdf" / robot / "panda.urdf"
        per = authors(theirs, problem, valid) if theirs.exists() else None
        a = None if per is None else (per[:, 0].mean(), np.median(per[:, 1]), per[:, 2].mean())
        print(f"{robot:20s} {train:14s} {len(v):8d}  {mean['nominal_consistency_mm']:7.3f}  {mean['consistency_mm']:10.3f} "
              f"({mean['predicted_consistency_mm']:.3f})      " + (f"{a[0] * 1e3:7.3f}" if a else "      -")
              + f" | {mean['median_spacing_mm']:26.3f}  " + (f"{a[1] * 1e3:7.3f}" if a else "      -")
              + f" | {mean['relocated_consistency_mm']:26.3f}  " + (f"{a[2] * 1e3:7.3f}" if a else "      -")
              + f"   {cal.model} ({len(cal.names)}){'' if cal.field is None else ', field'}  {wall:.0f} s")
        if cal.urdf is not None:  # what calibrated.urdf holds: the best model without the weight's compliances
            u = placement_means(cal.urdf.validation)
            print(f"    calibrated.urdf ({cal.urdf.model}, {len(cal.urdf.names)}): held out {u['consistency_mm']:.3f} "
                  f"(predicted {u['predicted_consistency_mm']:.3f}), median spacing {u['median_spacing_mm']:.3f}")
        for g, j in enumerate(v):
            print(f"    {j.name:16s} consistency {j.consistency_m * 1e3:.3f} (predicted {j.predicted_consistency_m * 1e3:.3f},"
                  f" nominal {j.nominal_consistency_m * 1e3:.2f})  spacing {j.spacing_m * 1e3:.3f}  ball moved "
                  f"{np.linalg.norm(j.moved_m) * 1e3:.2f} mm ({j.moved_std:.1f} std), relocated "
                  f"{j.relocated_consistency_m * 1e3:.3f}, beyond the prediction {j.beyond} of {j.rows}"
                  + ("" if per is None else f" | authors: consistency {per[g, 0] * 1e3:.3f}, spacing {per[g, 1] * 1e3:.3f}"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

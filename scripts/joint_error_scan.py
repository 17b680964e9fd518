"""Is the error no parameter explains an error of the joint angles? A periodogram of the residuals.

    python scripts/joint_error_scan.py [CASE.toml MEASUREMENTS.csv] [--terms 6] [--splits 2]

Default: IPA's UR10, all 2773 rows (``tests/data/ipa_ur10``). ``identify``'s default model is
fitted to every row; its residuals ``r_i`` (tracker frame, m) are regressed, for each joint j and
each N cycles per revolution (0.5 to 400 by 0.25), on an angle error of that joint,

    r_i ~ J_j(q_i) (a sin(N q_ij) + b cos(N q_ij)),

with ``J_j`` the calibrated robot's position Jacobian column (central differences, tracker
frame) and the calibration's own Jacobian projected out (what the fitted parameters absorb does
not count). Printed: per joint the three largest shares of the residuals' variance with their
amplitude (arcsec); then the greedy model of ``--terms`` such terms chosen on a random half of
the rows and judged on the other half, the calibration's parameters refitted with it
(``--splits`` halves). Units: residuals in mm, amplitudes in arcsec.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from casadi_design.runtime.threads import fixed_blas  # noqa: E402

fixed_blas()  # one BLAS thread, as every command (before numpy loads)

import numpy as np  # noqa: E402

from casadi_design.cli.identify import load_without_cell  # noqa: E402
from casadi_design.identification.calibrate import calibrate  # noqa: E402
from casadi_design.identification.measurements import FileFormat, read_measurements  # noqa: E402

IPA = ROOT / "tests" / "data" / "ipa_ur10"
ARCSEC = 180.0 / np.pi * 3600.0
N_GRID = np.arange(0.5, 400.01, 0.25)
#: The greedy model searches the N that the scan finds (on IPA every peak lies below 40).
N_GREEDY = np.arange(0.5, 60.01, 0.25)


def residuals(case: str, path: str, fmt: FileFormat) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The default calibration's rows used: joints Q (m, n), residuals r (m, 3), joint Jacobian
    columns J (m, n, 3) and the calibration's Jacobian C (3 m, L), all in the tracker frame."""
    problem = load_without_cell(case)
    meas = read_measurements(problem, path, fmt)
    cal = calibrate(problem, meas)
    f = cal.fit
    print(f"{case}: {meas.m} rows, model {cal.model}, {len(cal.outliers)} excluded")
    h = 1e-6
    J = np.stack([(f.tracker_points(meas.Q + h * e, meas.F)[:, 0] - f.tracker_points(meas.Q - h * e, meas.F)[:, 0])
                  / (2 * h) for e in np.eye(meas.Q.shape[1])], axis=1)
    u = f.used
    C = np.einsum("ab,mbl->mal", f.T0[:3, :3], f.J[u]).reshape(-1, f.J.shape[2])
    return meas.Q[u], cal.residual_axes_m[u, 0, :], J[u], C / np.linalg.norm(C, axis=0)


def columns(Q: np.ndarray, J: np.ndarray, terms: list[tuple[int, float]]) -> np.ndarray:
    """The regressors of the angle-error terms (joint j, N): (3 m, 2 per term)."""
    out = [(J[:, j] * f(N * Q[:, j])[:, None]).ravel() for j, N in terms for f in (np.sin, np.cos)]
    return np.array(out).T if out else np.zeros((3 * len(Q), 0))


def scan(Q: np.ndarray, J: np.ndarray, y: np.ndarray, basis: np.ndarray, j: int,
         grid: np.ndarray) -> list[tuple[float, float, float]]:
    """For each N of ``grid``: the share of ``y`` that joint j's term of N explains, orthogonal to
    ``basis``, with N and the term's amplitude (rad)."""
    out = []
    for N in grid:
        X = columns(Q, J, [(j, N)])
        X = X - basis @ (basis.T @ X)
        c, *_ = np.linalg.lstsq(X, y, rcond=None)
        out.append((float(np.sum((X @ c) ** 2) / (y @ y)), float(N), float(np.hypot(*c))))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("case", nargs="?", default=str(IPA / "ipa_ur10.toml"))
    parser.add_argument("measurements", nargs="?", default=str(IPA / "measurements_random_poses_xyz.csv"))
    parser.add_argument("--terms", type=int, default=6)
    parser.add_argument("--splits", type=int, default=2)
    args = parser.parse_args()
    fmt = FileFormat(units="mm", columns=(("measurement_x", "meas_x"), ("measurement_y", "meas_y"),
                                          ("measurement_z", "meas_z")))
    Q, r, J, C = residuals(args.case, args.measurements, fmt)
    names = load_without_cell(args.case).robot.joints
    y = r.ravel()
    basis, _ = np.linalg.qr(C)
    rest = y - basis @ (basis.T @ y)
    print(f"residual RMS per value {1e3 * np.sqrt(np.mean(y**2)):.4f} mm")
    moving = [j for j in range(Q.shape[1]) if np.max(np.linalg.norm(J[:, j], axis=1)) > 1e-3]
    for j in moving:
        shares = scan(Q, J, rest, basis, j, N_GRID)
        peaks = [s for k, s in enumerate(shares) if 0 < k < len(shares) - 1
                 and s[0] >= shares[k - 1][0] and s[0] >= shares[k + 1][0]]
        print(f"{names[j]:<22}" + "  ".join(f"N {N:6.2f}: {100 * e:5.1f} % ({a * ARCSEC:4.0f} arcsec)"
                                              for e, N, a in sorted(peaks, reverse=True)[:3]))
    m = len(Q)
    for seed in range(args.splits):
        A = np.zeros(m, dtype=bool)
        A[np.random.default_rng(seed).permutation(m)[: m // 2]] = True
        ia, ib = np.repeat(A, 3), np.repeat(~A, 3)
        terms: list[tuple[int, float]] = []
        for _ in range(args.terms):
            X = np.hstack([C, columns(Q, J, terms)])[ia]
            basis_a, _ = np.linalg.qr(X)
            ya = y[ia] - basis_a @ (basis_a.T @ y[ia])
            terms.append(max((share, (j, N)) for j in moving
                             for share, N, _ in scan(Q[A], J[A], ya, basis_a, j, N_GREEDY))[1])
        held = []
        for K in (0, len(terms)):
            X = np.hstack([C, columns(Q, J, terms[:K])])
            c, *_ = np.linalg.lstsq(X[ia], y[ia], rcond=None)
            held.append(1e3 * np.sqrt(np.mean((y[ib] - X[ib] @ c) ** 2)))
        print(f"half {seed + 1}: {len(terms)} terms chosen on it "
              f"({', '.join(f'{names[j]} {N:g}' for j, N in terms)}); the other half's RMS per value "
              f"{held[0]:.4f} mm calibrated, {held[1]:.4f} mm with them")


if __name__ == "__main__":
    main()

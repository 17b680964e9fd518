"""[calibration.prior]: a MAP fit of the problem's own parameters, as a candidate model of
identify, on FIGAROH's TIAGo measurements: optimality of the estimate, the plain fit as the
prior widens, the closed-form leave-one-out error against refits, and the file's errors."""

import math

import numpy as np
import pytest

from casadi_design.cli import main
from casadi_design.errors import ProblemError
from casadi_design.identification.choice import cross_validate, cv_error
from casadi_design.identification.fit import fit, fit_model, register, row_errors
from casadi_design.identification.measurements import read_measurements
from tests.conftest import build, read_raw
from tests.identification.test_real_data import PROBLEM, TRAINING

PRIOR = {"length_m": 1e-3, "angle_rad": 1e-2, "offset_rad": 0.05}


def _problem(prior):
    raw = read_raw(PROBLEM)
    if prior is not None:
        raw["calibration"]["prior"] = prior
    return build(raw, str(PROBLEM))


@pytest.fixture(scope="module")
def tiago_prior():
    problem = _problem(PRIOR)
    meas = read_measurements(problem, str(TRAINING))
    problem, _, T0, _ = register(problem, "tracker", meas)  # the measured point located
    return problem, meas, T0


def _fit(problem, meas, T0, prior, used=None):
    used = np.ones(meas.m, dtype=bool) if used is None else used
    return fit(problem, fit_model(problem, "tracker", None, prior), meas, T0, used)


def test_the_map_estimate_is_stationary_and_its_prior_is_the_groups(tiago_prior):
    problem, meas, T0 = tiago_prior
    f = _fit(problem, meas, T0, True)
    names = f.fit.model.parameter_names
    std = f.fit.prior_std
    for name, s in zip(names, std):
        if name.startswith(("base.", "tool.")):
            assert s == math.inf
        elif name.endswith(".offset"):
            assert s == (PRIOR["length_m"] if name.startswith("torso_lift") else PRIOR["offset_rad"])
        else:
            assert s == PRIOR["length_m" if name.rpartition(".")[2].startswith("t") else "angle_rad"]
    # d/dX (|r|^2 + sigma^2 |X / std|^2) / 2 = -J^T r + diag((sigma / std)^2) X = 0 at the MAP
    # estimate (J = dh/dX of the whitened values at the estimate, r = y - h)
    J, r = f.J[f.used].reshape(-1, len(names)), f.r[f.used].reshape(-1)
    gradient = -J.T @ r + f.prior_information * f.X
    assert np.max(np.abs(gradient) / (np.linalg.norm(J, axis=0) * problem.sigma_m)) < 1e-6
    # the prior pulls toward 0: a smaller weighted norm than the least squares, a larger residual
    plain = _fit(problem, meas, T0, False)
    held = std < math.inf
    assert np.linalg.norm((f.X / std)[held]) < np.linalg.norm((plain.X / std)[held])
    assert np.sum(f.r**2) > np.sum(plain.r**2)


def test_a_wide_prior_gives_the_least_squares_estimate(tiago_prior):
    problem, meas, T0 = tiago_prior
    wide = _problem({k: v * 1e6 for k, v in PRIOR.items()})
    wide, _, _, _ = register(wide, "tracker", meas)
    plain, map_ = _fit(problem, meas, T0, False), _fit(wide, meas, T0, True)
    scale = np.linalg.norm(plain.J.reshape(-1, len(plain.X)), axis=0)
    assert np.max(np.abs((map_.X - plain.X) * scale)) < 1e-7  # m at the measured points


def test_the_closed_form_left_out_error_matches_refits(tiago_prior):
    """PRESS of the ridge fit (linearised) against fitting without the row and predicting it."""
    problem, meas, T0 = tiago_prior
    f = _fit(problem, meas, T0, True)
    e, why = cross_validate(problem, f, meas)
    assert not why
    cv = cv_error(e)[0]
    refits = []
    for i in range(meas.m):
        used = np.ones(meas.m, dtype=bool)
        used[i] = False
        g = _fit(problem, meas, T0, True, used)
        refits.append(row_errors(problem, g, meas, [i])[0])
    assert cv == pytest.approx(math.sqrt(np.mean(np.square(refits))), rel=0.03)


def test_bad_priors_and_model_prior_without_one_are_one_line(tmp_path, capsys):
    raw = read_raw(PROBLEM)
    raw["calibration"]["prior"] = {"length_m": 0.0}
    with pytest.raises(ProblemError, match=r"\[calibration.prior\].length_m: must be positive, got 0.0"):
        build(raw, str(PROBLEM))
    raw["calibration"]["prior"] = {}
    with pytest.raises(ProblemError, match=r"\[calibration.prior\]: gives no standard deviation; give one or more of"):
        build(raw, str(PROBLEM))
    assert main(["identify", str(PROBLEM), "--measurements", str(TRAINING), "--model", "prior",
                 "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "--model prior: the problem file has no [calibration.prior]" in err and err.count("\n") == 1

"""The model a user asked for, held against registration only: the warning says which it is,
a model that predicts worse or one that could not be cross-validated, and why. auto's
one-standard-error rule on the paired differences of the rows' errors: its standard error
against a Monte Carlo of the rows, and the choice it makes where the unpaired one would not."""

import math
from types import SimpleNamespace

import numpy as np

from casadi_design.identification.choice import Candidate, choose, cv_error


def _candidate(name: str, L: int, cv_m: float, why: str = "") -> Candidate:
    return Candidate(name, SimpleNamespace(model=SimpleNamespace(L=L)), 1e-3, cv_m, 1e-4, why)


def test_the_warning_beside_registration_only_says_which_and_why():
    registration = _candidate("registration", 9, 4.9e-3)
    worse = _candidate("identifiable", 33, 5.2e-3)
    chosen, (warning,) = choose([registration, worse], "identifiable")
    assert chosen is worse
    assert warning.startswith("the identifiable model predicts new poses worse (5.200 mm cross-validated) than "
                              "registration only (4.900 mm): it fits what the model misses")
    unknown = _candidate("identifiable", 33, math.nan, "row 4 is needed to identify it")
    chosen, (warning,) = choose([registration, unknown], "identifiable")
    assert chosen is unknown
    assert warning.startswith("the identifiable model could not be cross-validated (row 4 is needed to identify "
                              "it), registration only could (4.900 mm): whether it predicts new poses better is "
                              "not known")
    assert choose([registration, _candidate("identifiable", 33, 4.0e-3)], "identifiable")[1] == []


def _judged(name: str, names: tuple[str, ...], e: np.ndarray, loaded: bool = False) -> Candidate:
    cv, se = cv_error(e)
    model = SimpleNamespace(L=len(names), parameter_names=names, gravity=loaded, loaded=loaded)
    return Candidate(name, SimpleNamespace(model=model), 1e-3, cv, se, cv_errors_m=e)


def _rows(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows' errors (m) of a small and a larger model on the same n rows: what the rows share
    (a hard row is hard for both) and, per model, a little of its own; the larger 3 % better."""
    shared = 2e-4 * rng.chisquare(3, n) ** 0.5
    return shared * (1 + 0.02 * rng.normal(size=n)), 0.97 * shared * (1 + 0.02 * rng.normal(size=n))


def test_the_paired_standard_error_is_the_spread_of_the_difference_over_draws_of_the_rows():
    rng = np.random.default_rng(0)
    draws = [_rows(rng, 60) for _ in range(4000)]
    spread = np.std([cv_error(a)[0] - cv_error(b)[0] for a, b in draws])
    formula = np.mean([cv_error(a, b)[1] for a, b in draws])
    assert abs(formula / spread - 1) < 0.1
    alone = np.std([cv_error(a)[0] for a, _ in draws])  # the unpaired one: the spread of one model's
    assert abs(np.mean([cv_error(a)[1] for a, _ in draws]) / alone - 1) < 0.1
    assert spread < alone / 5


GEOMETRY = ("joint2.offset", "joint3.offset", "tool.tx")


def test_auto_takes_the_weight_when_it_is_better_on_the_same_rows():
    """The chosen geometry with the compliances under the robot's weight, 3 % better on every
    kind of row: within one standard error of either model alone, beyond the paired one, so
    it is chosen; a larger geometry as much better is not (the one-standard-error rule), nor a
    weight no better than the rows' noise."""
    small_e, large_e = _rows(np.random.default_rng(1), 60)
    small = _judged("identifiable", GEOMETRY, small_e)
    weight = _judged("identifiable + gravity", GEOMETRY + ("k.joint2",), large_e, loaded=True)
    assert small.cv_rms_m - weight.cv_rms_m < weight.cv_se_m
    assert choose([small, weight], "auto")[0] is weight
    larger = _judged("offsets + 1", GEOMETRY + ("joint2.tx",), large_e)
    assert choose([small, larger], "auto")[0] is small
    noise = _judged("identifiable + gravity", GEOMETRY + ("k.joint2",),
                    small_e * (1 + 0.02 * np.random.default_rng(2).normal(size=60)), loaded=True)
    assert choose([small, noise], "auto")[0] is small

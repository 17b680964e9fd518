"""The model a user asked for, held against registration only: the warning says which it is,
a model that predicts worse or one that could not be cross-validated, and why."""

import math
from types import SimpleNamespace

from casadi_design.identification.choice import Candidate, choose


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

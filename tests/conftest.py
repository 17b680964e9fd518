"""Shared problems and robots for the tests."""

from __future__ import annotations

import copy
import tomllib
from pathlib import Path

import pytest

from casadi_design.problem import build_problem, load_problem

ROOT = Path(__file__).resolve().parents[1]
PAPER = ROOT / "problems" / "paper_planar_2r.toml"


def paper_raw() -> dict:
    """The paper's problem file as a fresh, editable dict."""
    with open(PAPER, "rb") as fh:
        return copy.deepcopy(tomllib.load(fh))


def build(raw: dict):
    return build_problem(raw, "test.toml")


@pytest.fixture(scope="session")
def paper():
    return load_problem(PAPER)

"""Property-based fuzzing of problem files and plan CSVs through the command line.

Mutations of valid files (types, NaN/inf, shapes, names, encodings, truncation) either still
describe a valid case (exit 0) or give exit 2, exactly one stderr line ``error: <file>: ...``,
and no output files.
"""

import copy
import math

import numpy as np
import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from casadi_design.build import load_problem
from casadi_design.cli import main
from casadi_design.export import csv_text, plan_table
from casadi_design.solve import random_plan
from tests.conftest import PAPER, ROOT, read_raw

#: Examples per property: bounded so that the default suite stays fast.
EXAMPLES = 15
GEOMETRIC = ROOT / "problems" / "planar_2r_geometric.toml"

BAD_VALUES = st.sampled_from([
    math.nan, math.inf, -math.inf, -1.0, 0, 10**9, 1e300, "12", "0.1", "", "x", True, [], [[]],
    [1.0], ["1", "2"], [math.nan, 1.0], {"a": 1}, [[0.1, 0.2], [0.3]], "identifiable",
])
BAD_CELLS = st.sampled_from(["nan", "inf", "-inf", "", "abc", "1,5", "1e999", "0x10", "--1", "1;2", "\"", "1 2"])


def _leaves(table: dict, prefix: tuple = ()) -> list[tuple]:
    """Paths to every value of a parsed TOML table (into lists of tables too)."""
    out = []
    for key, value in table.items():
        path = prefix + (key,)
        out.append(path)
        if isinstance(value, dict):
            out += _leaves(value, path)
        elif isinstance(value, list) and value and all(isinstance(v, dict) for v in value):
            for i, v in enumerate(value):
                out += _leaves(v, path + (i,))
    return out


def _set(table: dict, path: tuple, value) -> None:
    for key in path[:-1]:
        table = table[key]
    if value is _DELETE:
        del table[path[-1]]
    else:
        table[path[-1]] = value


_DELETE = object()


@st.composite
def problem_files(draw) -> bytes:
    raw = read_raw(draw(st.sampled_from([PAPER, GEOMETRIC])))
    kind = draw(st.sampled_from(["value", "value", "delete", "unknown", "encoding", "truncate"]))
    if kind in ("value", "delete", "unknown"):
        raw = copy.deepcopy(raw)
        path = draw(st.sampled_from(_leaves(raw)))
        if kind == "unknown":
            path = path[:-1] + (path[-1] + "_typo",)
        _set(raw, path, _DELETE if kind == "delete" else draw(BAD_VALUES))
        try:
            return tomli_w.dumps(raw).encode()
        except (TypeError, ValueError):  # not representable in TOML (e.g. a list of mixed types)
            return b"[robot\n"
    text = tomli_w.dumps(raw).encode()
    if kind == "truncate":
        return text[: draw(st.integers(0, len(text) - 1))]
    return draw(st.sampled_from([
        text.decode().encode("utf-16"), b"\xff\xfe" + text, text[:40] + b"\xff\x00\x01" + text[40:],
        b"\x89PNG\r\n\x1a\n\x00\x00", "\ufeff".encode() + text.replace(b"sigma_m", b"sigma_\xc3\xa9m"),
    ]))


def _check_run(argv: list[str], named: str, out, capsys) -> None:
    rc = main(argv)
    _, err = capsys.readouterr()
    if rc == 0:
        return
    lines = err.strip().splitlines()
    assert rc == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: ") and named in lines[0], err
    hint = lines[0].split("; ", 1)
    assert len(hint) == 2 and hint[1].strip(), f"no hint after the semicolon: {lines[0]}"
    assert not out.exists(), f"{out} written by a failed run"


@settings(max_examples=EXAMPLES, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=problem_files())
def test_mutated_problem_files(data, tmp_path_factory, capsys):
    folder = tmp_path_factory.mktemp("fuzz")
    path, out = folder / "case.toml", folder / "out"
    path.write_bytes(data)
    _check_run(["solve", str(path), "--m", "3", "--criteria", "D", "--starts", "1", "--jobs", "1",
                "--quiet", "--out", str(out)], str(path), out, capsys)


@pytest.fixture(scope="module")
def plan_text(paper) -> str:
    Q, F = random_plan(paper, 3, np.random.default_rng(0))
    return csv_text(*plan_table(paper, Q.T, F.T))


@st.composite
def plan_edits(draw, text: str) -> bytes:
    rows = [line.split(",") for line in text.strip().splitlines()]
    kind = draw(st.sampled_from(["cell", "cell", "header", "drop", "add", "semicolons", "encoding",
                                 "truncate", "trailing"]))
    if kind == "cell":
        r, c = draw(st.integers(1, len(rows) - 1)), draw(st.integers(0, len(rows[0]) - 1))
        rows[r][c] = draw(BAD_CELLS)
    elif kind == "header":
        rows[0][draw(st.integers(0, len(rows[0]) - 1))] = draw(st.sampled_from(["q9_deg", "", "joint1", "fx", "q1_deg"]))
    elif kind == "drop":
        c = draw(st.integers(0, len(rows[0]) - 1))
        rows = [row[:c] + row[c + 1:] for row in rows]
    elif kind == "add":
        rows = [row + [draw(st.sampled_from(["extra", "1.0"]))] for row in rows]
    elif kind == "trailing":
        rows = [row + [""] for row in rows]
    body = "\n".join(";".join(r) if kind == "semicolons" else ",".join(r) for r in rows) + "\n"
    if kind == "encoding":
        return draw(st.sampled_from([body.encode("utf-16"), b"\xff" + body.encode(), "\ufeff".encode() + body.encode(),
                                     body.encode().replace(b"\n", b"\x00\n")]))
    if kind == "truncate":
        return body.encode()[: draw(st.integers(0, len(body) - 1))]
    return body.encode()


@settings(max_examples=EXAMPLES, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_mutated_plan_csvs(data, plan_text, tmp_path_factory, capsys):
    folder = tmp_path_factory.mktemp("fuzz")
    path, out = folder / "plan.csv", folder / "out"
    path.write_bytes(data.draw(plan_edits(plan_text)))
    _check_run(["evaluate", str(PAPER), "--plan", str(path), "--quiet", "--out", str(out)], str(path), out, capsys)


def test_a_valid_problem_still_solves_after_the_fuzzer_helpers(tmp_path):
    """The mutation helpers leave the original untouched: a round trip through TOML loads."""
    path = tmp_path / "case.toml"
    path.write_text(tomli_w.dumps(read_raw(PAPER)))
    assert load_problem(path).model.parameter_names == ("k.joint1", "k.joint2")

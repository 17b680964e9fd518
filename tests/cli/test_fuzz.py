"""Property-based fuzzing of problem files and plan CSVs through the command line.

Mutations of valid files (types, NaN/inf, shapes, names, encodings, truncation) each carry
whether they leave a valid case (:attr:`Mutation.valid`): a valid one must run (exit 0, its
files written), an invalid one must give exit 2, exactly one stderr line
``error: <file>: ...; <hint>``, and no output files. Validity comes from the documented format
(docs/problem-format.md, :func:`casadi_design.records.export.read_plan_csv`), not from the reader under
test; where it depends on the drawn value (a number in range, a cut that keeps whole rows) it is
computed from that value.
"""

import copy
import csv
import math
import sys
import tomllib
from typing import Any, NamedTuple

import numpy as np
import pytest
import tomli_w
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from casadi_design.cli import main
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import load_problem
from casadi_design.records.export import csv_text, plan_table
from tests.conftest import PAPER, ROOT, read_raw

#: Examples per property: bounded so that the default suite stays fast.
EXAMPLES = 15
GEOMETRIC = ROOT / "problems" / "planar_2r_geometric.toml"

BAD_VALUES = st.sampled_from([
    math.nan, math.inf, -math.inf, -1.0, 0, 10**9, 1e300, "12", "0.1", "", "x", True, [], [[]],
    [1.0], ["1", "2"], [math.nan, 1.0], {"a": 1}, [[0.1, 0.2], [0.3]], "identifiable",
])
BAD_CELLS = st.sampled_from(["nan", "inf", "-inf", "", "abc", "1,5", "1e999", "0x10", "--1", "1;2", "\"", "1 2"])


class Mutation(NamedTuple):
    """A mutated input file and what the command must do with it."""

    data: bytes
    valid: bool  #: True: must run (exit 0); False: must be refused (exit 2, one line, nothing written)
    what: str  #: the mutation, for failure messages


# --------------------------------------------------------------------------- problem files

def _number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


#: The largest float whose square is finite: a noise or a load above it cannot be computed with
#: (sigma^2, |F|^2 overflow), so it must be refused like a negative one.
SQUARABLE = math.sqrt(sys.float_info.max)


def _positive(v: Any) -> bool:
    """A TOML "float > 0" (an integer is accepted for a float) whose square is finite."""
    return _number(v) and 0 < v <= SQUARABLE


def _integer(low: int, high: int):
    return lambda v: isinstance(v, int) and not isinstance(v, bool) and low <= v <= high


#: Leaves of the two problem files whose value may change and still give a valid case, with the
#: values the format accepts (docs/problem-format.md); any other leaf accepts only its own value
#: (a name of a frame, joint, component or criterion; a shape; a table). Not here:
#: ``parameters = "identifiable"`` of the geometric case, a valid value that selects 6
#: parameters, too many for its m = [2, 4] with 2 measured values per experiment (refused).
ACCEPTS = {
    ("name",): lambda v: isinstance(v, str),
    ("description",): lambda v: isinstance(v, str),
    ("measurement", "sigma_m"): _positive,
    ("test_poses", "elbow"): lambda v: isinstance(v, str) and v in ("up", "down"),
    ("test_poses", "line_m", "nodes"): _integer(2, 5_000),
    ("experiments", "force", "magnitude_N"): _positive,
    ("design", "parameter_scaling"): lambda v: isinstance(v, str) and v in ("column", "none"),
    ("solver", "starts"): _integer(1, 100_000),
    ("solver", "seed"): _integer(0, 2**63 - 1),
}
#: Leaves of the two problem files that may be left out (a default applies).
OPTIONAL = {("name",), ("description",), ("calibration", "compliant_joints"), ("test_poses", "components"),
            ("test_poses", "elbow"), ("design", "parameter_scaling"), ("solver",), ("solver", "starts"),
            ("solver", "seed")}


def _same(a: Any, b: Any) -> bool:
    """Equal values of equal TOML types (``1 != 1.0 != True`` here; NaN is never the same)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


def _accepted(path: tuple, value: Any, original: Any) -> bool:
    return _same(value, original) or path in ACCEPTS and ACCEPTS[path](value)


def _still_valid(original: dict, table: dict, prefix: tuple = ()) -> bool:
    """Whether ``table`` (parsed TOML) is a valid case, ``original`` being one: no key that
    ``original`` lacks, missing keys all optional, changed values all accepted."""
    if set(table) - set(original):
        return False
    for key, value in original.items():
        path = prefix + (key,)
        if key not in table:
            if path not in OPTIONAL:
                return False
        elif isinstance(value, dict) and isinstance(table[key], dict):
            if not _still_valid(value, table[key], path):
                return False
        elif not _accepted(path, table[key], value):
            return False
    return True


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


def _get(table: dict, path: tuple) -> Any:
    for key in path:
        table = table[key]
    return table


def _set(table: dict, path: tuple, value) -> None:
    for key in path[:-1]:
        table = table[key]
    if value is _DELETE:
        del table[path[-1]]
    else:
        table[path[-1]] = value


_DELETE = object()


def _edited(raw: dict, kind: str, path: tuple, value: Any) -> Mutation:
    """``raw`` with the leaf ``path`` set to ``value`` (kind "value"), deleted ("delete"), or
    with a misspelt key ``<leaf>_typo = value`` beside it ("unknown")."""
    name = ".".join(map(str, path))
    if kind == "unknown":
        valid, what = False, f"unknown key {name}_typo = {value!r}"  # no table of these files takes any key
        path = path[:-1] + (path[-1] + "_typo",)
    elif kind == "delete":
        valid, what = path in OPTIONAL, f"{name} deleted"
    else:
        valid, what = _accepted(path, value, _get(raw, path)), f"{name} = {value!r}"
    raw = copy.deepcopy(raw)
    _set(raw, path, _DELETE if kind == "delete" else value)
    try:
        return Mutation(tomli_w.dumps(raw).encode(), valid, what)
    except (TypeError, ValueError):  # not representable in TOML (e.g. a list of mixed types)
        return Mutation(b"[robot\n", False, f"{what} (not TOML: an unclosed table header instead)")


def _truncated(raw: dict, text: bytes, cut: int) -> Mutation:
    """The first ``cut`` bytes of ``text`` (``raw`` written as TOML): valid when they are TOML
    that only leaves out optional keys and shortens accepted values (``seed = 20`` of 2024)."""
    try:
        valid = _still_valid(raw, tomllib.loads(text[:cut].decode()))
    except (UnicodeDecodeError, tomllib.TOMLDecodeError):
        valid = False
    return Mutation(text[:cut], valid, f"cut after byte {cut}: ...{text[max(cut - 30, 0):cut]!r}")


def _encodings(text: bytes) -> list[Mutation]:
    """``text`` in encodings and byte forms that are not UTF-8 TOML, and with a byte-order mark
    (accepted) and a key renamed to a non-ASCII name (unknown unless there was no such key)."""
    renamed = "\ufeff".encode() + text.replace(b"sigma_m", b"sigma_\xc3\xa9m")
    return [Mutation(text.decode().encode("utf-16"), False, "UTF-16"),
            Mutation(b"\xff\xfe" + text, False, "a UTF-16 byte-order mark before UTF-8"),
            Mutation(text[:40] + b"\xff\x00\x01" + text[40:], False, "binary bytes inside"),
            Mutation(b"\x89PNG\r\n\x1a\n\x00\x00", False, "a PNG header"),
            Mutation(renamed, b"sigma_m" not in text, "byte-order mark, sigma_m renamed sigma_\u00e9m")]


@st.composite
def problem_files(draw) -> Mutation:
    raw = read_raw(draw(st.sampled_from([PAPER, GEOMETRIC])))
    kind = draw(st.sampled_from(["value", "value", "delete", "unknown", "encoding", "truncate"]))
    if kind in ("value", "delete", "unknown"):
        path = draw(st.sampled_from(_leaves(raw)))
        return _edited(raw, kind, path, None if kind == "delete" else draw(BAD_VALUES))
    text = tomli_w.dumps(raw).encode()
    if kind == "truncate":
        return _truncated(raw, text, draw(st.integers(0, len(text) - 1)))
    return draw(st.sampled_from(_encodings(text)))


def _check_run(argv: list[str], mutation: Mutation, named: str, out, capsys) -> None:
    """The command ``argv`` on the mutated file ``named`` does what ``mutation.valid`` says."""
    rc = main(argv)
    _, err = capsys.readouterr()
    if mutation.valid:
        assert rc == 0, f"{mutation.what}: valid, so it must run; got exit {rc}: {err.strip()}"
        assert out.is_dir() and any(out.iterdir()), f"{mutation.what}: ran but wrote nothing in {out}"
        return
    lines = err.strip().splitlines()
    assert rc == 2, f"{mutation.what}: invalid, so it must be refused with exit 2; got exit {rc}: {err.strip()}"
    assert len(lines) == 1 and lines[0].startswith("error: ") and named in lines[0], err
    hint = lines[0].split("; ", 1)
    assert len(hint) == 2 and hint[1].strip(), f"no hint after the semicolon: {lines[0]}"
    assert not out.exists(), f"{out} written by a failed run"


@settings(max_examples=EXAMPLES, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(mutation=problem_files())
def test_mutated_problem_files(mutation, tmp_path_factory, capsys):
    folder = tmp_path_factory.mktemp("fuzz")
    path, out = folder / "case.toml", folder / "out"
    path.write_bytes(mutation.data)
    _check_run(["solve", str(path), "--m", "3", "--criteria", "D", "--starts", "1", "--jobs", "1",
                "--quiet", "--out", str(out)], mutation, str(path), out, capsys)


# --------------------------------------------------------------------------- plan CSVs

#: Columns of a plan that the reader skips (read_plan_csv: "the columns experiment, x_mm,
#: y_mm, z_mm are ignored") and the load columns of the paper's case (all needed).
IGNORED_COLUMNS = ("experiment", "x_mm", "y_mm", "z_mm")
FORCE_COLUMNS = ("fx_N", "fy_N")
#: Joint columns of the paper's arm (joints joint1, joint2): each names a joint k, by number
#: (q1, q2) or by name, in deg or rad; one of them per joint is enough.
JOINT_COLUMNS = {f"{name}_{unit}": k for k, joint in enumerate(("joint1", "joint2"))
                 for name in (f"q{k + 1}", joint) for unit in ("deg", "rad")}


def _cells(line: str) -> list[str]:
    return next(csv.reader([line]), [])


def _renamed_ok(header: list[str], c: int, name: str) -> bool:
    """Whether column ``c`` may be named ``name``: the same name, or another unused name of the
    same joint in the same unit (``joint1_deg`` as ``q1_deg``; its values stay in that unit)."""
    old = header[c]
    return name == old or (old in JOINT_COLUMNS and JOINT_COLUMNS.get(name) == JOINT_COLUMNS[old]
                           and name.rsplit("_", 1)[1] == old.rsplit("_", 1)[1] and name not in header)


def _truncated_plan_ok(body: str, cut: int, width: int) -> bool:
    """Whether the first ``cut`` characters of ``body`` are a plan: the header and at least one
    row, the last row whole or cut in its last cell (z_mm, ignored)."""
    _, *rows = body[:cut].split("\n")  # no row: the cut is in the header
    return bool(rows) and any(rows) and (not rows[-1] or len(_cells(rows[-1])) == width)


@st.composite
def plan_edits(draw, text: str) -> Mutation:
    rows = [line.split(",") for line in text.strip().splitlines()]
    header, width = list(rows[0]), len(rows[0])
    kind = draw(st.sampled_from(["cell", "cell", "header", "drop", "add", "semicolons", "encoding",
                                 "truncate", "trailing"]))
    valid = {"add": False, "semicolons": False, "trailing": True}.get(kind)  # unknown column; ';'; empty cells
    what = kind
    if kind == "cell":
        r, c = draw(st.integers(1, len(rows) - 1)), draw(st.integers(0, width - 1))
        rows[r][c] = draw(BAD_CELLS)
        # no bad cell is a finite number: only an ignored column takes it, if it splits no cell
        valid = header[c] in IGNORED_COLUMNS and len(_cells(",".join(rows[r]))) == width
        what = f"row {r + 1}, column {header[c]} = {rows[r][c]!r}"
    elif kind == "header":
        c = draw(st.integers(0, width - 1))
        rows[0][c] = draw(st.sampled_from(["q9_deg", "", "joint1", "fx", "q1_deg"]))
        valid, what = _renamed_ok(header, c, rows[0][c]), f"column {header[c]} named {rows[0][c]!r}"
    elif kind == "drop":
        c = draw(st.integers(0, width - 1))
        rows = [row[:c] + row[c + 1:] for row in rows]
        valid, what = header[c] not in FORCE_COLUMNS, f"column {header[c]} dropped"  # joints: the other unit
    elif kind == "add":
        rows = [row + [draw(st.sampled_from(["extra", "1.0"]))] for row in rows]
    elif kind == "trailing":
        rows = [row + [""] for row in rows]
    body = "\n".join(";".join(r) if kind == "semicolons" else ",".join(r) for r in rows) + "\n"
    if kind == "encoding":
        return draw(st.sampled_from([Mutation(body.encode("utf-16"), False, "UTF-16"),
                                     Mutation(b"\xff" + body.encode(), False, "not UTF-8"),
                                     Mutation("\ufeff".encode() + body.encode(), True, "byte-order mark"),
                                     Mutation(body.encode().replace(b"\n", b"\x00\n"), False, "NUL bytes")]))
    if kind == "truncate":
        cut = draw(st.integers(0, len(body) - 1))
        return Mutation(body.encode()[:cut], _truncated_plan_ok(body, cut, width),
                        f"cut after character {cut}: ...{body[max(cut - 30, 0):cut]!r}")
    return Mutation(body.encode(), valid, what)


@pytest.fixture(scope="module")
def plan_text(paper) -> str:
    Q, F = random_plan(paper, 3, np.random.default_rng(0))
    return csv_text(*plan_table(paper, Q, F))


@settings(max_examples=EXAMPLES, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_mutated_plan_csvs(data, plan_text, tmp_path_factory, capsys):
    folder = tmp_path_factory.mktemp("fuzz")
    path, out = folder / "plan.csv", folder / "out"
    mutation = data.draw(plan_edits(plan_text))
    path.write_bytes(mutation.data)
    _check_run(["evaluate", str(PAPER), "--plan", str(path), "--quiet", "--out", str(out)], mutation,
               str(path), out, capsys)


def test_a_valid_problem_still_solves_after_the_fuzzer_helpers(tmp_path):
    """The mutation helpers leave the original untouched: a round trip through TOML loads."""
    raw = read_raw(PAPER)
    for path in _leaves(raw):
        _edited(raw, "delete", path, None)
    path = tmp_path / "case.toml"
    path.write_text(tomli_w.dumps(raw))
    assert load_problem(path).model.parameter_names == ("k.joint1", "k.joint2")

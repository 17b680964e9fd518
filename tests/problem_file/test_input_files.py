"""Bad input files and output folders: one-line errors, never a traceback, a hang or a wrong answer.

Plan CSVs raise :class:`ProblemError`, results files and output folders :class:`OutputError`,
each as ``<file>: <what is wrong>; <what to do>``.
"""

import copy
import json
import math
import os

import numpy as np
import pytest

from casadi_design.cli import main
from casadi_design.errors import ProblemError
from casadi_design.records.export import read_plan_csv
from casadi_design.plan.design import Design, StartRecord
from casadi_design.errors import OutputError
from casadi_design.records.files import prepare_out, read_results, write_atomic, write_json
from casadi_design.records.results import design_from_record, results_dict
from casadi_design.optimisation.solve import plan_scores
from casadi_design.execution.campaign import Settings, campaign_key
from casadi_design.execution.sweep import RESUME_FILES, Sweep, sweep_from_record, sweep_record
from tests.conftest import PAPER

HEADER = "q1_deg,q2_deg,fx_N,fy_N"
ROWS = "0,90,0,100\n90,-90,100,0\n45,-120,-60,80\n"
PLAN = HEADER + "\n" + ROWS
RESULTS_HINT = "; give a results file written by casadi-design solve or sweep"


def _write(path, data):
    if isinstance(data, str):
        data = data.encode()
    path.write_bytes(data)
    return path


def _one_line_with_hint(exc: Exception) -> None:
    """The message format: one line, ``<what is wrong>; <what to do>`` with a hint."""
    text = str(exc)
    assert "\n" not in text and "; " in text and text.rsplit("; ", 1)[1].strip()


@pytest.fixture
def plan(paper, tmp_path):
    """Q (rad) and F (N) of the reference plan ``PLAN``."""
    return read_plan_csv(paper, _write(tmp_path / "ref.csv", PLAN))


# --------------------------------------------------------------------------- plan CSV: the file

def test_plan_path_that_is_a_folder(paper, tmp_path):
    with pytest.raises(ProblemError, match="is a folder, not a plan file; give the CSV file") as err:
        read_plan_csv(paper, tmp_path)
    _one_line_with_hint(err.value)


def test_plan_path_that_is_a_pipe_does_not_hang(paper, tmp_path):
    fifo = tmp_path / "plan.csv"
    os.mkfifo(fifo)
    with pytest.raises(ProblemError, match="is not a regular file"):
        read_plan_csv(paper, fifo)


def test_empty_plan_path(paper):
    with pytest.raises(ProblemError, match="the plan file name is empty; give the CSV file"):
        read_plan_csv(paper, "")


@pytest.mark.parametrize("data, match", [
    (b"\xff\xfe\x00q\x001\x00", r"is UTF-16 text \(Excel 'Unicode Text'\), not UTF-8; save it as"),
    (b"\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", r"is a binary file \(it holds NUL bytes\), not UTF-8"),
    ("# poses de référence\n".encode("latin-1") + PLAN.encode(),
     r"is not UTF-8 text \(byte 0xe9 at offset 12\); save it as 'CSV UTF-8"),
])
def test_plan_not_utf8_text(paper, tmp_path, data, match):
    with pytest.raises(ProblemError, match=match) as err:
        read_plan_csv(paper, _write(tmp_path / "p.csv", data))
    _one_line_with_hint(err.value)


def test_plan_with_utf8_bom_reads_like_without(paper, tmp_path, plan):
    Q, F = read_plan_csv(paper, _write(tmp_path / "bom.csv", b"\xef\xbb\xbf" + PLAN.encode()))
    np.testing.assert_array_equal(Q, plan[0])
    np.testing.assert_array_equal(F, plan[1])


def test_plan_larger_than_10_MB_is_refused_before_reading(paper, tmp_path):
    big = tmp_path / "big.csv"
    with open(big, "wb") as fh:
        fh.truncate(11 * 2**20)  # sparse: nothing to read
    with pytest.raises(ProblemError, match="is 11.0 MB; a plan has at most 100000 experiments") as err:
        read_plan_csv(paper, big)
    _one_line_with_hint(err.value)


def test_plan_with_more_than_100000_rows(paper, tmp_path):
    path = _write(tmp_path / "long.csv", HEADER + "\n" + "0,90,0,100\n" * 100_001)
    with pytest.raises(ProblemError, match="has 100001 rows; a plan has at most 100000 experiments"):
        read_plan_csv(paper, path)


# --------------------------------------------------------------------------- plan CSV: the table

@pytest.mark.parametrize("text, match", [
    ("q1_deg;q2_deg,fx_N;fy_N\n0;90;0;100\n", "its header \\(line 1\\) has both ';' and ',' between names"),
    ("q1_deg;q2_deg;fx_N;fy_N\n0;90.5;0;100\n",
     "row 2, column 'q2_deg': '90.5' has a '.' in a file separated by ';', where ',' is the decimal point"),
])
def test_plan_with_semicolons(paper, tmp_path, text, match):
    with pytest.raises(ProblemError, match=match) as err:
        read_plan_csv(paper, _write(tmp_path / "excel.csv", text))
    _one_line_with_hint(err.value)


@pytest.mark.parametrize("text", [
    HEADER + ",,\n" + ROWS.replace("\n", ",,\n"),  # Excel: empty trailing columns
    HEADER + "\n" + ROWS.replace("\n", ",\n"),  # trailing commas in the rows only
    HEADER + ",\n" + ROWS,  # in the header only
    HEADER + "\n,,,\n" + ROWS + ",,,,\n",  # lines of empty cells
    HEADER + "\r\n" + ROWS.replace("\n", "\r\n"),  # Windows line ends
])
def test_plan_with_empty_trailing_cells_reads_like_without(paper, tmp_path, plan, text):
    Q, F = read_plan_csv(paper, _write(tmp_path / "p.csv", text))
    np.testing.assert_array_equal(Q, plan[0])
    np.testing.assert_array_equal(F, plan[1])


@pytest.mark.parametrize("text, match", [
    (HEADER + "\n0,90,0,100,7\n", "row 2 has 5 cells, the header has 4; give one value per column"),
    ("# by hand\n" + HEADER + "\n0,90,0,100\n0,90\n", "row 4 has 2 cells, the header has 4"),
    (HEADER + "\n0,90,0,100\n0,90,5,0,100\n", "row 3 has 5 cells, the header has 4.*decimal comma"),
    (HEADER + ",,\n0,90,0,100,,3\n", "row 2 has 6 cells, the header has 4"),
])
def test_plan_rows_of_another_length_than_the_header(paper, tmp_path, text, match):
    with pytest.raises(ProblemError, match=match) as err:
        read_plan_csv(paper, _write(tmp_path / "p.csv", text))
    _one_line_with_hint(err.value)


@pytest.mark.parametrize("cell", ["nan", "NaN", "inf", "-inf", "", "1e999"])
def test_plan_non_finite_cells(paper, tmp_path, cell):
    text = f"# by hand\n{HEADER}\n0,90,0,100\n0,{cell},0,100\n"
    with pytest.raises(ProblemError, match=r"row 4, column 'q2_deg': not a finite number") as err:
        read_plan_csv(paper, _write(tmp_path / "p.csv", text))
    _one_line_with_hint(err.value)


@pytest.mark.parametrize("text, match", [
    (HEADER + "\n", "no experiments below the header; give one row per experiment"),
    ("", "empty plan file; give a header row and one row per experiment"),
    ("# nothing\n\n", "empty plan file; give a header row and one row per experiment"),
    ("q1_deg,,q2_deg,fx_N,fy_N\n0,,90,0,100\n", "column 2 of the header has no name; name it"),
    ("q1_deg,q2_deg,q1_deg,fx_N,fy_N\n0,90,0,0,100\n", "column 'q1_deg' is given 2 times; give"),
    (HEADER + "\n0,x,0,100\n", "row 2, column 'q2_deg': expected a number, got 'x'; give a number"),
])
def test_plan_header_and_cells(paper, tmp_path, text, match):
    with pytest.raises(ProblemError, match=match) as err:
        read_plan_csv(paper, _write(tmp_path / "p.csv", text))
    _one_line_with_hint(err.value)


def test_bad_plan_is_one_error_line_and_exit_2_through_the_command(tmp_path, capsys):
    assert main(["evaluate", str(PAPER), "--plan", str(tmp_path)]) == 2
    assert capsys.readouterr().err == (f"error: {tmp_path}: is a folder, not a plan file; "
                                       "give the CSV file\n")


# --------------------------------------------------------------------------- results files

@pytest.fixture(scope="module")
def designs(paper):
    """Two designs (D and test-pose, m = 2) made without the solver: scores of fixed plans, each
    with a winning start and a failed one (infinite value and error)."""
    designs = []
    for criterion, deg, load in (("D", [[0, 90], [45, -120]], [[0, 100], [-60, 80]]),
                                 ("test-pose", [[90, -90], [45, -120]], [[100, 0], [-60, 80]])):
        Q, F = np.radians(deg), np.array(load, dtype=float)
        scores = plan_scores(paper, Q, F)
        won = StartRecord("Solve_Succeeded", 12, scores.value(criterion), scores.max_rms_error_m, True)
        failed = StartRecord("Restoration_Failed", 3, float("inf"), float("inf"), False)
        designs.append(Design(criterion, 2, Q, F, scores, won.status, (won, failed), 0.5, 2024))
    return designs


@pytest.fixture(scope="module")
def record(paper, designs):
    """A results record of the two designs."""
    return json.loads(json.dumps(results_dict(paper, designs)))  # JSON types, Infinity as float


def _results_file(tmp_path, record, name="results.json"):
    """``record`` written as other tools may write it: NaN and Infinity as JSON's extensions."""
    return _write(tmp_path / name, json.dumps(record))


def test_results_file_reads_back_with_infinite_values_of_failed_starts(tmp_path, record):
    path = _results_file(tmp_path, record)
    assert "Infinity" in path.read_text()  # the failed start, as Python's json writes it
    got = read_results(path)
    assert got["_path"] == str(path)
    d = design_from_record(got["designs"][1])
    assert d.criterion == "test-pose" and d.Q.shape == (2, 2) and d.starts[1].value == float("inf")
    assert read_results(tmp_path)["_path"] == str(path)  # the folder holding it


def test_our_results_files_are_standard_json_with_null_for_failed_starts(tmp_path, record):
    path = tmp_path / "results.json"
    write_json(path, record)
    text = path.read_text()
    assert "Infinity" not in text and "NaN" not in text and "null" in text
    json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    d = design_from_record(read_results(path)["designs"][1])
    assert d.starts[1].status == "Restoration_Failed" and np.isnan(d.starts[1].value)


def _assert_cell(got, want, nulls: bool, where: str) -> None:
    """A value read back is the value written: NaN as NaN, or as None when written as ``null``
    (``nulls``); anything else equal and of the same JSON type."""
    if isinstance(want, float) and math.isnan(want):
        if nulls:
            assert got is None, f"{where}: NaN written as null, read back as {got!r}"
        else:
            assert isinstance(got, float) and math.isnan(got), f"{where}: NaN written, read back {got!r}"
    else:
        assert got == want and _json_type(got) == _json_type(want), f"{where}: wrote {want!r}, read back {got!r}"


def _json_type(value) -> str:
    if value is None or isinstance(value, (bool, str)):
        return type(value).__name__
    return "number" if isinstance(value, (int, float)) else "other"


def _assert_same_design(got: Design, want: Design, nulls: bool, where: str) -> None:
    """``got`` (read back) is ``want`` exactly (JSON floats round-trip); the infinite value and
    error of a failed start come back infinite, or NaN when written as ``null`` (``nulls``)."""
    assert ((got.criterion, got.m, got.status, got.wall_s, got.seed, got.bound)
            == (want.criterion, want.m, want.status, want.wall_s, want.seed, want.bound)), where
    np.testing.assert_array_equal(got.Q, want.Q, err_msg=f"{where}.Q")
    np.testing.assert_array_equal(got.F, want.F, err_msg=f"{where}.F")
    assert got.scores.as_dict() == want.scores.as_dict(), f"{where}.scores"
    assert len(got.starts) == len(want.starts), f"{where}.starts"
    for k, (g, w) in enumerate(zip(got.starts, want.starts)):
        assert (g.status, g.iterations, g.feasible, g.origin) == (w.status, w.iterations, w.feasible, w.origin)
        for name in ("value", "max_rms_error_m"):
            value = getattr(w, name)
            _assert_cell(getattr(g, name), math.nan if nulls and not math.isfinite(value) else value, False,
                         f"{where}.starts[{k}].{name}")


@pytest.mark.parametrize("nulls", [False, True], ids=["NaN-as-written-by-python-json", "null-by-write_json"])
def test_sweep_record_with_nan_in_its_table_reads_back(tmp_path, paper, designs, nulls):
    """A sweep.json whose table has NaN cells reads back cell by cell, and its designs and
    reference design as they were, written by other tools (NaN, Infinity) or by us (null)."""
    sweep = Sweep((2,), ("D", "test-pose"), {(d.criterion, d.m): d for d in designs}, 1, False, designs[1],
                  criterion_starts=(("test-pose", 3),))
    written = sweep_record(paper, sweep, campaign_key(paper, sweep.criteria, sweep.m_values, Settings(1)))
    rows = written["sweep"]["rows"]
    rows[0]["seeded_best_max_error_mm"] = math.nan  # as when every seeded start failed
    rows[1]["repeat_best_single_pose_mm"] = math.nan  # as without a test-pose reference
    assert rows[0]["bound"] is None and rows[0]["max_error_mm"] > 0  # null and finite cells too
    path = tmp_path / "sweep.json"
    if nulls:
        write_json(path, written)
    else:
        _write(path, json.dumps(written))
    got = read_results(path)
    assert got["_path"] == str(path)
    assert len(got["sweep"]["rows"]) == len(rows)
    for i, (want_row, got_row) in enumerate(zip(rows, got["sweep"]["rows"])):
        assert list(got_row) == list(want_row), f"rows[{i}]: columns"
        for column, want in want_row.items():
            _assert_cell(got_row[column], want, nulls, f"rows[{i}].{column}")
    back = sweep_from_record(got)
    assert ((back.m_values, back.criteria, back.seeded_starts, back.warm_start, back.criterion_starts)
            == (sweep.m_values, sweep.criteria, sweep.seeded_starts, sweep.warm_start, sweep.criterion_starts))
    assert list(back.designs) == list(sweep.designs)
    for key, want in sweep.designs.items():
        _assert_same_design(back.designs[key], want, nulls, f"designs{key}")
    for i, d in enumerate(got["designs"]):
        _assert_same_design(design_from_record(d), designs[i], nulls, f"designs[{i}]")
    _assert_same_design(back.reference, sweep.reference, nulls, "reference")
    assert back.repeat_reference_m(2) == sweep.repeat_reference_m(2)


def _set(path, value):
    """A change to a record: ``path`` (keys and indices) set to ``value`` (None: deleted)."""
    def change(record):
        *where, last = path
        for k in where:
            record = record[k]
        if value is None:
            del record[last]
        else:
            record[last] = value
    return change


@pytest.mark.parametrize("change, match", [
    (_set(["designs"], {"0": 1}), r"designs: expected a non-empty list, got an object"),
    (_set(["designs"], []), r"designs: expected a non-empty list, got a list of 0"),
    (_set(["designs", 1, "scores"], None), r"designs\[1\]: missing key 'scores'"),
    (_set(["designs", 1, "m"], "2"), r"designs\[1\].m: expected an integer >= 1, got \"2\""),
    (_set(["designs", 1, "m"], 2.0), r"designs\[1\].m: expected an integer >= 1, got 2.0"),
    (_set(["designs", 1, "m"], True), r"designs\[1\].m: expected an integer >= 1, got true"),
    (_set(["designs", 0, "m"], 3), r"designs\[0\].experiments: expected a list of m \+ m_measured = 3 experiments, "
                                   "got a list of 2"),
    (_set(["designs", 0, "criterion"], "G"), r"designs\[0\].criterion: expected one of test-pose, D"),
    (_set(["designs", 0, "experiments"], "none"), r"designs\[0\].experiments: expected a list"),
    (_set(["designs", 0, "experiments", 1], [0.1, 0.2]),
     r"designs\[0\].experiments\[1\]: expected an object, got a list of 2"),
    (_set(["designs", 0, "experiments", 1, "force"], None),
     r"designs\[0\].experiments\[1\]: missing key 'force'"),
    (_set(["designs", 0, "experiments", 1, "q_rad", 0], "0.1"),
     r"designs\[0\].experiments\[1\].q_rad\[0\]: expected a finite number, got \"0.1\""),
    (_set(["designs", 0, "experiments", 1, "q_rad", 0], float("nan")),
     r"designs\[0\].experiments\[1\].q_rad\[0\]: expected a finite number, got NaN"),
    (_set(["designs", 0, "experiments", 1, "force", 1], float("inf")),
     r"designs\[0\].experiments\[1\].force\[1\]: expected a finite number, got Infinity"),
    (_set(["designs", 1, "experiments", 0, "q_rad"], [0.1, 0.2, 0.3]),
     r"designs\[1\].experiments\[0\].q_rad: expected 2 numbers \(as designs\[0\].experiments\[0\]"),
    (_set(["designs", 1, "rms_error_m"], [1e-4] * 60),
     r"designs\[1\].rms_error_m: expected 61 numbers \(one per test pose\), got a list of 60"),
    (_set(["designs", 1, "scores", "condition"], float("inf")),
     r"designs\[1\].scores.condition: expected a finite number, got Infinity"),
    (_set(["designs", 1, "scores", "identifiable"], 1),
     r"designs\[1\].scores.identifiable: expected true or false, got 1"),
    (_set(["designs", 1, "solver", "per_start", 0, "feasible"], "yes"),
     r"designs\[1\].solver.per_start\[0\].feasible: expected true or false, got \"yes\""),
    (_set(["designs", 1, "solver", "per_start", 0, "note"], "x"),
     r"designs\[1\].solver.per_start\[0\]: unexpected key 'note'"),
    (_set(["designs", 1, "solver", "wall_s"], -1), r"designs\[1\].solver.wall_s: expected a number"),
    (_set(["test_poses"], None), r"has no 'test_poses'"),
    (_set(["test_poses", 3, "position_m"], [0.1]),
     r"test_poses\[3\].position_m: expected 3 numbers \(as test_poses\[0\].position_m\)"),
    (_set(["sweep"], {"m": [2, 3], "criteria": ["D"], "seeded_starts": 1, "warm_start": True,
                      "reference": None}),
     r"designs: no design for criterion D, m = 3 of the sweep"),
    (_set(["sweep"], {"m": [2], "criteria": ["D"], "seeded_starts": 1, "warm_start": True,
                      "reference": None, "criterion_starts": {"X": 2}}),
     r"sweep.criterion_starts: expected criteria among .*test-pose"),
])
def test_damaged_results_record(tmp_path, record, change, match):
    damaged = copy.deepcopy(record)
    change(damaged)
    with pytest.raises(OutputError, match=match) as err:
        read_results(_results_file(tmp_path, damaged))
    assert str(err.value).startswith(f"{tmp_path / 'results.json'}: ")
    assert str(err.value).endswith(RESULTS_HINT)
    _one_line_with_hint(err.value)


@pytest.mark.parametrize("text, match", [
    ("[]", "holds a list of 0, not a results record"),
    ("42", "holds 42, not a results record"),
    ('"designs"', "holds \"designs\", not a results record"),
    ("[" * 100_000, "JSON nested too deeply"),
    ('{"designs": [}', r"not valid JSON \(Expecting value"),
])
def test_results_file_that_is_not_a_record(tmp_path, text, match):
    with pytest.raises(OutputError, match=match) as err:
        read_results(_write(tmp_path / "results.json", text))
    _one_line_with_hint(err.value)


@pytest.mark.parametrize("data", [b"\x89PNG\r\n\x1a\n\x00\x00", b'{"problem": "\xe9"}'])
def test_results_file_not_utf8(tmp_path, data):
    with pytest.raises(OutputError, match=r"is not UTF-8 text \(byte at offset \d+\)") as err:
        read_results(_write(tmp_path / "results.json", data))
    assert str(err.value).endswith(RESULTS_HINT)


def test_missing_results_file(tmp_path):
    with pytest.raises(OutputError, match="none.json: no such results file; check the path"):
        read_results(tmp_path / "none.json")


def test_results_path_that_is_a_pipe_does_not_hang(tmp_path):
    os.mkfifo(tmp_path / "results.json")
    with pytest.raises(OutputError, match="is not a regular file"):
        read_results(tmp_path / "results.json")


# --------------------------------------------------------------------------- output folders

@pytest.mark.parametrize("out", ["", "  "])
def test_empty_out(out):
    with pytest.raises(OutputError, match="^--out is empty; give a folder name$"):
        prepare_out(out)


def test_out_accepts_a_string_and_creates_nothing(tmp_path):
    assert prepare_out(str(tmp_path / "new")) == tmp_path / "new"
    assert not (tmp_path / "new").exists()


def test_out_whose_parents_do_not_exist_is_checked_and_left_uncreated(tmp_path):
    """`--out out/tiago` in a fresh folder (docs/identify.md): the missing parents are fine,
    created with the folder when the files are written, and the check leaves none behind."""
    out = tmp_path / "missing" / "deeper" / "out"
    assert prepare_out(out) == out
    assert not (tmp_path / "missing").exists()


def test_out_whose_parent_is_a_file(tmp_path):
    _write(tmp_path / "file", "x")
    with pytest.raises(OutputError, match=f"^{tmp_path / 'file' / 'out'}: {tmp_path / 'file'} is not a folder; "
                                          "choose another --out$"):
        prepare_out(tmp_path / "file" / "out")


@pytest.mark.skipif(os.geteuid() == 0, reason="root may write in any folder")
def test_out_in_a_read_only_folder(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o555)
    try:
        with pytest.raises(OutputError, match=f"no permission to write in {ro}; choose another --out"):
            prepare_out(ro / "out")
        with pytest.raises(OutputError, match=f"no permission to write in {ro}; choose another --out"):
            prepare_out(ro)
    finally:
        ro.chmod(0o755)


def test_out_not_writable_as_os_access_says(tmp_path, monkeypatch):
    """The same check as above, also where the tests run as root (access() is then true)."""
    monkeypatch.setattr(os, "access", lambda path, mode: False)
    with pytest.raises(OutputError, match=f"{tmp_path / 'out'}: no permission to write in {tmp_path}; "):
        prepare_out(tmp_path / "out")


def test_resume_with_nothing_to_resume_keeps_the_folder(tmp_path):
    _write(tmp_path / "report.md", "mine")
    with pytest.raises(OutputError, match=f"^{tmp_path}: nothing to resume \\(no sweep.partial.json or "
                                          "sweep.json\\); run without --resume$"):
        prepare_out(tmp_path, resume=True, resume_files=RESUME_FILES)
    with pytest.raises(OutputError, match="nothing to resume"):
        prepare_out(tmp_path / "new", resume=True, resume_files=RESUME_FILES)
    assert (tmp_path / "report.md").read_text() == "mine"


@pytest.mark.parametrize("name", ["sweep.partial.json", "sweep.json"])
def test_resume_of_a_saved_sweep_is_allowed(tmp_path, name):
    _write(tmp_path / name, "{}")
    _write(tmp_path / "report.md", "old")
    assert prepare_out(tmp_path, resume=True, resume_files=RESUME_FILES) == tmp_path


def test_existing_out_messages_are_kept(tmp_path):
    _write(tmp_path / "file", "x")
    with pytest.raises(OutputError, match="file: exists and is not a folder; choose another --out"):
        prepare_out(tmp_path / "file")
    with pytest.raises(OutputError, match="folder exists and is not empty; add --force"):
        prepare_out(tmp_path)
    assert prepare_out(tmp_path, force=True) == tmp_path


# --------------------------------------------------------------------------- written files

@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)])
def test_written_files_follow_the_umask(tmp_path, umask, mode):
    old = os.umask(umask)
    try:
        write_atomic(tmp_path / "a.txt", b"x")
        write_atomic(tmp_path / "a.txt", b"y")  # replaced: the same mode
    finally:
        os.umask(old)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == mode
    assert (tmp_path / "a.txt").read_bytes() == b"y"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]  # no temporary file left

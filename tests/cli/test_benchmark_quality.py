"""scripts/benchmark.py --quality: r of each design on its own criterion, the verdict of the rule
(geometric mean <= 1, no r above R_MAX, the fixed targets), on copies of the suite's paper run;
and the figures of one design (``run_one``, what ``--cases`` prints a row of)."""

import json
import math
import sys

import pytest

from tests.conftest import ROOT

sys.path.insert(0, str(ROOT / "scripts"))
import benchmark  # noqa: E402


def _set(folder, paper_out, edit=None):
    """A benchmark-set folder whose every run is the paper's results (edited by ``edit``)."""
    record = json.loads((paper_out / "results.json").read_text())
    if edit:
        edit(record)
    for name in benchmark.QUALITY_SET:
        (folder / name).mkdir(parents=True)
        (folder / name / "results.json").write_text(json.dumps(record))
    return folder


def _design(record, c, m):
    return next(d for d in record["designs"] if (d["criterion"], d["m"]) == (c, m))


def test_the_same_runs_are_accepted_and_a_worse_plan_is_refused(tmp_path, paper_solve_out, capsys):
    base = _set(tmp_path / "base", paper_solve_out)
    assert benchmark.quality(base, _set(tmp_path / "same", paper_solve_out))
    assert "verdict: accepted" in capsys.readouterr().out

    def worse(record):
        d = _design(record, "test-pose", 5)
        d["max_rms_error_m"] *= 1.03
        D = _design(record, "D", 1)
        D["scores"]["log_det_M"] -= len(record["calibration"]["parameters"]) * math.log(1.01)

    assert not benchmark.quality(base, _set(tmp_path / "worse", paper_solve_out, worse))
    out = capsys.readouterr().out
    rows = {tuple(ln.split()[:3]): float(ln.split()[3]) for ln in out.splitlines()
            if ln.startswith("paper ")}
    assert rows["paper", "test-pose", "5"] == pytest.approx(1.03)
    assert rows["paper", "D", "1"] == pytest.approx(1.01)  # exp of the log det's loss per parameter
    assert "largest r 1.0300 > 1.02" in out and "verdict: refused" in out


def test_a_plan_off_table_4_is_refused(tmp_path, paper_solve_out, capsys):
    base = _set(tmp_path / "base", paper_solve_out)

    def off(record):  # better on its criterion, but not the paper's figure
        _design(record, "E", 1)["max_rms_error_m"] = 0.230e-3

    assert not benchmark.quality(base, _set(tmp_path / "off", paper_solve_out, off))
    assert "paper E m = 1: 0.2300 mm is not Table 4's 0.24" in capsys.readouterr().out


def test_one_design_gives_its_figures():
    """``run_one`` on the paper's D design at m = 1: two seeded starts, no capsule rows, the
    Table 4 error (0.170 mm); a failure there prints a row "failed: ..." instead of figures."""
    from tests.conftest import PAPER

    row = benchmark.run_one(str(PAPER), "D", 1, 2, None)
    assert len(row["iterations"]) == 2 and row["converged"] >= 1 and row["rows"] == 0
    assert row["best_max_error_mm"] == pytest.approx(0.1700, abs=5e-5)

"""Starts on other processes or a Dask cluster give the serial numbers, bit for bit."""

import pickle
import sys
from concurrent.futures.process import BrokenProcessPool

import numpy as np
import pytest

from casadi_design.cli import main
from casadi_design.errors import DesignError
from casadi_design.execution.campaign import Settings
from casadi_design.execution.parallel import (
    DaskExecutor,
    MissingExtraError,
    ProcessExecutor,
    _Workers,
    make_executor,
    run_start,
)
from casadi_design.execution.sweep import run_sweep
from casadi_design.optimisation.approximate import ROUNDED
from casadi_design.optimisation.solve import solve_design
from tests.conftest import PAPER

#: Designs compared: a smooth criterion and the PSD-constrained E, at 1 and 3 experiments.
CASES = [("test-pose", 1), ("E", 3)]
STARTS = 4
#: The approximate designs' first pool in the comparisons across executors: what they check
#: (the same numbers wherever the work runs) does not depend on its size, and 50 candidates
#: cost a third of the default 300.
SMALL_POOL = 50


@pytest.fixture(scope="module")
def serial(paper):
    return {(c, m): solve_design(paper, c, m, starts=STARTS) for c, m in CASES}


def _assert_same(a, b):
    np.testing.assert_array_equal(a.Q, b.Q)
    np.testing.assert_array_equal(a.F, b.F)
    np.testing.assert_array_equal(a.scores.rms_error_m, b.scores.rms_error_m)
    assert a.starts == b.starts and a.status == b.status


def test_process_pool_equals_serial(paper, serial):
    with ProcessExecutor(2) as ex:
        for (c, m), d in serial.items():
            _assert_same(solve_design(paper, c, m, starts=STARTS, executor=ex), d)


@pytest.mark.parametrize("processes", [pytest.param(False, marks=pytest.mark.slow), True],
                         ids=["threads", "processes"])
def test_dask_local_cluster_equals_serial(paper, serial, processes):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=processes,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        ex = DaskExecutor(client)
        for (c, m), d in serial.items():
            _assert_same(solve_design(paper, c, m, starts=STARTS, executor=ex), d)
        ex.close()  # a client given by the caller stays open
        assert client.status == "running"


@pytest.mark.slow  # a sweep twice (2.5 s); process pools equal serial runs in the default run (test_process_pool_equals_serial)
def test_sweep_on_processes_equals_serial_sweep(paper):
    args = (paper, ["test-pose", "D"], [1, 2, 3], Settings(2, bound_steps=0))
    plain = run_sweep(*args)
    with ProcessExecutor(2) as ex:
        pooled = run_sweep(*args, executor=ex)
    for key, d in plain.designs.items():
        _assert_same(pooled.designs[key], d)
    _assert_same(pooled.reference, plain.reference)


def test_a_one_start_solve_spreads_the_searches_over_the_workers_to_the_same_design(paper, monkeypatch):
    """A one-start solve on workers: its seeded start first, told as the best plan so far with
    the approximate design named as what comes next, then the approximate design with each
    exchange step's searches split over the workers, then the rounded starts; the same design,
    starts and bound as the campaign run here, one after the other. Two approximate designs to
    compute on two workers: one per worker, beside the starts (nothing spread). The whole
    pipeline with bounds: the slow test below and test_the_commands_give_the_same_numbers_for_any_jobs."""
    from casadi_design.execution import campaign

    settings = Settings(1, bound_steps=1, bound_pool=SMALL_POOL)
    monkeypatch.setattr(campaign, "APPROXIMATE", campaign.APPROXIMATE.empty())
    serial = campaign.run_campaign(paper, ["test-pose"], [1], settings)
    monkeypatch.setattr(campaign, "APPROXIMATE", campaign.APPROXIMATE.empty())
    told = []
    with ProcessExecutor(2) as ex:
        one, two = [("test-pose", 0)], [("test-pose", 0), ("D", 0)]
        assert campaign._to_spread(one, ("test-pose",), (1,), settings, {}, ex.slots) == one
        assert campaign._to_spread(two, ("test-pose", "D"), (1,), settings, {}, ex.slots) == []
        spread = campaign.run_campaign(paper, ["test-pose"], [1], settings, executor=ex, on_better=told.append)
    first = told[0]
    assert (first.returned, first.total, first.bound, first.running) == (1, None, None, ())
    assert first.later == ("the approximate design of test-pose",)
    assert "next: the approximate design of test-pose" in first.line()
    a, b = spread.approx["test-pose", 0], serial.approx["test-pose", 0]
    assert (a.value, a.certified, a.d_max, a.history, a.checked) == (b.value, b.certified, b.d_max, b.history, b.checked)
    for field in ("Q", "F", "weights", "W", "mu"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
    d, e = spread.designs["test-pose", 1], serial.designs["test-pose", 1]
    _assert_same(d, e)
    assert [s.origin for s in d.starts] == [s.origin for s in e.starts] and d.bound == e.bound


@pytest.mark.slow  # 10 s: two sweeps with their approximate designs, one on workers
def test_pipelined_sweep_with_bounds_equals_the_serial_sweep(paper, monkeypatch):
    """On workers the campaign is a pipeline (the approximate designs, the seeded starts of
    later designs, the rounded and warm starts once their inputs returned): the same designs,
    starts and bounds as one design after the other."""
    from casadi_design.execution import campaign

    args = (paper, ["test-pose", "D"], [1, 2], Settings(1, bound_steps=2, bound_pool=SMALL_POOL))
    monkeypatch.setattr(campaign, "APPROXIMATE", campaign.APPROXIMATE.empty())
    plain = run_sweep(*args)
    monkeypatch.setattr(campaign, "APPROXIMATE", campaign.APPROXIMATE.empty())  # computed again, on the workers
    with ProcessExecutor(2) as ex:
        pooled = run_sweep(*args, executor=ex)
    assert list(pooled.designs) == list(plain.designs)
    for key, d in plain.designs.items():
        _assert_same(pooled.designs[key], d)
        assert [s.origin for s in pooled.designs[key].starts] == [s.origin for s in d.starts]
        assert pooled.designs[key].bound == d.bound
    assert {s.origin for s in plain.designs["D", 2].starts} == {"seeded", "warm start", ROUNDED}


def test_worker_builds_the_problem_from_its_plain_data(paper, serial):
    """What a worker runs, called here with a copy of the problem's data only."""
    from casadi_design.execution.parallel import ProblemRef
    from casadi_design.optimisation.solve import start_rng
    from casadi_design.plan.sampling import random_plan

    d = serial["test-pose", 1]
    Q0, F0 = random_plan(paper, 1, start_rng(paper.solver.seed, "test-pose", 1))
    ref = ProblemRef.of(paper)
    copied = pickle.loads(pickle.dumps(ref.spec))
    rec, _, _, _ = run_start(ProblemRef(copied, ref.key), "test-pose", 1, Q0, F0)
    assert rec == d.starts[0]


def test_extra_starts_run_after_the_seeded_ones_and_only_improve(paper):
    few = solve_design(paper, "test-pose", 5, starts=1)
    good = solve_design(paper, "test-pose", 5, starts=8)
    assert good.scores.max_rms_error_m < few.scores.max_rms_error_m  # the test needs a gap
    both = solve_design(paper, "test-pose", 5, starts=1, initial_plans=[(good.Q, good.F)])
    assert both.starts[0] == few.starts[0] and len(both.starts) == 2
    assert both.scores.max_rms_error_m == pytest.approx(good.scores.max_rms_error_m, rel=1e-6)
    again = solve_design(paper, "test-pose", 5, starts=8, initial_plans=[(few.Q, few.F)])
    assert again.starts[:8] == good.starts
    if not again.starts[8].value < good.scores.max_rms_error_m:  # the extra start did not win
        np.testing.assert_array_equal(again.Q, good.Q)
    assert again.scores.max_rms_error_m <= good.scores.max_rms_error_m


def test_initial_plan_of_the_wrong_shape(paper):
    with pytest.raises(ValueError, match=r"initial plan 0 has Q of shape \(4, 2\).*expected \(5, 2\)"):
        solve_design(paper, "D", 5, starts=1, initial_plans=[(np.zeros((4, 2)), np.zeros((4, 2)))])


def test_executor_choice():
    with make_executor(1) as ex:
        assert ex is None
    with make_executor(2) as ex:
        assert isinstance(ex, ProcessExecutor) and ex.jobs == 2
    with pytest.raises(ValueError, match="--jobs: expected a positive number of processes, got 0"):
        make_executor(0)


def test_dask_workers_with_other_blas_threads_or_kernels_are_refused():
    """A worker whose BLAS runs on other threads or kernels than the command would give other
    numbers (and its approximate designs would be kept under the command's name): one error
    that says how to start the workers."""
    from types import SimpleNamespace

    from casadi_design.runtime.threads import KERNEL, blas_setup

    here = blas_setup()
    assert here == (KERNEL, 1)  # this process, as the command (tests/conftest.py)
    for setup in [(KERNEL, 4), ("SkylakeX", 1)]:
        client = SimpleNamespace(run=lambda fn, s=setup: {"tcp://w1": s, "tcp://w2": fn()},
                                 scheduler=SimpleNamespace(address="tcp://10.0.0.1:8786"))
        ex = object.__new__(DaskExecutor)
        ex.client, ex._own = client, False
        with pytest.raises(DesignError, match=rf"1 worker\(s\) .* \(tcp://w1: {setup[0]}, {setup[1]} thread\(s\); "
                                              rf"here: {KERNEL}, 1 thread\(s\)\).*OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1 "
                                              r"dask worker tcp://10.0.0.1:8786 --nthreads 1"):
            ex._check_blas()
    ex.client = SimpleNamespace(run=lambda fn: {"tcp://w1": fn()})
    ex._check_blas()  # the same setup everywhere: no error


def test_missing_dask_gives_the_install_hint(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    with pytest.raises(MissingExtraError, match=r"pip install casadi-design\[dask\]"):
        DaskExecutor("tcp://127.0.0.1:8786")
    assert main(["solve", str(PAPER), "--dask-scheduler", "tcp://127.0.0.1:8786", "--m", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install casadi-design[dask]" in err[0]


@pytest.mark.slow  # a local cluster of worker processes; DaskExecutor itself: the test above
def test_dask_scheduler_option_of_the_command_equals_a_serial_run(tmp_path):
    import json

    distributed = pytest.importorskip("distributed")
    args = ["solve", str(PAPER), "--m", "1", "--criteria", "test-pose,E", "--starts", "3", "--quiet"]
    assert main([*args, "--jobs", "1", "--out", str(tmp_path / "serial")]) == 0
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        assert main([*args, "--dask-scheduler", cluster.scheduler_address,
                     "--out", str(tmp_path / "dask")]) == 0
    a, b = (json.loads((tmp_path / d / "results.json").read_text())["designs"] for d in ("serial", "dask"))
    for x, y in zip(a, b):
        assert x["experiments"] == y["experiments"] and x["solver"]["per_start"] == y["solver"]["per_start"]


@pytest.mark.slow  # 12 s: four commands twice; the default suite keeps the executors' equality (Dask, spread searches)
def test_the_commands_give_the_same_numbers_for_any_jobs(tmp_path, monkeypatch, capsys):
    """``--jobs 1`` (everything in this process) and ``--jobs 2`` (starts and approximate
    designs on workers) write the same results.json, bounds included: one thread for BLAS and
    OpenMP in every process (casadi_design.runtime.threads). ``bound --jobs 2`` computes its approximate
    designs of test-pose and D at the same time, one per worker (before the solve, which then
    computes them again in its pipeline): the same table as ``bound --jobs 1``."""
    import json

    from casadi_design.execution import campaign

    bounds = ["--bound-steps", "2", "--bound-pool", str(SMALL_POOL), "--quiet"]
    records, tables = [], []
    for jobs in ("1", "2"):
        monkeypatch.setattr(campaign, "APPROXIMATE", campaign.APPROXIMATE.empty())  # the approximate designs computed again
        if jobs == "2":
            assert main(["bound", str(PAPER), "--m", "1:3", *bounds, "--jobs", jobs]) == 0
            tables.append(capsys.readouterr().out)
            monkeypatch.setattr(campaign, "APPROXIMATE", campaign.APPROXIMATE.empty())
        assert main(["solve", str(PAPER), "--m", "1,3", "--criteria", "test-pose,D", "--starts", "3", *bounds,
                     "--jobs", jobs, "--out", str(tmp_path / f"jobs{jobs}")]) == 0
        capsys.readouterr()
        if jobs == "1":  # the bound of the designs just computed here
            assert main(["bound", str(PAPER), "--m", "1:3", *bounds, "--jobs", jobs]) == 0
            tables.append(capsys.readouterr().out)
        records.append(json.loads((tmp_path / f"jobs{jobs}" / "results.json").read_text()))

    def numbers(record):
        designs = [{k: v for k, v in d.items() if k != "solver"} | {"per_start": d["solver"]["per_start"]}
                   for d in record["designs"]]
        return designs, [{k: v for k, v in a.items() if k != "wall_s"} for a in record["approximate_designs"]]

    assert numbers(records[0]) == numbers(records[1])
    assert tables[0] == tables[1] and "log det M <=" in tables[0]


def test_a_design_without_a_converged_start_is_the_same_error_for_any_jobs(capsys):
    """The pipeline judges the largest m first, but the error names the first failing design
    in campaign order, as a serial run does (one line, exit code 2)."""
    args = ["solve", str(PAPER), "--m", "1,5", "--criteria", "test-pose,D", "--starts", "2",
            "--ipopt", "max_iter=1", "--bound-steps", "0", "--quiet"]
    errors = []
    for jobs in ("1", "2"):
        assert main([*args, "--jobs", jobs]) == 2
        errors.append(capsys.readouterr().err.strip())
    assert errors[0] == errors[1] and len(errors[0].splitlines()) == 1
    assert "criterion test-pose, m = 1: none of 2 starts converged" in errors[0]


class _DyingPool(_Workers):
    """Workers whose pool breaks (a worker dies) just before its third task is sent, while
    another task still runs: the race of a process pool whose worker dies between two results."""

    slots = 2

    def __init__(self):
        self.sent, self.generation, self.broken, self.alone = 0, 0, False, []

    def _submit(self, task):
        self.sent += 1
        if self.sent == 3 and not self.generation:
            self.broken = True
        if self.broken:
            raise BrokenProcessPool("a worker died")
        return (task, self.generation)

    def _finished(self, handles):
        return handles[:1]

    def _result(self, handle, task):
        if self.broken and handle[1] == self.generation:
            raise BrokenProcessPool("a worker died")
        return task.fn(*task.args)

    def _restart(self):
        self.generation, self.broken = self.generation + 1, False

    def _alone(self, task):
        self.alone.append(task.args)
        return task.fn(*task.args)

    def _cancel(self, handles):
        pass


def test_a_pool_that_breaks_before_a_task_is_sent_runs_every_task_once():
    pool = _DyingPool()
    assert list(pool._map(pow, [(2, k) for k in range(6)], "powers")) == [2**k for k in range(6)]
    # the task running when the pool broke ran again alone; the one not sent went to the new pool
    assert pool.alone == [(2, 1)] and pool.generation == 1


def test_the_best_plan_so_far_is_told_as_it_improves(paper, monkeypatch):
    """On workers each design tells its best plan as its starts return: better each time
    (beyond the criterion's same-optimum tolerance), the last one the design's optimum, with
    the gap once the bound is known and what still runs. D runs its own number of seeded starts
    (``criterion_starts``) beside its rounded ones."""
    from casadi_design.execution import campaign

    monkeypatch.setattr(campaign, "APPROXIMATE", campaign.APPROXIMATE.empty())
    told = []
    settings = Settings(2, bound_steps=1, bound_pool=30, criterion_starts=(("D", 1),))
    with ProcessExecutor(2) as ex:
        done = campaign.run_campaign(paper, ("test-pose", "D"), (5,), settings, executor=ex, on_better=told.append)
    assert [len(done.designs[c, 5].starts) for c in ("test-pose", "D")] == [2 + 4, 1 + 8]  # seeded + rounded
    for c in ("test-pose", "D"):
        ours = [i for i in told if i.criterion == c]
        crit = campaign.CRITERIA[c]
        assert ours and all(crit.better(b.value, a.value) for a, b in zip(ours, ours[1:]))
        assert crit.same_optimum(ours[-1].value, done.designs[c, 5].scores.value(c))  # (told beyond the tolerance)
    last = [i for i in told if i.bound is not None][-1]
    assert "% from the bound" in last.line() and last.total is not None
    assert any(i.running for i in told) or all(i.bound is not None for i in told)

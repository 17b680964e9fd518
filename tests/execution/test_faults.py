"""Faults a long study meets: a killed worker, a full disk, Ctrl-C at start-up, absurd ranges.

Each ends the command with one line (exit 2, or 130 for Ctrl-C), names what is kept and how to
continue, and leaves no half-written file. The killed workers are real: a start that kills its
own process with SIGKILL, as the kernel's out-of-memory killer does.
"""

import errno
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from casadi_design.execution import parallel
from casadi_design.cli import main
from casadi_design.errors import DesignError
from casadi_design.execution.parallel import DaskExecutor, ProcessExecutor, WorkerLost, run_start
from casadi_design.optimisation.solve import solve_design
from tests.conftest import PAPER, ROOT

#: A file whose absence makes the next start kill its worker (then the file exists).
MARKER = "CASADI_DESIGN_TEST_KILL_MARKER"
TINY = ["--starts", "2", "--bound-steps", "0", "--quiet"]


def _die_once(*args):
    """``run_start``, but the first start of the test kills its worker process."""
    marker = Path(os.environ[MARKER])
    if not marker.exists():
        marker.touch()
        os.kill(os.getpid(), signal.SIGKILL)
    return run_start(*args)


#: The m whose every start kills its worker process (:func:`_die_at_m`).
KILL_M = "CASADI_DESIGN_TEST_KILL_M"


def _die_at_m(ref, criterion, m, *args):
    """``run_start``, but every start of a design with m = $KILL_M kills its worker process."""
    if str(m) == os.environ[KILL_M]:
        os.kill(os.getpid(), signal.SIGKILL)
    return run_start(ref, criterion, m, *args)


@pytest.fixture
def kill_at_m(monkeypatch):
    """Every start of the designs with the m set by the returned function kills its worker."""
    monkeypatch.setattr(parallel, "run_start", _die_at_m)
    return lambda m: monkeypatch.setenv(KILL_M, str(m))


def _same(a, b):
    np.testing.assert_array_equal(a.Q, b.Q)
    np.testing.assert_array_equal(a.F, b.F)
    assert a.starts == b.starts


@pytest.fixture
def kill_once(tmp_path, monkeypatch):
    monkeypatch.setenv(MARKER, str(tmp_path / "killed"))
    monkeypatch.setattr(parallel, "run_start", _die_once)
    return tmp_path / "killed"


def test_a_killed_worker_is_replaced_and_its_starts_give_the_same_design(paper, kill_once):
    serial = solve_design(paper, "D", 2, starts=4)
    with ProcessExecutor(2) as ex:
        again = solve_design(paper, "D", 2, starts=4, executor=ex)
    assert kill_once.exists()  # a worker was killed
    _same(again, serial)


@pytest.mark.slow  # 3 s: a worker killed again after its replacement; one kill, replaced, runs by default
def test_a_worker_killed_twice_names_the_design_the_signal_and_what_is_kept(tmp_path, kill_at_m, capsys):
    kill_at_m(2)
    out = tmp_path / "sweep"
    args = ["sweep", str(PAPER), "--m", "1:2", "--criteria", "D", "--jobs", "2", *TINY]
    assert main([*args, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "criterion D, m = 2: a worker process was killed by SIGKILL" in err[0]
    assert "out-of-memory" in err[0] and "twice" in err[0]
    assert f"1 of 2 designs kept in {out / 'sweep.partial.json'}; continue with the same command and --resume" in err[0]
    kept = json.loads((out / "sweep.partial.json").read_text())["designs"]
    assert [(d["criterion"], d["m"]) for d in kept] == [("D", 1)]
    # resuming (m = 2 only, m = 1 kept) is tested with solve below and in tests/execution/test_sweep.py


def test_a_solve_keeps_what_it_finished_and_resumes(tmp_path, kill_at_m, capsys):
    """A solve hands out the starts of the largest m first (independent designs): m = 2 is
    finished and kept when the starts of m = 1 kill their workers."""
    kill_at_m(1)
    out = tmp_path / "solve"
    args = ["solve", str(PAPER), "--m", "1,2", "--criteria", "D", "--jobs", "2", *TINY]
    assert main([*args, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "criterion D, m = 1" in err and f"1 of 2 designs kept in {out / 'solve.partial.json'}" in err
    kill_at_m(2)  # the resumed solve solves m = 1 only: m = 2 is kept
    assert main([*args, "--out", str(out), "--resume"]) == 0
    assert not (out / "solve.partial.json").exists()
    designs = json.loads((out / "results.json").read_text())["designs"]
    assert [(d["criterion"], d["m"]) for d in designs] == [("D", 1), ("D", 2)]


@pytest.mark.slow  # a Dask cluster with a worker killed (2.5 s); a killed process-pool worker in the default run
def test_dask_reschedules_the_start_of_a_worker_that_went_away(paper, kill_once):
    distributed = pytest.importorskip("distributed")
    serial = solve_design(paper, "D", 2, starts=4)
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        again = solve_design(paper, "D", 2, starts=4, executor=DaskExecutor(client))
    assert kill_once.exists()
    _same(again, serial)


@pytest.mark.slow  # a cluster whose workers die and restart: 4 s
def test_dask_workers_that_keep_dying_are_one_error(paper, kill_at_m):
    distributed = pytest.importorskip("distributed")
    kill_at_m(2)
    import dask

    with dask.config.set({"distributed.scheduler.allowed-failures": 1}), \
            distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                     dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        with pytest.raises(WorkerLost, match="criterion D, m = 2: a worker process went away"):
            solve_design(paper, "D", 2, starts=2, executor=DaskExecutor(client))
    assert issubclass(WorkerLost, DesignError)  # the command prints it as one line


_FDOPEN = os.fdopen


class _FullDisk:
    """A file object whose writes fail with ENOSPC from the ``after``-th file on (the disk
    fills up while the command writes)."""

    opened = 0

    def __init__(self, fd, mode, after):
        self.fh, self.fail = _FDOPEN(fd, mode), _FullDisk.opened >= after
        _FullDisk.opened += 1

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.fh.close()

    def write(self, data):
        if self.fail:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self.fh.write(data)


def test_a_full_disk_is_one_line_naming_the_file_and_what_was_written(tmp_path, monkeypatch, capsys):
    _FullDisk.opened = 0
    # the disk fills up after solve.partial.json and results.json
    monkeypatch.setattr(os, "fdopen", lambda fd, mode="r", *a, **k: _FullDisk(fd, mode, after=2))
    out = tmp_path / "out"
    assert main(["solve", str(PAPER), "--m", "1", "--criteria", "D", "--jobs", "1", *TINY, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    partial = out / "solve.partial.json"
    assert err[0].startswith(f"error: {out / 'fig1.png'}: could not be written (No space left on device); "
                             f"already written: {partial}, {out / 'results.json'}; free some disk space")
    assert err[0].endswith(f"the designs are kept in {partial}: once fixed, run the same command with "
                           "--resume to write the files without solving again")
    assert not list(out.glob(".*.tmp"))  # no temporary file left
    json.loads((out / "results.json").read_text())  # what was written is whole
    monkeypatch.setattr(os, "fdopen", _FDOPEN)
    assert main(["solve", str(PAPER), "--m", "1", "--criteria", "D", "--jobs", "1", *TINY, "--out", str(out),
                 "--resume"]) == 0
    assert (out / "fig1.png").exists() and not partial.exists()


#: Ctrl-C ends a command within this (s), on a loaded machine.
STOPS_WITHIN_S = 1.0


@pytest.mark.parametrize("delay_s", [0.3, 0.8, 1.1])
def test_ctrl_c_during_start_up_exits_130_with_one_line(tmp_path, delay_s):
    """SIGINT while the package is still being imported (about a second), or just after: the
    command ends at once (0.15 to 0.2 s; it waited 1 to 2 s for its workers' first starts when
    the campaign had turned the KeyboardInterrupt into its one-line error)."""
    proc = subprocess.Popen([sys.executable, "-m", "casadi_design", "solve", str(PAPER), "--out",
                             str(tmp_path / "out")], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    time.sleep(delay_s)
    proc.send_signal(signal.SIGINT)
    sent = time.perf_counter()
    _, err = proc.communicate(timeout=30)
    assert time.perf_counter() - sent < STOPS_WITHIN_S, err
    assert proc.returncode == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1].startswith("interrupted"), err
    assert len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out" / "results.json").exists()


#: A command whose Ctrl-C passed through code that a native library ran with ``PyRun_String``
#: (CPython then marks it unhandled, though the command caught it).
_PYRUN_INTERRUPTED = """
import ctypes, sys
import casadi_design.cli
from casadi_design.launch import main

def interrupted(argv):
    run = ctypes.pythonapi.PyRun_String
    run.restype, run.argtypes = ctypes.py_object, [ctypes.c_char_p, ctypes.c_int, ctypes.py_object, ctypes.py_object]
    try:
        run(b"raise KeyboardInterrupt", 257, {}, {})  # 257: Py_file_input
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130

casadi_design.cli.main = interrupted
sys.exit(main([]))
"""


def test_ctrl_c_through_a_native_librarys_python_code_still_exits_130(tmp_path):
    """Python run as ``python -m`` ends itself by SIGINT (status -2) after a Ctrl-C it believes
    unhandled; the command ends with 130 all the same (``launch``; fails with -2 when
    ``launch.main`` returns 130 instead of ending the process)."""
    (tmp_path / "pyrun_interrupted.py").write_text(_PYRUN_INTERRUPTED)
    done = subprocess.run([sys.executable, "-m", "pyrun_interrupted"], cwd=tmp_path, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 130, done.stderr
    assert done.stderr == "interrupted\n"


@pytest.mark.parametrize("edit, option, match", [
    (("sigma_m = 1.0e-4", "sigma_m = 1e300"), [], r"\[measurement\]\.sigma_m: is 1e\+300 m, above 1 m"),
    (("magnitude_N = 100.0", "magnitude_N = 1e300"), [], r"\[experiments.force\]\.magnitude_N: is 1e\+300 N"),
    (None, ["--out", "/proc/some_dir"], r"/proc/some_dir: the folder cannot be created .*; choose another --out"),
    (None, ["--m", "1:100000"], r"--m 100000 is above 500, the most experiments a plan may have; give fewer"),
    # how far a start got before the limit varies with the machine's load: its plan may already
    # break a rule ("Maximum_CpuTime_Exceeded (the plan breaks a rule of the problem) x 1")
    (None, ["--ipopt", "max_cpu_time=1e-9"], r"IPOPT: Maximum_CpuTime_Exceeded[^;]*\); raise \[solver.ipopt\] max_cpu_time"),
])
def test_absurd_ranges_are_one_line(tmp_path, capsys, edit, option, match):
    path = PAPER
    if edit is not None:
        path = tmp_path / "case.toml"
        text = PAPER.read_text()
        assert edit[0] in text
        path.write_text(text.replace(*edit))
    assert main(["solve", str(path), "--jobs", "1", *TINY, *option]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: "), err
    assert re.search(match, err[0]), err[0]


def test_ctrl_c_turned_into_a_casadi_error_still_keeps_the_designs(tmp_path):
    """Building a solver runs Python callbacks; CasADi turns the KeyboardInterrupt raised in one
    into a RuntimeError. With Ctrl-C recorded, it ends as Ctrl-C: what is kept, and exit 130."""
    from casadi_design.runtime import interrupt
    from casadi_design.execution import study

    partial = tmp_path / "sweep.partial.json"
    handler = signal.getsignal(signal.SIGINT)
    interrupt.install()
    try:
        interrupt._HIT.set()
        with pytest.raises(study.Interrupted, match=f"interrupted: 3 of 8 designs kept in {partial}"):
            with study._keeping(partial, lambda: 3, 8):
                raise RuntimeError("Error in Function::factory for 'nlp' [CallbackInternal]: KeyboardInterrupt")
        with pytest.raises(study.Interrupted, match=r"^interrupted: none of the 8 designs had finished; nothing is "
                                                    r"kept$"):  # no --resume to suggest: nothing to resume
            with study._keeping(partial, lambda: 0, 8):
                raise KeyboardInterrupt
        interrupt._HIT.clear()
        with pytest.raises(RuntimeError, match="factory"):  # without Ctrl-C: a bug, reported as such
            with study._keeping(partial, lambda: 3, 8):
                raise RuntimeError("Error in Function::factory")
    finally:
        interrupt._HIT.clear()
        signal.signal(signal.SIGINT, handler)


#: A parent whose two workers are in the middle of a long call: it prints their pids and waits.
_BUSY_PARENT = """
import sys, time
from casadi_design.execution.parallel import ProcessExecutor
ex = ProcessExecutor(2)
futures = [ex._pool.submit(time.sleep, 120) for _ in range(2)]
time.sleep(1.0)
print(*[p.pid for p in ex._processes()], flush=True)
time.sleep(120)
"""


def _running(pid: int) -> bool:
    stat = Path(f"/proc/{pid}/stat")
    return stat.exists() and stat.read_text().rsplit(")", 1)[1].split()[0] != "Z"


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="the parent-death signal is Linux's")
def test_workers_end_with_a_killed_command():
    """A command killed outright (SIGKILL: no handler of its own runs; a batch system's time
    limit, the out-of-memory killer) takes its worker processes along, even those in the middle
    of a long call, instead of leaving them computing for nobody."""
    proc = subprocess.Popen([sys.executable, "-c", _BUSY_PARENT], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    try:
        workers = [int(p) for p in proc.stdout.readline().split()]
        assert len(workers) == 2 and all(_running(p) for p in workers)
        proc.kill()
        proc.wait()
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and any(_running(p) for p in workers):
            time.sleep(0.05)
        assert not any(_running(p) for p in workers)
    finally:
        proc.kill()
        proc.wait()

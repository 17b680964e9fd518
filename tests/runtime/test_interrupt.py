"""Ctrl-C stops a command at once (exit 130, no traceback) and keeps what a sweep finished."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from tests.conftest import PAPER, ROOT

#: Seconds to wait for the first finished design, then for the process to end after Ctrl-C.
WAIT_FIRST_DESIGN_S = 60.0
WAIT_EXIT_S = 10.0
SWEEP = ["--m", "1:3", "--criteria", "test-pose,D", "--starts", "15", "--no-warm-start",
         "--bound-steps", "0"]


def _sweep(out, jobs: int, *extra: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "casadi_design", "sweep", str(PAPER), *SWEEP, "--jobs", str(jobs),
         "--out", str(out), "--quiet", *extra],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.parametrize("jobs", [1, 2])
def test_ctrl_c_during_ipopt_exits_130_and_keeps_finished_designs(tmp_path, jobs):
    out = tmp_path / "sweep"
    proc = _sweep(out, jobs)
    partial = out / "sweep.partial.json"
    t0 = time.monotonic()
    while not partial.exists() and proc.poll() is None and time.monotonic() - t0 < WAIT_FIRST_DESIGN_S:
        time.sleep(0.02)
    assert proc.poll() is None, "the sweep ended before it could be interrupted"
    time.sleep(0.15)  # inside the next design's starts: IPOPT is running
    sent = time.monotonic()
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=WAIT_EXIT_S)
    assert time.monotonic() - sent < 5.0
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "KeyboardInterruptException" not in err
    assert "interrupted:" in err and "--resume" in err
    kept = json.loads(partial.read_text())["designs"]
    assert 1 <= len(kept) < 6
    # resuming reproduces the uninterrupted numbers: test_sweep.py checks it design by design
    # (an in-process Ctrl-C), and the slow test below from a subprocess


@pytest.mark.slow
def test_sweep_resumed_after_ctrl_c_completes(tmp_path):
    out = tmp_path / "sweep"
    proc = _sweep(out, 1)
    partial = out / "sweep.partial.json"
    t0 = time.monotonic()
    while not partial.exists() and proc.poll() is None and time.monotonic() - t0 < WAIT_FIRST_DESIGN_S:
        time.sleep(0.02)
    proc.send_signal(signal.SIGINT)
    proc.communicate(timeout=WAIT_EXIT_S)
    assert proc.returncode == 130
    resumed = _sweep(out, 1, "--resume")
    _, err = resumed.communicate(timeout=120)
    assert resumed.returncode == 0, err
    got = {(d["criterion"], d["m"]) for d in json.loads((out / "sweep.json").read_text())["designs"]}
    assert got == {(c, m) for c in ("test-pose", "D") for m in (1, 2, 3)}


@pytest.mark.slow  # the sweep tests above already send Ctrl-C during IPOPT, with 1 and 2 processes
def test_ctrl_c_of_solve_exits_130_at_once(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "casadi_design", "solve", str(PAPER), "--starts", "400", "--jobs", "1",
         "--out", str(tmp_path / "solve"), "--quiet"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"})
    time.sleep(2.5)  # imports, load, then IPOPT starts
    assert proc.poll() is None
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=WAIT_EXIT_S)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    assert not (tmp_path / "solve").exists()  # nothing half-written


def test_a_ctrl_c_where_python_cannot_raise_it_prints_no_traceback(capsys):
    """A Ctrl-C that lands in a weakref callback (as importlib's module locks run while the
    package is imported: a CI run printed "Exception ignored in: <function
    _get_module_lock.<locals>.cb>" and a traceback before "interrupted") is recorded and says
    nothing; any other exception raised there is still reported by Python's own hook."""
    import gc
    import weakref

    from casadi_design.runtime import interrupt

    class Body:
        pass

    previous = signal.getsignal(signal.SIGINT)
    interrupt.install()
    try:
        body = Body()
        ref = weakref.ref(body, lambda r: interrupt._handler(signal.SIGINT, None))
        del body
        gc.collect()
        assert capsys.readouterr().err == "" and interrupt.pressed() and ref() is None
        other = Body()
        ref = weakref.ref(other, lambda r: 1 / 0)
        del other
        gc.collect()
        err = capsys.readouterr().err
        assert "Exception ignored" in err and "ZeroDivisionError" in err
    finally:
        signal.signal(signal.SIGINT, previous)
        sys.unraisablehook = sys.__unraisablehook__
        interrupt._HIT.clear()


#: A tiny IPOPT solve whose objective sends Ctrl-C to its own process at the 5th evaluation,
#: once by CasADi alone, then inside the package's ipopt_call; no handler installed (a library
#: user's process).
_LIBRARY_CTRL_C = '''
import os, signal
import casadi as ca
from casadi_design.optimisation.ipopt import ipopt_call

class Sigint(ca.Callback):
    def __init__(self):
        ca.Callback.__init__(self)
        self.calls = 0
        self.construct("sigint", {"enable_fd": True})
    def get_n_in(self): return 1
    def get_n_out(self): return 1
    def get_sparsity_in(self, i): return ca.Sparsity.dense(2)
    def eval(self, arg):
        self.calls += 1
        if self.calls == 5:
            os.kill(os.getpid(), signal.SIGINT)
        return [ca.sumsqr(arg[0] - 3)]

def solver(f):
    x = ca.MX.sym("x", 2)
    return ca.nlpsol("s", "ipopt", {"x": x, "f": f(x)}, {"print_time": False, "ipopt.print_level": 0, "ipopt.sb": "yes"})

first, second = Sigint(), Sigint()  # alive as long as their solvers
alone = solver(first)
alone(x0=[0, 0])
print("casadi:", alone.stats()["return_status"])
try:
    with ipopt_call():
        solver(second)(x0=[0, 0])
    print("package: returned")
except KeyboardInterrupt:
    print("package: KeyboardInterrupt")
'''


def test_ctrl_c_in_library_use_raises_instead_of_ending_the_run_early():
    """Used as a library (no handler of the command), Ctrl-C inside IPOPT made CasADi end that
    run and return: a start went on from a cut-short run and was kept on disk as if computed.
    Inside the package's solver call it raises ``KeyboardInterrupt`` and CasADi's warning is
    not printed."""
    proc = subprocess.run([sys.executable, "-c", _LIBRARY_CTRL_C], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.splitlines() == ["casadi: NonIpopt_Exception_Thrown", "package: KeyboardInterrupt"]
    assert proc.stderr.count("KeyboardInterruptException") == 1  # CasADi's own, for the first run

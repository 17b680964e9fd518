"""What is kept on disk between runs (casadi_design.runtime.cache): computed once, read again to the
bit, computed anew when the file is damaged or the cache cannot be written; the capsules fitted
around a URDF's meshes read back as the fit gives them."""

from __future__ import annotations

import pickle
import sys
import threading
import time

import numpy as np
import pytest

from casadi_design.cell import capsules, collision, pairs
from casadi_design.cell.capsules import capsules_from_geometry, load_collision_geometry
from casadi_design.cell.cell import _package_dirs
from casadi_design.robot.robots import load_urdf, urdf_file
from casadi_design.runtime import cache
from tests.conftest import ROOT

UR10 = "example-robot-data:ur_description/urdf/ur10_robot.urdf"


@pytest.fixture
def directory(tmp_path, monkeypatch):
    monkeypatch.setenv("CASADI_DESIGN_CACHE", str(tmp_path))
    return tmp_path


def test_a_value_is_computed_once_and_read_again(directory):
    calls = []

    def make():
        calls.append(1)
        return {"x": np.arange(3.0) / 7}

    key = cache.digest(b"inputs", b"code")
    first = cache.stored("test", key, make)
    again = cache.stored("test", key, make)
    assert calls == [1] and np.array_equal(first["x"], again["x"])
    assert sorted(p.name for p in directory.iterdir()) == [f"test-{key}.lock", f"test-{key}.pickle"]  # no temporary
    other = cache.stored("test", cache.digest(b"other inputs", b"code"), make)  # another key: computed
    assert np.array_equal(other["x"], first["x"]) and calls == [1, 1]


def test_a_value_asked_for_at_once_is_computed_once(directory):
    """Two askers at the same time (two processes on a fresh machine; here two threads, whose
    own opens of the lock file exclude each other as processes do): one computes, the other
    waits and reads what it wrote."""
    calls, got = [], []

    def make():
        calls.append(1)
        time.sleep(0.5)
        return np.arange(4.0) / 3

    key = cache.digest(b"at once")
    askers = [threading.Thread(target=lambda: got.append(cache.stored("test", key, make))) for _ in range(2)]
    for t in askers:
        t.start()
    for t in askers:
        t.join()
    assert calls == [1] and len(got) == 2 and np.array_equal(got[0], got[1])


def test_the_digest_tells_its_parts_apart():
    assert cache.digest(b"ab", b"c") != cache.digest(b"a", b"bc")


def test_a_damaged_file_is_computed_again(directory):
    key = cache.digest(b"k")
    (directory / f"test-{key}.pickle").write_bytes(b"\x80\x04 half a pickle")
    assert cache.stored("test", key, lambda: 42) == 42
    assert pickle.loads((directory / f"test-{key}.pickle").read_bytes()) == 42


def test_an_unwritable_cache_still_gives_the_value(tmp_path, monkeypatch):
    blocker = tmp_path / "a file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("CASADI_DESIGN_CACHE", str(blocker / "cache"))
    assert cache.stored("test", cache.digest(b"k"), lambda: [1, 2]) == [1, 2]


@pytest.mark.slow  # fits the UR10's capsules twice (4 s); the cell's pairs read back in the default run
def test_the_ur10_capsules_read_back_as_fitted(directory, monkeypatch):
    model = load_urdf(UR10)
    geometry = load_collision_geometry(model, urdf_file(UR10), _package_dirs(UR10))
    fitted = capsules_from_geometry(model, geometry, 2)
    assert len(list(directory.glob("capsules-*.pickle"))) == 1

    def no_fit(*args, **kwargs):
        raise AssertionError("fitted again")

    monkeypatch.setattr(capsules, "fit_capsule", no_fit)
    again = capsules_from_geometry(model, geometry, 2)
    assert pickle.dumps(again) == pickle.dumps(fitted)  # the same capsules to the bit
    with pytest.raises(AssertionError, match="fitted again"):  # other inputs: fitted anew
        capsules_from_geometry(model, geometry, 1)
    # other BLAS kernels round the fit differently: their capsules are not these
    monkeypatch.setattr(capsules, "blas_kernels", lambda: "SkylakeX")
    with pytest.raises(AssertionError, match="fitted again"):
        capsules_from_geometry(model, geometry, 2)


def test_the_cells_pairs_read_back_as_selected(directory, monkeypatch):
    """The pairs of the ABB's cell are selected once (sampled configurations), then read back:
    the same pairs as a selection computed here; another clearance selects anew."""
    from casadi_design.cell import cell as cell_module
    from casadi_design.problem.build import load_problem

    problem = load_problem(ROOT / "problems" / "abb_irb6640_machining.toml")
    c = problem.cell
    args = (problem.robot, c.capsules, c.obstacles, c.spec.clearance_m, c.spec.disabled_pairs)
    first = cell_module._pairs(*args)
    assert len(list(directory.glob("cell-pairs-*.pickle"))) == 1
    selected = pairs.self_collision_pairs(*args[:2], args[3], args[4])
    assert first[0] == selected and first[1] == collision.obstacle_pairs(*args[:3], args[3])
    assert selected.kept and first[1][0]  # pairs of both kinds are there to compare

    def no_selection(*a, **k):
        raise AssertionError("selected again")

    monkeypatch.setattr(cell_module, "self_collision_pairs", no_selection)
    assert pickle.dumps(cell_module._pairs(*args)) == pickle.dumps(first)
    with pytest.raises(AssertionError, match="selected again"):
        cell_module._pairs(*args[:3], args[3] + 0.001, args[4])
    monkeypatch.setattr(cell_module, "blas_kernels", lambda: "SkylakeX")
    with pytest.raises(AssertionError, match="selected again"):
        cell_module._pairs(*args)


@pytest.fixture
def kept_designs(directory, monkeypatch):
    """Approximate designs kept on disk (the suite turns it off), none in this process yet."""
    from casadi_design.execution import campaign

    monkeypatch.setenv(cache.KEEP_DESIGNS, "1")
    monkeypatch.setattr(campaign, "APPROXIMATE", campaign.APPROXIMATE.empty())
    return campaign


@pytest.mark.slow  # an approximate design computed twice (3.5 s); a design read back start by start runs by default
def test_an_approximate_design_is_read_back_to_the_bit_by_a_later_run(kept_designs, monkeypatch, paper):
    """An approximate design computed once is read back from the disk by a later process (here:
    this one with its in-process designs cleared) without computing, to the bit and marked
    ``kept``; another pool, steps or criterion is computed."""
    campaign = kept_designs
    first = campaign.approximate_designs(paper, [("test-pose", 0), ("D", 0)], 2, 50)
    assert not any(a.kept for a in first.values())
    monkeypatch.setattr(campaign, "APPROXIMATE", campaign.APPROXIMATE.empty())
    computing = []

    def computes(*args, **kwargs):
        computing.append(args[1:4])
        raise LookupError("computing")

    monkeypatch.setattr(campaign, "approximate_one", computes)
    again = campaign.approximate_designs(paper, [("test-pose", 0), ("D", 0)], 2, 50)
    assert computing == [] and all(a.kept for a in again.values())
    for c, a in first.items():
        b = again[c]
        for name in ("Q", "F", "weights", "W", "mu"):
            np.testing.assert_array_equal(getattr(b, name), getattr(a, name))
        assert (b.value, b.certified, b.d_max, b.history, b.checked, b.pool_size, b.wall_s) == \
            (a.value, a.certified, a.d_max, a.history, a.checked, a.pool_size, a.wall_s)
    for steps, pool in ((2, 60), (1, 50)):  # not on the disk: computed (here: stopped as it starts)
        with pytest.raises(LookupError, match="computing"):
            campaign.approximate_designs(paper, [("test-pose", 0)], steps, pool)
    assert computing == [("test-pose", 2, 60), ("test-pose", 1, 50)]


def test_a_design_read_back_start_by_start_is_the_design_computed(directory, monkeypatch, paper):
    """A design's starts are kept on disk (:func:`casadi_design.optimisation.solve.solve_start`): the same
    design again reads every start back without IPOPT and is the same to the bit; another m,
    ``verbose`` (IPOPT's output asked for) or ``CASADI_DESIGN_KEEP_DESIGNS=0`` computes."""
    from casadi_design.optimisation import solve

    monkeypatch.setenv(cache.KEEP_DESIGNS, "1")
    first = solve.solve_design(paper, "test-pose", 2, starts=4)
    assert len(list(directory.glob("start-*.pickle"))) == 4
    solved = []
    computed = solve._solved_start

    def computes(*args):
        solved.append(args[1].m)
        return computed(*args)

    monkeypatch.setattr(solve, "_solved_start", computes)
    again = solve.solve_design(paper, "test-pose", 2, starts=4)
    assert solved == []
    np.testing.assert_array_equal(again.Q, first.Q)
    assert again.starts == first.starts and (first.kept_starts, again.kept_starts) == (0, 4)
    np.testing.assert_array_equal(again.scores.rms_error_m, first.scores.rms_error_m)
    solve.solve_design(paper, "test-pose", 3, starts=1)
    solve.solve_design(paper, "test-pose", 2, starts=1, verbose=True)
    monkeypatch.setenv(cache.KEEP_DESIGNS, "0")
    solve.solve_design(paper, "test-pose", 2, starts=1)
    assert solved == [3, 2, 2]


def test_the_fingerprint_is_of_the_files_not_their_paths(tmp_path, monkeypatch):
    """A URDF edited in place (a joint moved by 1 um) keeps the problem's path and checked data
    but not its fingerprint: what was kept for it is not read back."""
    import tomli_w

    from casadi_design.problem import build
    from casadi_design.robot.robots import urdf_file
    from tests.conftest import ROOT, read_raw

    urdf = tmp_path / "ur10.urdf"
    text = urdf_file(UR10).read_text()
    urdf.write_text(text)
    raw = read_raw(ROOT / "problems" / "ur10_drilling.toml")
    raw.pop("cell")
    raw["robot"]["urdf"] = str(urdf)
    path = tmp_path / "case.toml"
    path.write_text(tomli_w.dumps(raw))

    def built():
        monkeypatch.setattr(build, "_BUILT", build._BUILT.empty())  # built anew, as in a later run
        return build.load_problem(path)

    before = built()
    assert 'xyz="0.0 0.0 0.1273"' in text  # the shoulder joint's origin
    urdf.write_text(text.replace('xyz="0.0 0.0 0.1273"', 'xyz="0.0 0.0 0.127301"', 1))
    after = built()
    assert after.digest == before.digest and after.fingerprint != before.fingerprint
    copy = tmp_path / "copy" / "case.toml"  # the same file elsewhere: the same problem
    copy.parent.mkdir()
    copy.write_text(path.read_text())
    monkeypatch.setattr(build, "_BUILT", build._BUILT.empty())
    assert build.load_problem(copy).fingerprint == after.fingerprint


def test_the_fingerprint_names_the_blas_thread_count(monkeypatch):
    """A library caller whose BLAS runs on several threads rounds differently (the commands and
    this suite fix one thread first, casadi_design.runtime.threads): what it keeps is not read back by a
    command, nor the other way round."""
    from threadpoolctl import threadpool_limits

    from casadi_design.problem import build
    from casadi_design.runtime.threads import blas_threads
    from tests.conftest import PAPER

    def built():
        monkeypatch.setattr(build, "_BUILT", build._BUILT.empty())  # built anew, as in another process
        return build.load_problem(PAPER)

    assert blas_threads() == 1
    one = built().fingerprint
    with threadpool_limits(limits=2):
        assert blas_threads() == 2
        two = built()
        assert two.fingerprint != one
    assert two.digest == built().digest and built().fingerprint == one


def test_a_memo_keeps_the_values_used_last_and_reads_its_disk_layer(tmp_path, monkeypatch):
    """The one memo of the package: bounded (the least recently used dropped), ``make`` called
    once per key, a disk layer only with a kind and while ``disk()`` holds, marked on read."""
    monkeypatch.setenv("CASADI_DESIGN_CACHE", str(tmp_path))
    made = []

    def make(k):
        made.append(k)
        return k * 10

    memo = cache.Memo(2)
    assert [memo.get(k, lambda k=k: make(k)) for k in (1, 2, 1, 3, 1, 2)] == [10, 20, 10, 30, 10, 20]
    assert made == [1, 2, 3, 2] and len(memo) == 2  # 2 was the least recently used when 3 came
    assert not list(tmp_path.iterdir())  # no kind: nothing on disk

    on_disk = {"on": True}
    kept = cache.Memo(1, kind="test", disk=lambda: on_disk["on"], on_read=lambda v: ("read", v))
    assert kept.get("k1", lambda: "v1") == "v1" and (tmp_path / "test-k1.pickle").exists()
    again = kept.empty()  # a later process: its memory empty, the disk kept
    assert again.lookup("k1") == ("read", "v1") and again.lookup("k1") == ("read", "v1")
    on_disk["on"] = False
    assert kept.empty().lookup("k1") is None  # the disk layer switched off
    kept.keep("k2", "v2")
    assert not (tmp_path / "test-k2.pickle").exists() and kept.lookup("k2") == "v2"
    assert cache.Memo(0, kind="test", disk=lambda: True).get("k3", lambda: "v3") == "v3"
    assert cache.Memo(0).get("k4", lambda: "v4") == "v4" and len(cache.Memo(0)) == 0
    nothing = cache.Memo(2)  # None is a value (a problem without a cell): made once
    assert [nothing.get("k", lambda: made.append("none")) for _ in range(3)] == [None] * 3
    assert made.count("none") == 1


def test_a_memoised_function_keeps_its_values_by_argument_and_threads_share_it():
    """``memoised(size)``: the function's values by its arguments, computed once while kept,
    the least recently used dropped past ``size``; threads that share it get the values of
    their own arguments."""
    import threading

    made = []

    @cache.memoised(2)
    def square(x, y=0):
        made.append((x, y))
        return x * x + y

    assert [square(k) for k in (1, 2, 1, 3, 1, 2)] == [1, 4, 1, 9, 1, 4]
    assert made == [(1, 0), (2, 0), (3, 0), (2, 0)] and len(square.memo) == 2
    assert square(1, 5) == 6 and square.__name__ == "square"

    @cache.memoised(4, key=lambda x, tag: x)  # the value depends on x alone
    def double(x, tag):
        made.append(tag)
        return 2 * x

    assert [double(3, "a"), double(3, "b"), double(4, "c")] == [6, 6, 8] and made[-2:] == ["a", "c"]

    @cache.memoised(64)
    def echo(x):
        return (x, threading.get_ident())

    wrong, failed = [], []

    def ask(offset):
        try:
            for k in range(5000):
                key = (k * 7 + offset) % 100
                if echo(key)[0] != key:
                    wrong.append(key)
        except Exception as exc:  # (a lookup that lost its key to another thread)
            failed.append(repr(exc))

    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # threads switch between any two steps of a lookup
    try:
        threads = [threading.Thread(target=ask, args=(i,)) for i in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        sys.setswitchinterval(interval)
    assert wrong == [] and failed == [] and len(echo.memo) == 64

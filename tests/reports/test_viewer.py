"""viewer.html (casadi_design/reports/viewer.py) read back and opened in a real browser.

The data the page shows are read back from the page (its embedded JSON) and compared with the
plan CSV and the cell check computed apart. The pages are opened in headless Chromium (Debian's
package ``chromium``; without it these tests are skipped and say so), one browser per test
module (each page loaded anew in its tab) driven over the DevTools protocol on a pipe: screenshots of pose 1, pose 2 and pose 1 without
the robot (the robot's pixels are where the two pose-1 images differ), and the page's own check
(``viewer.check()``: every pose of every plan drawn, the robot's vertices finite and moving
from one pose to the next, a route's every frame placed), with no JavaScript error on the
console or in the page. The UR10's and the other robots' viewers are
built from random feasible plans (no solve: seconds, not minutes); the paper's is the one of
the suite's ``solve``.
"""

from __future__ import annotations

import base64
import csv
import fcntl
import json
import os
import re
import select
import shutil
import signal
import tempfile
import time
import tomllib
from pathlib import Path

import numpy as np
import pytest

from casadi_design.cell.cell import clearances
from casadi_design.cli import main
from casadi_design.measures.criteria import CRITERIA
from casadi_design.optimisation.solve import plan_scores
from casadi_design.plan.design import Design, StartRecord
from casadi_design.plan.sampling import random_plan
from casadi_design.problem.build import build_problem, load_problem
from casadi_design.problem_file.read import parse_problem
from casadi_design.records.export import read_plan_table, write_plans
from casadi_design.reports.viewer import (
    VIEWER_NAME,
    arrow_scale,
    decimated,
    read_viewer_data,
    round_mesh,
    write_viewer,
)
from tests.conftest import PAPER, ROOT

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
browser = pytest.mark.skipif(CHROMIUM is None, reason="no browser to open viewer.html in: install Debian's "
                                                      "package chromium (apt-get install chromium)")
#: Chromium headless, offline, in a profile of its own, driven over the DevTools protocol on a
#: pipe (no Python package needed); software WebGL (SwiftShader) asked for by name (its silent
#: fallback is deprecated).
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars", "--remote-debugging-pipe")
#: The page's size in the browser (px).
VIEWPORT = (900, 640)
#: The plot's part of a screenshot (px): right of it the panel, above it the controls.
PLOT_BOX = (0, 40, 600, 640)
#: Pixels of the robot in the plot (where the page with and without it differ) and pixels
#: that differ between two poses, at least.
ROBOT_PIXELS = 1500
POSE_PIXELS = 500
#: A pixel differs when a channel differs by more than this (0..255).
PIXEL_TOL = 24
#: Longest a page may take to open or to answer (s).
TIMEOUT_S = 240
UR10 = ROOT / "problems" / "ur10_drilling.toml"
ABB = ROOT / "problems" / "abb_irb6640_machining.toml"


class Browser:
    """Headless Chromium on one page, driven over the DevTools protocol on a pipe
    (``--remote-debugging-pipe``: commands on its fd 3, answers on its fd 4, each a JSON
    message ended by a NUL byte). JavaScript errors (exceptions, ``console.error``) are
    collected in ``errors``; :meth:`open` shows another page in the same tab (the errors
    collected anew); :meth:`close` leaves no process running."""

    def __init__(self, page: Path | None = None, fragment: str = ""):
        self.profile = tempfile.mkdtemp(prefix="chromium-")
        pipes = [os.pipe(), os.pipe()]  # commands, answers: both ends moved above fd 9
        (cmd_r, self.cmd_w), (self.ans_r, ans_w) = [[fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10) for fd in pipe]
                                                     for pipe in pipes]
        for fd in (fd for pipe in pipes for fd in pipe):
            os.close(fd)
        self.log = tempfile.TemporaryFile()  # noqa: SIM115 (the browser's stderr while it runs: closed by close())
        actions = [(os.POSIX_SPAWN_DUP2, cmd_r, 3), (os.POSIX_SPAWN_DUP2, ans_w, 4),
                   (os.POSIX_SPAWN_DUP2, self.log.fileno(), 2), (os.POSIX_SPAWN_OPEN, 1, os.devnull, os.O_WRONLY, 0)]
        self.pid = os.posix_spawn(CHROMIUM, [CHROMIUM, *FLAGS, f"--user-data-dir={self.profile}",
                                             f"--window-size={VIEWPORT[0]},{VIEWPORT[1]}",
                                             f"{page.as_uri()}#{fragment}" if page else "about:blank"],
                                  dict(os.environ),
                                  file_actions=actions, setsid=True)
        os.close(cmd_r)
        os.close(ans_w)
        self.buffer, self.count, self.errors, self.session = b"", 0, [], None
        try:
            deadline = time.monotonic() + TIMEOUT_S
            while True:
                pages = [t for t in self.call("Target.getTargets")["targetInfos"] if t["type"] == "page"]
                if pages or time.monotonic() > deadline:
                    break
                time.sleep(0.05)
            self.session = self.call("Target.attachToTarget", targetId=pages[0]["targetId"], flatten=True)["sessionId"]
            self.call("Runtime.enable")
            self.call("Emulation.setDeviceMetricsOverride", width=VIEWPORT[0], height=VIEWPORT[1], deviceScaleFactor=1,
                      mobile=False)
            if page is not None:
                self._drawn(page)
        except BaseException:
            self.close()
            raise

    def open(self, page: Path) -> None:
        """Show ``page`` in place of the page shown, once it has drawn (the page before is
        marked: a page counts as drawn only without the mark); the errors are collected anew.
        The page, self-contained (nothing loaded from elsewhere), is shown from a copy at one
        address in a folder of this browser, loaded anew for each page: Chromium starts once,
        and V8 compiles the plotly.js every page embeds once, not once per page (2 s a page)."""
        shown = Path(self.profile) / "pages" / "viewer.html"
        again = shown.exists()
        shown.parent.mkdir(exist_ok=True)
        shutil.copyfile(page, shown)
        self.evaluate("window.replacedBy = 1")
        self.errors = []
        if again:
            self.call("Page.reload")
        else:
            self.call("Page.navigate", url=shown.as_uri())
        self._drawn(page)

    def _drawn(self, page: Path) -> None:
        deadline = time.monotonic() + TIMEOUT_S
        while not self.ready():  # the page loads (from about:blank), then draws its first pose
            assert time.monotonic() < deadline, f"{page}: not drawn in {TIMEOUT_S} s"
            time.sleep(0.05)

    def ready(self) -> bool:
        """Whether the page has drawn (its status says so); False while it is still loading."""
        result = self.call("Runtime.evaluate", returnByValue=True, expression=(
            "!!(!window.replacedBy && document.readyState === 'complete' && document.getElementById('status') && "
            "document.getElementById('status').dataset.ready)"), check=False)
        return bool(result and result.get("result", {}).get("value"))

    def call(self, method: str, check: bool = True, **params) -> dict | None:
        """Send a command (to the page once attached) and return its result (``check``: fail on
        an error answer, else None)."""
        self.count += 1
        message = {"id": self.count, "method": method, "params": params}
        if self.session and not method.startswith("Target."):
            message["sessionId"] = self.session
        os.write(self.cmd_w, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + TIMEOUT_S
        while True:
            while b"\0" not in self.buffer:
                ready, _, _ = select.select([self.ans_r], [], [], max(0.0, deadline - time.monotonic()))
                chunk = os.read(self.ans_r, 1 << 20) if ready else b""
                assert chunk, f"Chromium gave no answer to {method}: {self.stderr()[-2000:]}"
                self.buffer += chunk
            text, self.buffer = self.buffer.split(b"\0", 1)
            answer = json.loads(text)
            if answer.get("method") == "Runtime.exceptionThrown":
                self.errors.append(answer["params"]["exceptionDetails"].get("exception", {}).get("description", text))
            elif answer.get("method") == "Runtime.consoleAPICalled" and answer["params"]["type"] in ("error", "assert"):
                self.errors.append(" ".join(str(a.get("value", a.get("description"))) for a in answer["params"]["args"]))
            if answer.get("id") == self.count:
                assert "error" not in answer or not check, (method, answer["error"])
                return answer.get("result")

    def evaluate(self, expression: str):
        """The value of a JavaScript expression (a promise awaited)."""
        result = self.call("Runtime.evaluate", expression=expression, awaitPromise=True, returnByValue=True)
        assert "exceptionDetails" not in result, result["exceptionDetails"]
        return result["result"].get("value")

    def screenshot(self, path: Path) -> Path:
        self.evaluate("new Promise(function (ok) { requestAnimationFrame(function () { requestAnimationFrame(ok); }); })")
        path.write_bytes(base64.b64decode(self.call("Page.captureScreenshot", format="png")["data"]))
        return path

    def stderr(self) -> str:
        self.log.seek(0)
        return self.log.read().decode("utf-8", "replace")

    def close(self) -> None:
        try:
            os.killpg(self.pid, signal.SIGKILL)  # the browser, its renderer and GPU processes
        except ProcessLookupError:
            pass
        os.waitpid(self.pid, 0)
        for fd in (self.cmd_w, self.ans_r):
            os.close(fd)
        self.log.close()
        shutil.rmtree(self.profile, ignore_errors=True)


def pixels(path: Path) -> np.ndarray:
    from PIL import Image

    x0, y0, x1, y1 = PLOT_BOX
    return np.asarray(Image.open(path).convert("RGB"), dtype=int)[y0:y1, x0:x1]


def differ(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.any(np.abs(a - b) > PIXEL_TOL, axis=2)


@pytest.fixture(scope="module")
def chromium():
    """One headless Chromium for the pages of this module's tests (:meth:`Browser.open`)."""
    browser = Browser()
    try:
        yield browser
    finally:
        browser.close()


def check_in_browser(chromium: Browser, page: Path, tmp_path: Path, screenshots: bool) -> dict:
    """Open the page in Chromium: its check of every pose (and route frame), and with
    ``screenshots`` the robot drawn (screenshots of pose 1 with and without the robot) and pose
    2 unlike pose 1 on screen; no JavaScript error. Returns the page's report."""
    chromium.open(page)
    report = chromium.evaluate("viewer.check()")
    if screenshots:  # the first plan of two experiments or more
        view = 1 + next(k for k, v in enumerate(report["views"]) if v["poses"] > 1)
        shots = {}
        for name, pose, hide in (("pose1", 1, []), ("pose2", 2, []), ("bare", 1, ["robot", "tool"])):
            chromium.evaluate(f"viewer.show({view}, {pose}, {json.dumps(hide)})")
            shots[name] = pixels(chromium.screenshot(tmp_path / f"{page.parent.name}_{name}.png"))
    errors = chromium.errors + chromium.evaluate("window.viewerErrors")
    assert errors == [], errors
    for view, data in zip(report["views"], read_viewer_data(page)["views"], strict=True):
        assert view["shown"] == view["poses"] and view["finite"] and view["drawn"], view
        # the robot moves to each pose apart from those before it (a plan may repeat an
        # experiment: an E-optimal one of the paper's does)
        assert apart(np.array([p["q"] for p in data["poses"]])) <= view["distinct"] <= view["poses"], view
        assert view["frames_shown"] == (view["frames"] if view["kind"] == "program" else 0), view
    if screenshots:
        a, b, c = shots["pose1"], shots["pose2"], shots["bare"]
        robot = differ(a, c)
        assert robot.sum() >= ROBOT_PIXELS, robot.sum()  # the robot is drawn ...
        assert np.mean(np.all(a[robot] > 245, axis=1)) < 0.5  # ... in colour, not blank
        assert differ(a, b).sum() >= POSE_PIXELS  # and moves to pose 2
    return report


#: Joint angles (deg) at which two poses of a plan are apart: the robot drawn at one moves
#: by far more than the page's 1e-6 in its vertices' checksum.
APART_DEG = 1e-3


def apart(q_deg: np.ndarray) -> int:
    """How many poses of ``q_deg`` (k, n) are farther than :data:`APART_DEG` from every
    pose before them."""
    return sum(all(np.abs(q - p).max() > APART_DEG for p in q_deg[:k]) for k, q in enumerate(q_deg))


def design_of(problem, criterion: str, Q: np.ndarray, F: np.ndarray) -> Design:
    """A :class:`Design` of the plan ``Q``, ``F`` as solve keeps it (scores, the cell check's
    clearances), without solving."""
    scores = plan_scores(problem, Q, F)
    near = None if problem.cell is None else tuple(clearances(problem.cell, Q))
    start = StartRecord("Solve_Succeeded", 0, scores.value(criterion), scores.max_rms_error_m, True)
    return Design(criterion, len(Q), Q, F, scores, start.status, (start,), 0.0, problem.solver.seed, clearances=near)


def random_designs(problem, criteria: tuple[str, ...], m: int, seed: int = 0) -> list[Design]:
    rng = np.random.default_rng(seed)
    return [design_of(problem, c, *random_plan(problem, m, rng)) for c in criteria]


def rows_of(path: Path) -> list[list[str]]:
    with open(path, newline="") as fh:
        return [row for row in csv.reader(fh) if row and not row[0].startswith("#")]


def check_against_plans(viewer: Path, plans: Path, problem) -> None:
    """The page's rows are its plan CSVs' (same numbers), its poses their joints (deg) and its
    clearances the cell check's, computed here apart (:func:`casadi_design.cell.cell.clearances`)."""
    data = read_viewer_data(viewer)
    n = problem.robot.n
    plan_views = [v for v in data["views"] if v["kind"] == "plan"]
    assert plan_views
    for view in plan_views:
        header, *rows = rows_of(plans / Path(view["file"]).name)
        assert view["columns"] == header
        assert len(view["rows"]) == len(rows) == len(view["poses"])
        for shown, row in zip(view["rows"], rows):
            assert [str(v) if isinstance(v, str) else repr(float(v)) if isinstance(v, float) else str(v)
                    for v in shown] == row
        Q, _, _, _ = read_plan_table(problem, plans / Path(view["file"]).name)
        for k, (pose, row) in enumerate(zip(view["poses"], rows)):
            assert pose["number"] == int(row[0]) == k + 1
            assert pose["q"] == [float(v) for v in row[1:1 + n]]
        near = clearances(problem.cell, Q) if problem.cell is not None else None
        for pose, row in zip(view["poses"], rows):
            if near is None:
                assert pose["clearance_mm"] is None and "clearance_mm" not in header
            else:
                assert pose["clearance_mm"] == float(row[header.index("clearance_mm")])
        if near is not None:
            assert [p["clearance_mm"] for p in view["poses"]] == [c.distance_m * 1e3 for c in near]
            assert [p["closest"] for p in view["poses"]] == [" / ".join(c.between) for c in near]
        _, F, _, _ = read_plan_table(problem, plans / Path(view["file"]).name)
        assert np.allclose(np.array(view["rms_mm"]) * 1e-3, plan_scores(problem, Q, F).rms_error_m, rtol=1e-9, atol=0)


# --------------------------------------------------------------------------- without a browser


def test_a_round_mesh_is_closed_and_decimation_keeps_the_shape():
    """A capsule's triangles close it (every edge in two triangles); vertex clustering on a
    grid of c moves no vertex more than c * sqrt(3) and keeps fewer triangles."""
    V, T = round_mesh(0.1, 0.2, caps=True)
    edges = np.sort(np.vstack([T[:, [0, 1]], T[:, [1, 2]], T[:, [2, 0]]]), axis=1)
    _, count = np.unique(edges, axis=0, return_counts=True)
    assert np.all(count == 2) and np.isclose(V[:, 2].max(), 0.3) and np.isclose(V[:, 2].min(), -0.3)
    W, S = decimated(V, T, 0.05)
    assert len(S) < len(T) and S.max() < len(W)
    assert max(np.min(np.linalg.norm(V - w, axis=1)) for w in W) <= 0.05 * np.sqrt(3)
    assert arrow_scale(2e-4) == 500.0 and arrow_scale(1e-3, 0.15) == 100.0


@pytest.fixture(scope="module")
def ur10_viewer(tmp_path_factory):
    """The UR10's viewer of a random feasible plan of 9 experiments (in the cell), and its plan
    CSV, as solve writes them (the paper's viewer holds six plans)."""
    problem = load_problem(UR10)
    designs = random_designs(problem, ("test-pose",), problem.m_min)
    out = tmp_path_factory.mktemp("ur10_viewer")
    write_plans(out, problem, designs)
    write_viewer(out, problem, designs)
    return problem, out


def test_the_ur10_viewer_shows_the_plan_csv_and_the_cell_check(ur10_viewer):
    problem, out = ur10_viewer
    check_against_plans(out / VIEWER_NAME, out / "plans", problem)
    data = read_viewer_data(out / VIEWER_NAME)
    assert data["geometry"]["robot_source"] == "URDF visual meshes" and data["geometry"]["tracker_m"] == [2.5, 0.0, 0.5]
    assert {s["name"] for s in data["geometry"]["static"]} == {"table", "tracker stand"}
    assert [t["group"] for t in data["geometry"]["traces"]] == ["robot", "tool", "capsules"]
    text = (out / VIEWER_NAME).read_text()
    assert (out / VIEWER_NAME).stat().st_size < 20e6
    skeleton = text[:text.index('id="viewer-data"')] + text[text.rindex("</script>"):]
    assert not re.search(r"<(script|link|img|iframe)[^>]*\b(src|href)=", skeleton)  # nothing loaded from elsewhere


@browser
def test_the_ur10_viewer_draws_the_robot_and_every_pose_in_a_browser(ur10_viewer, chromium, tmp_path):
    check_in_browser(chromium, ur10_viewer[1] / VIEWER_NAME, tmp_path, screenshots=True)


def test_the_paper_viewer_of_solve_shows_its_plan_csvs(paper_solve_out, paper):
    check_against_plans(paper_solve_out / VIEWER_NAME, paper_solve_out / "plans", paper)
    data = read_viewer_data(paper_solve_out / VIEWER_NAME)
    assert [(v["criterion"], v["m"]) for v in data["views"]] == [(c, m) for m in (1, 5) for c in ("test-pose", "D", "E")]
    assert data["geometry"]["sticks"] and data["test_poses"]["path"]
    assert data["views"][3]["label"].startswith(CRITERIA["test-pose"].legend)


@browser
def test_the_paper_viewer_draws_the_robot_and_every_pose_in_a_browser(paper_solve_out, chromium, tmp_path):
    check_in_browser(chromium, paper_solve_out / VIEWER_NAME, tmp_path, screenshots=True)


def test_plot_writes_the_viewer_of_a_solve_folder(paper_solve_out, tmp_path, capsys):
    """``plot DIR`` builds the problem again from the results' problem file; a folder whose
    problem file is gone gets its figures and one line saying why it has no viewer."""
    assert main(["plot", str(paper_solve_out), "--out", str(tmp_path / "again"), "--format", "png"]) == 0
    assert read_viewer_data(tmp_path / "again" / VIEWER_NAME)["views"] == read_viewer_data(
        paper_solve_out / VIEWER_NAME)["views"]
    record = json.loads((paper_solve_out / "results.json").read_text())
    moved = tmp_path / "moved"
    moved.mkdir()
    (moved / "results.json").write_text(json.dumps(record | {"problem_file": str(tmp_path / "gone.toml")}))
    capsys.readouterr()
    assert main(["plot", str(moved), "--format", "png"]) == 0
    out = capsys.readouterr().out
    assert not (moved / VIEWER_NAME).exists() and f"no {VIEWER_NAME}: its problem file" in out and out.count("\n") == 1


#: The other robots: the ABB (DH, capsules of its cell, three reflectors, a hung load), a
#: Panda (URDF meshes, capsules given as numbers), a DH arm without a cell (a line through its
#: joints).
def _panda():
    from tests.cell.test_cell import PANDA_CELL

    return build_problem(parse_problem(tomllib.loads(PANDA_CELL), "panda.toml"))


def _dh_arm():
    from tests.identification.test_dh_table import CRAIG_TOML

    return build_problem(parse_problem(tomllib.loads(CRAIG_TOML), "craig.toml"))


@pytest.mark.slow  # 20 s in a browser; the default run opens the UR10's and the paper's
@browser
@pytest.mark.parametrize("make, source", [(lambda: load_problem(ABB), "capsules of the cell"),
                                          (_panda, "URDF visual meshes"), (_dh_arm, "sticks")],
                         ids=["abb", "panda", "dh_arm"])
def test_the_viewers_of_other_robots_show_every_pose_in_a_browser(make, source, chromium, tmp_path):
    problem = make()
    designs = random_designs(problem, ("D",), problem.m_min, seed=1)
    write_plans(tmp_path, problem, designs)
    write_viewer(tmp_path, problem, designs)
    data = read_viewer_data(tmp_path / VIEWER_NAME)
    assert data["geometry"]["robot_source"] == source
    check_against_plans(tmp_path / VIEWER_NAME, tmp_path / "plans", problem)
    check_in_browser(chromium, tmp_path / VIEWER_NAME, tmp_path, screenshots=False)


def test_program_and_identify_write_their_viewers(paper_solve_out, paper, tmp_path, request):
    """``program``'s viewer: the experiments in the program's order, numbered as in the plan,
    and its route through every point of the program; ``identify``'s: the measured points and
    the calibrated model's, residual arrows ``model + scale (measured - model)`` with the scale
    printed. Both open in a browser with every pose and frame drawn."""
    from tests.identify_data import measured, measurement_csv, perturbed

    plan = paper_solve_out / "plans" / "test-pose_m5.csv"
    assert main(["program", str(PAPER), "--plan", str(plan), "--format", "json", "--out", str(tmp_path / "program"),
                 "--quiet"]) == 0
    view = read_viewer_data(tmp_path / "program" / VIEWER_NAME)["views"][0]
    program = json.loads((tmp_path / "program" / "program.json").read_text())
    order = [p["experiment"] for p in program["points"] if p["experiment"]]
    assert [p["number"] for p in view["poses"]] == order == view["route"]["order"]
    assert len(view["route"]["moves"]) == len(order) + 1 and view["route"]["moves"][0]["from"] == "home"
    assert view["frames"]["count"] == len(view["route"]["times_s"]) > len(program["points"])
    Q, F, _, _ = read_plan_table(paper, plan)
    true = perturbed(paper, np.random.default_rng(3))
    (tmp_path / "meas.csv").write_text(measurement_csv(paper, Q, F, measured(paper, true, Q, F, np.random.default_rng(4))))
    assert main(["identify", str(PAPER), "--measurements", str(tmp_path / "meas.csv"), "--model", "identifiable",
                 "--out", str(tmp_path / "identify"), "--quiet"]) == 0
    view = read_viewer_data(tmp_path / "identify" / VIEWER_NAME)["views"][0]
    r = view["residuals"]
    assert len(view["poses"]) == len(Q) and r["text"].startswith(f"residual arrows x {r['scale']:g}")
    model, arrows, meas = (np.array(r[k], dtype=float) for k in ("model_m", "arrows_m", "measured_m"))
    assert np.allclose(arrows, model + r["scale"] * (meas - model), atol=1e-12)
    rms = np.sqrt(np.mean(np.sum((meas - model) ** 2, axis=2), axis=1))  # the plane's two axes: z is 0
    assert np.allclose([p["residual_rms_mm"] * 1e-3 for p in view["poses"]], rms, rtol=1e-6, atol=1e-12)
    assert 0.05 <= r["scale"] * np.max(np.linalg.norm(meas - model, axis=2)) <= 0.15  # drawn 5 to 15 cm long
    if CHROMIUM is not None:
        for folder in ("program", "identify"):
            check_in_browser(request.getfixturevalue("chromium"), tmp_path / folder / VIEWER_NAME, tmp_path,
                             screenshots=False)


@pytest.mark.slow
@browser
def test_the_ur10_study_viewer_opens_in_a_browser(chromium, tmp_path):
    """The whole UR10 study (5 criteria, m = 9 and 12: 105 poses), solved with one start and
    no bound, under 20 MB, every pose drawn."""
    assert main(["solve", str(UR10), "--starts", "1", "--bound-steps", "0", "--out", str(tmp_path / "ur10"),
                 "--quiet"]) == 0
    page = tmp_path / "ur10" / VIEWER_NAME
    assert page.stat().st_size < 20e6
    check_against_plans(page, tmp_path / "ur10" / "plans", load_problem(UR10))
    report = check_in_browser(chromium, page, tmp_path, screenshots=True)
    assert sum(v["poses"] for v in report["views"]) == 5 * (9 + 12)

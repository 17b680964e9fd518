"""identify and solve for points fixed in an artefact, on a Panda whose recordings are made
independently of the package's model (tests/artefact_data.py): the fit, the predicted held-out
consistency against a Monte Carlo of the seating's noise, a ball not seated found, the
recordings' bad input, the measured point moved on the hand found, and the commands end to end
(calibrated.urdf read back by Pinocchio)."""

import json

import numpy as np
import pinocchio as pin
import pytest

from casadi_design.calibrated.artefact_report import held_out, judged_record
from casadi_design.calibrated.report import parameter_unit
from casadi_design.cli import main
from casadi_design.errors import ProblemError
from casadi_design.identification.artefact_fit import (
    UNSEATED_SHARE,
    artefact_base_set,
    ball_points,
    beyond_prediction,
    calibrate_artefact,
    figures,
    fit_artefact,
    fit_without_outliers,
    judged,
    relocated,
)
from casadi_design.identification.fit import fit_model
from casadi_design.identification.lsq import frame_poses
from casadi_design.identification.recordings import Recordings, read_recordings
from casadi_design.problem.build import load_problem
from tests.artefact_data import ball_socket_file, recordings, seated as seated_at, true_ball
from tests.conftest import ROOT

PANDA = ROOT / "problems" / "panda_ball_socket.toml"
SIGMA = 5e-5
PER_POINT = 15


@pytest.fixture(scope="module")
def ideal():
    """The Panda problem, its true robot, 15 configurations per socket of two placements with the
    ball exactly seated, and each configuration's least-norm IK step (n x 3) of the true robot:
    ``q + S e`` seats the ball ``e`` off (to first order)."""
    problem = load_problem(PANDA)
    true, Q, k, g = recordings(problem, 0, PER_POINT, 0.0)
    model, data = true.model, true.model.createData()
    steps = []
    for q in Q:
        J = pin.computeFrameJacobian(model, data, problem.robot.full_q(q), true.frame_id, pin.LOCAL_WORLD_ALIGNED)[:3]
        steps.append(np.linalg.pinv(J[:, [model.joints[j].idx_v for j in problem.robot.joint_ids]]))
    return problem, true, Q, k, g, np.array(steps)


def seated(ideal, rng: np.random.Generator) -> np.ndarray:
    """The ideal configurations with the seating's noise N(0, SIGMA^2 I) on the ball."""
    _, _, Q, _, _, steps = ideal
    return Q + np.einsum("kij,kj->ki", steps, rng.normal(0, SIGMA, (len(Q), 3)))


@pytest.fixture(scope="module")
def simulated(ideal):
    """The Panda problem, its true robot and one draw of the recordings."""
    problem, true, _, k, g, _ = ideal
    return problem, true, seated(ideal, np.random.default_rng(0)), k, g


def _split(Q, k, g) -> tuple[Recordings, Recordings]:
    names = ("front", "side")
    train = Recordings(Q[g == 0], k[g == 0], np.zeros(int(np.sum(g == 0)), int), names[:1],
                       tuple(f"front {i}" for i in range(int(np.sum(g == 0)))))
    valid = Recordings(Q[g == 1], k[g == 1], np.zeros(int(np.sum(g == 1)), int), names[1:],
                       tuple(f"side {i}" for i in range(int(np.sum(g == 1)))))
    return train, valid


def test_the_fit_recovers_the_robot_and_the_predicted_consistency_is_a_monte_carlos(simulated, ideal):
    """Trained on one placement, the fit leaves the seating's noise (sigma per value); over 40
    draws of the seating's noise at both placements, the mean held-out consistency is the
    predicted one within 5 %."""
    problem, _, Q, k, g = simulated
    train, valid = _split(Q, k, g)
    names, _ = artefact_base_set(problem, train, problem.model.parameter_names)
    fm = fit_model(problem, "base", names)
    f = fit_artefact(problem, fm, train)
    assert np.sqrt(np.sum(f.r**2) / f.dof) == pytest.approx(SIGMA, rel=0.3)
    predicted = judged(problem, f, valid, None, SIGMA, train)[0].predicted_consistency_m
    rng = np.random.default_rng(7)
    seen = []
    for _ in range(40):
        tr, va = _split(seated(ideal, rng), k, g)
        fn = fit_artefact(problem, fm, tr)
        seen.append(figures(problem.artefact, ball_points(fm.model, va.Q, fn.X)[0], va.point)[0])
    assert np.mean(seen) == pytest.approx(predicted, rel=0.05)


def test_a_ball_not_seated_is_an_outlier(simulated):
    problem, true, Q, k, g = simulated
    train, _ = _split(Q, k, g)
    bad = true_ball(problem, true, train.Q[3:4])  # configuration 3 moved 1 mm: the ball sat 1 mm off
    data = true.model.createData()
    qf = problem.robot.full_q(train.Q[3])
    J = pin.computeFrameJacobian(true.model, data, qf, true.frame_id, pin.LOCAL_WORLD_ALIGNED)[:3]
    J = J[:, [true.model.joints[j].idx_v for j in problem.robot.joint_ids]]
    Qb = train.Q.copy()
    Qb[3] = Qb[3] + np.linalg.pinv(J) @ np.array([1e-3, 0.0, 0.0])
    assert np.linalg.norm(true_ball(problem, true, Qb[3:4]) - bad) == pytest.approx(1e-3, rel=1e-2)
    names, _ = artefact_base_set(problem, train, problem.model.parameter_names)
    f, outliers, _ = fit_without_outliers(problem, fit_model(problem, "base", names),
                                          Recordings(Qb, train.point, train.placement, train.names, train.sources))
    assert [where for where, _ in outliers] == ["front 3"]
    assert not f.used[3] and f.used.sum() == len(Qb) - 1


def test_the_configurations_beyond_the_prediction_are_those_moved():
    """Rows seated at two points, each deviating from its point's mean by N(0, S_i), S_i of
    another shape each: three moved 20 standard deviations are the three beyond the prediction, as
    a loop of 3 x 3 solves counts them; under noise alone, none."""
    rng = np.random.default_rng(5)
    N = 60
    k = np.repeat([0, 1], N // 2)
    A = rng.standard_normal((N, 3, 3))
    S = 1e-10 * (np.eye(3) + A @ A.transpose(0, 2, 1) / np.sum(A**2, axis=(1, 2))[:, None, None])  # ~(0.01 mm)^2
    means = np.array([[0.5, 0.0, 0.2], [0.55, 0.0, 0.2]])
    p = means[k] + np.einsum("nab,nb->na", np.linalg.cholesky(S), rng.standard_normal((N, 3)))
    assert not beyond_prediction(p, k, S).any()
    moved = [4, 17, 40]
    for i in moved:
        u = rng.standard_normal(3)
        p[i] += 20 * u / np.sqrt(u @ np.linalg.solve(S[i], u))  # 20 std along u
    flagged = beyond_prediction(p, k, S)
    loop = [i for i in range(N) if (d := p[i] - p[k == k[i]].mean(axis=0)) @ np.linalg.solve(S[i], d) > 16]
    assert np.flatnonzero(flagged).tolist() == loop == moved


def test_a_placement_recorded_badly_is_said_so(simulated, ideal):
    """Held out beside one recorded well, a placement whose configurations mostly sat 1 mm off
    their socket (balls not seated) has them beyond the prediction, a note to record it again,
    and the held-out means are given without it too: those of the placement recorded well,
    recomputed from the calibrated robot's ball centres. Recorded well, none is beyond, no note
    is printed and no second mean given."""
    problem, _, Q, k, g = simulated
    train, valid = _split(Q, k, g)
    steps = ideal[5][g == 1]
    rng = np.random.default_rng(11)
    n = valid.N
    for bad in (False, True):
        Qv = valid.Q.copy()
        if bad:
            off = rng.standard_normal((n, 3))
            keep = np.arange(n) % 3 == 0  # a third seated, the others 1 mm off in random directions
            Qv[~keep] += np.einsum("kij,kj->ki", steps[~keep], 1e-3 * off[~keep] / np.linalg.norm(off[~keep], axis=1)[:, None])
        two = Recordings(np.vstack([Qv, valid.Q]), np.tile(valid.point, 2), np.repeat([0, 1], n), ("side", "side again"),
                         tuple(f"{name} {i}" for name in ("side", "side again") for i in range(n)))
        cal = calibrate_artefact(problem, train, two, model="identifiable", with_field=False)
        j, again = cal.validation
        noted = [n for n in cal.notes if "record the placement again" in n]
        record = judged_record(cal)["validation"]
        assert not again.recorded_badly and again.beyond <= 1
        if bad:
            assert j.recorded_badly and j.beyond > UNSEATED_SHARE * j.rows
            assert len(noted) == 1 and f"at side ({j.beyond} of" in noted[0]
            p, _ = ball_points(cal.fit.fit.model, valid.Q, cal.fit.X)
            consistency, spacing = figures(problem.artefact, p, valid.point)
            well = record["recorded_well"]
            assert well["without"] == ["side"]
            assert well["consistency_mm"] == pytest.approx(consistency * 1e3, rel=1e-9)
            assert well["median_spacing_mm"] == pytest.approx(spacing * 1e3, rel=1e-9, abs=1e-12)
            assert record["consistency_mm"] == pytest.approx((j.consistency_m + consistency) / 2 * 1e3, rel=1e-9)
            assert f"without side (recorded badly), mean consistency {consistency * 1e3:.3f} mm" in held_out(cal)
        else:
            assert not j.recorded_badly and j.beyond <= 1 and not noted
            assert record["recorded_well"] is None and "recorded badly" not in held_out(cal)


def _folder(path, Q, k):
    path.mkdir(parents=True, exist_ok=True)
    for j in np.unique(k):
        np.savetxt(path / f"hole_{j}.csv", Q[k == j], delimiter=",")
    return path


def test_bad_recordings_get_one_line_naming_the_file_and_the_fix(simulated, tmp_path):
    problem, _, Q, k, _ = simulated
    cases = {
        "joints": (lambda d: np.savetxt(d / "hole_0.csv", Q[:5, :6], delimiter=","), "6 joint values a row"),
        "point": (lambda d: np.savetxt(d / "hole_5.csv", Q[:5], delimiter=","), "point 5 is not a point"),
        "one": (lambda d: np.savetxt(d / "hole_0.csv", Q[:1], delimiter=","), "one configuration"),
        "empty": (lambda d: None, "a folder with no recordings"),
        "degrees": (lambda d: np.savetxt(d / "hole_0.csv", np.degrees(Q[:5]), delimiter=","), "look like degrees"),
        "twice": (lambda d: [np.savetxt(d / f, Q[:5], delimiter=",") for f in ("hole_0.csv", "hole_00.csv")],
                  "are both point 0"),
        # fitted, a placement at one point tells none of its turns (it said "record more varied configurations")
        "at one point": (lambda d: np.savetxt(d / "hole_1.csv", Q[:5], delimiter=","),
                         "at point 1 only, which tell 0 of the 2 turns .* or give it as --validation"),
    }
    for name, (make, message) in cases.items():
        folder = tmp_path / name
        folder.mkdir()
        make(folder)
        with pytest.raises(ProblemError, match=message) as info:
            read_recordings(problem, [str(folder)])
        assert "\n" not in str(info.value) and str(folder) in str(info.value)
    with pytest.raises(ProblemError, match="no such file or folder"):
        read_recordings(problem, [str(tmp_path / "missing.csv")])
    # MUKCa's folders as published also hold each point's FK poses (7 numbers a row) and the
    # operator's comments: not recordings, read past
    placed = _folder(tmp_path / "robot" / "front", Q[:12], np.arange(12) % 2)
    for j in (0, 1):
        np.savetxt(placed / f"hole_{j}_pose.csv", np.ones((6, 7)), delimiter=",")
    (placed / "comments.txt").write_text("tool screwed in the fourth row\n")
    read = read_recordings(problem, [str(placed)])
    assert read.N == 12 and np.array_equal(read.Q, np.vstack([Q[:12:2], Q[1:12:2]]))
    # a robot's folder of placements, and one point's file, are named with the folder to give
    for path, message in ((placed.parent, r"a folder of 1 placement \(front\).*--measurements .*robot/front"),
                          (placed / "hole_0.csv", r"one point's recordings of a placement; give its folder")):
        with pytest.raises(ProblemError, match=message) as info:
            read_recordings(problem, [str(path)])
        assert "\n" not in str(info.value)
    # a held-out point of one configuration tells no consistency (in a fit it is welcome: a plan may have one)
    alone = tmp_path / "alone"
    alone.mkdir()
    np.savetxt(alone / "hole_0.csv", Q[:1], delimiter=",")
    np.savetxt(alone / "hole_1.csv", Q[1:6], delimiter=",")
    assert read_recordings(problem, [str(alone)]).N == 6
    with pytest.raises(ProblemError, match=r"--validation alone: point 0 has one configuration"):
        read_recordings(problem, [str(alone)], "--validation")
    joints = ",".join(f"{j}_rad" for j in problem.robot.joints)
    for name, rows, message in (
            ("named.csv", [(0, 0, "front"), (1, 0, "front"), (0, 1, "front"), (1, 1, "front")],
             "'front' names two placement numbers"),
            ("huge.csv", [(0, 0, "a"), (1e30, 0, "a")], r"column 'point': 1e\+30 is not an integer")):
        text = [f"{joints},point,placement,placement_name"]
        text += [",".join(f"{v:.9g}" for v in Q[i]) + f",{k:g},{g},{n}" for i, (k, g, n) in enumerate(rows * 2)]
        (tmp_path / name).write_text("\n".join(text) + "\n")
        with pytest.raises(ProblemError, match=message):
            read_recordings(problem, [str(tmp_path / name)])


def test_identify_and_solve_end_to_end(simulated, tmp_path, capsys):
    """identify on one placement's folder with another held out: identification.json holds the
    held-out consistency, measured and predicted; Pinocchio evaluating calibrated.urdf's
    measured_point on the recorded joints gets the consistency identify prints. solve
    --candidates (one per placement) chooses recordings whose plan CSV identify reads back."""
    problem, _, Q, k, g = simulated
    front = _folder(tmp_path / "front", Q[g == 0], k[g == 0])
    side = _folder(tmp_path / "side", Q[g == 1], k[g == 1])
    out = tmp_path / "id"
    assert main(["identify", str(PANDA), "--measurements", str(front), "--validation", str(side),
                 "--out", str(out), "--quiet"]) == 0
    record = json.loads((out / "identification.json").read_text())
    v = record["validation"]
    assert v["placements"][0]["placement"] == "side"
    assert 0 < v["consistency_mm"] < 0.2 and 0 < v["predicted_consistency_mm"] < 0.2
    assert "base.tx" in [a["name"] for a in record["absorbed"]]
    assert record["calibrated_urdf"]["model"] == record["model"]  # no compliance chosen: the URDF holds it all
    consistency = _urdf_figures(problem, out, Q[g == 1], k[g == 1])[0]
    assert consistency * 1e3 == pytest.approx(v["consistency_mm"], rel=1e-9)
    design = tmp_path / "design"
    assert main(["solve", str(PANDA), "--candidates", str(front), "--candidates", str(side), "--m", "12",
                 "--criteria", "test-pose,D", "--starts", "2", "--out", str(design), "--quiet"]) == 0
    designs = json.loads((design / "results.json").read_text())["designs"]
    assert [d["criterion"] for d in designs] == ["test-pose", "D"]
    assert designs[0]["max_rms_error_m"] <= designs[1]["max_rms_error_m"]
    chosen = read_recordings(problem, [str(design / "plans" / "test-pose_m12.csv")])
    assert chosen.N == 12 and set(map(tuple, chosen.Q)) <= set(map(tuple, Q))  # from both placements' recordings
    assert set(chosen.names) <= {"front", "side"}


def _urdf_figures(problem, out, Q, k) -> tuple[float, float]:
    """Consistency and spacing error (m) of ``out``'s calibrated.urdf, its ``measured_point``
    evaluated by Pinocchio on the recorded joints ``Q`` seated at points ``k``."""
    model = pin.buildModelFromUrdf(str(out / "calibrated.urdf"))
    data, fid = model.createData(), model.getFrameId("measured_point")
    P = []
    for q in Q:
        full = pin.neutral(model)
        full[:7] = q
        pin.framesForwardKinematics(model, data, full)
        P.append(data.oMf[fid].translation.copy())
    return figures(problem.artefact, np.array(P), k)


def test_a_model_with_compliances_leaves_calibrated_urdf_the_best_model_without_them(simulated, tmp_path):
    """The weight's compliances have no place in a URDF: with them chosen, calibrated.urdf holds
    the best model without them, identified alike, and identification.json's ``calibrated_urdf``
    gives its figures, the ones Pinocchio gets from the file (the chosen model's own differ)."""
    problem, _, Q, k, g = simulated
    front = _folder(tmp_path / "front", Q[g == 0], k[g == 0])
    side = _folder(tmp_path / "side", Q[g == 1], k[g == 1])
    out = tmp_path / "id"
    assert main(["identify", str(PANDA), "--measurements", str(front), "--validation", str(side),
                 "--model", "identifiable + gravity", "--out", str(out), "--quiet"]) == 0
    record = json.loads((out / "identification.json").read_text())
    urdf = record["calibrated_urdf"]
    assert record["model"] == "identifiable + gravity" and urdf["model"] == "identifiable"
    assert not any(p["name"].startswith("k.") for p in urdf["parameters"])
    consistency, spacing = _urdf_figures(problem, out, Q[g == 1], k[g == 1])
    assert consistency * 1e3 == pytest.approx(urdf["validation"]["consistency_mm"], rel=1e-9)
    assert spacing * 1e3 == pytest.approx(urdf["validation"]["median_spacing_mm"], rel=1e-9)
    assert consistency * 1e3 != pytest.approx(record["validation"]["consistency_mm"], rel=1e-6)
    train = _urdf_figures(problem, out, Q[g == 0], k[g == 0])[0]
    assert train * 1e3 == pytest.approx(urdf["training"]["consistency_mm"], rel=1e-9)


def test_a_model_named_is_the_one_fitted(simulated):
    """--model ball fits the nominal robot with its ball located (the ball's parameters alone),
    and a tracker's model name is refused for an artefact's recordings in one line."""
    from casadi_design.identification.artefact_fit import calibrate_artefact

    problem, _, Q, k, g = simulated
    train, valid = _split(Q, k, g)
    cal = calibrate_artefact(problem, train, valid, model="ball", with_field=False)
    assert cal.model == "ball" and all(n.startswith("tool.") for n in cal.names)
    assert [c.name for c in cal.candidates] == ["ball"]
    with pytest.raises(ProblemError, match="--model registration: allowed for an artefact"):
        calibrate_artefact(problem, train, valid, model="registration")


def test_the_bearings_tilts_are_fitted_when_named_only(simulated):
    """The tilt model (compliances across the loaded joints' axes) is fitted when named; auto
    does not judge it (it made auto's choice worse on 16 configurations)."""
    from casadi_design.identification.artefact_fit import TILT_MODEL, calibrate_artefact

    problem, _, Q, k, g = simulated
    train, valid = _split(Q, k, g)
    cal = calibrate_artefact(problem, train, valid, model=TILT_MODEL, with_field=False)
    assert cal.model == TILT_MODEL and [c.name for c in cal.candidates] == [TILT_MODEL]
    tilts = [n for n in cal.names if n.startswith("k.") and n.count(".") == 2]
    assert tilts and all(n.rsplit(".", 1)[1] in ("rx", "ry") for n in tilts)
    assert {parameter_unit(cal, n) for n in tilts} == {"rad/(N m)"}  # identification.json's units
    assert TILT_MODEL not in [c.name for c in calibrate_artefact(problem, train, valid, with_field=False).candidates]


def test_a_ball_moved_on_the_hand_is_found_and_relocated():
    """A Panda exactly nominal but for its ball, moved 0.3 mm on the hand (in the ball's frame,
    Pinocchio's model changed apart), seated at both sockets: the move is found to 1e-9 m, the
    consistency with it moved is nil, and under the seating's noise alone (24 configurations)
    the move is over 10 standard deviations (25); the nominal ball is found where it is."""
    problem = load_problem(PANDA)
    robot = problem.robot
    R, t = pin.rpy.rpyToMatrix(0.0, 0.0, 0.3), np.array([0.50, -0.05, 0.10])
    A = problem.artefact
    for delta in (np.array([2e-4, -1e-4, 2e-4]), np.zeros(3)):
        model = pin.Model(robot.model)
        frame = model.frames[robot.frame_id]
        frame.placement = frame.placement * pin.SE3(np.eye(3), delta)
        model.frames[robot.frame_id] = frame
        true = type("True", (), {"model": model, "frame_id": robot.frame_id})
        rng = np.random.default_rng(3)
        Q = np.vstack([seated_at(problem, true, t + R @ a, rng, 12) for a in A.points_m])
        k = np.repeat([0, 1], 12)
        L, nF = problem.model.L, problem.model.nF
        found, consistency, C = relocated(*frame_poses(problem.model, Q, np.zeros((len(Q), nF)), np.zeros(L)), k,
                                          SIGMA**2 * np.eye(3 * len(Q)))
        np.testing.assert_allclose(found, delta, atol=1e-9)
        assert consistency < 1e-8
        std = float(np.sqrt(found @ np.linalg.solve(C, found)))
        assert std > 10 if delta.any() else std < 1e-3
        before = figures(A, ball_points(problem.model, Q, np.zeros(L))[0], k)[0]
        assert before > 2e-5 if delta.any() else before < 1e-8


def test_what_an_artefact_s_commands_do_not_use_is_refused_in_one_line(simulated, tmp_path, capsys):
    """A tracker's identify options, an unknown criterion, solve's --program and the weight's
    models on a robot without masses: one line each, before anything is fitted or solved."""
    from casadi_design.identification.artefact_fit import calibrate_artefact
    from tests.conftest import build, read_raw

    problem, _, Q, k, g = simulated
    front = _folder(tmp_path / "front", Q[g == 0], k[g == 0])
    for args, message in (
            (["identify", "--measurements", str(front), "--loss", "cauchy"], "--loss: not used with an artefact"),
            (["identify", "--measurements", str(front), "--frame", "base"], "--frame: not used with an artefact"),
            (["solve", "--criteria", "Z"], "--criteria has 'Z'"),
            (["solve", "--candidates", str(front), "--criteria", "Z"], "--criteria has 'Z'"),
            (["solve", "--program", "json"], "--program: not written by solve for an artefact")):
        assert main([args[0], str(PANDA), *args[1:], "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1
    raw = read_raw(PANDA)
    del raw["robot"]["inertias_urdf"]  # MUKCa's URDF alone: no masses
    raw["robot"]["urdf"] = str(ROOT / "problems" / raw["robot"]["urdf"])
    massless = build(raw)
    train, valid = _split(Q, k, g)
    with pytest.raises(ProblemError, match="the robot's links carry no masses"):
        calibrate_artefact(massless, train, valid, model="identifiable + gravity", with_field=False)


def test_recordings_that_vary_too_little_are_said_so(simulated):
    """Two configurations, each recorded 30 times, tell a base set far smaller than varied
    recordings do: identify says so, and names what they do not tell; the simulated recordings
    tell all of it (no note)."""
    from casadi_design.identification.artefact_fit import calibrate_artefact, generic_base_set

    problem, _, Q, k, g = simulated
    train, _ = _split(Q, k, g)
    told = generic_base_set(problem, problem.model.parameter_names)
    full = calibrate_artefact(problem, train, model="identifiable", with_field=False)
    assert set(full.names) == set(told) and not any("vary too little" in n for n in full.notes)
    two = np.repeat(np.flatnonzero(g == 0)[[0, PER_POINT]], 30)  # one configuration at each point
    poor = Recordings(Q[two], k[two], np.zeros(len(two), dtype=int), ("poor",), (), ())
    cal = calibrate_artefact(problem, poor, model="identifiable", with_field=False)
    assert len(cal.names) < len(told)
    assert any(f"tell {len(cal.names)} of the {len(told)} parameters" in n and "vary too little" in n for n in cal.notes)


def test_a_model_named_like_a_smaller_one_is_fitted_under_its_name():
    """The Gen3 lite's joint offsets are not in its base set: ``offsets`` holds the ball's
    parameters alone, as ``ball`` does. Named, it is fitted (auto judges it once, as ball)."""
    problem = load_problem(ROOT / "examples" / "gen3lite_ball_socket.toml")
    _, Q, k, g = recordings(problem, 1, 8, SIGMA)
    rec = Recordings(Q, k, g, ("a", "b"), tuple(f"c{i}" for i in range(len(Q))))
    ball, offsets = (calibrate_artefact(problem, rec, model=m, with_field=False) for m in ("ball", "offsets"))
    assert offsets.model == "offsets" and offsets.names == ball.names == ("tool.tx", "tool.ty")
    np.testing.assert_allclose(offsets.fit.X, ball.fit.X)
    assert "offsets" not in [c.name for c in calibrate_artefact(problem, rec, with_field=False).candidates]


def test_a_gravity_model_whose_compliances_are_not_told_is_its_own_urdf(simulated):
    """Named on two recordings (one a socket), the weight's model holds no compliance (the
    rows tell one parameter, a geometric one): calibrated.urdf holds it as it is, no second model."""
    from casadi_design.identification.artefact_fit import calibrate_artefact

    problem, _, Q, k, g = simulated
    rows = np.concatenate([np.flatnonzero((g == 0) & (k == j))[:1] for j in (0, 1)])
    rec = Recordings(Q[rows], k[rows], np.zeros(len(rows), int), ("front",), tuple(map(str, rows)))
    cal = calibrate_artefact(problem, rec, model="identifiable + gravity", with_field=False)
    assert not any(n.startswith("k.") for n in cal.names) and cal.urdf is None and cal.in_urdf is cal


def test_readings_past_a_joint_limit_are_accepted_within_the_tolerance_and_said(simulated, tmp_path, capsys):
    """An encoder reads past the URDF's limit (a robot seated at its limit by hand): identify
    accepts 0.5 mrad past (--limit-tolerance, 1 mrad by default) with a note naming the file,
    printed and written once (folder and CSV alike: the CSV's note was read and lost), refuses 5
    mrad past naming the row and the option, and accepts it with --limit-tolerance 0.01. The other
    commands' readings (solve --candidates, evaluate, program) keep the limits: refused. Before,
    any reading past by 1e-6 was refused and --limit-tolerance was refused with an artefact's
    recordings."""
    from casadi_design.identification.measurements import LIMIT_TOLERANCE

    problem, _, Q, k, g = simulated
    rows = np.flatnonzero(g == 0)
    j = 3
    for past, ok in ((5e-4, True), (5e-3, False)):
        Qp = Q[rows].copy()
        Qp[0, j] = problem.robot.q_max[j] + past
        folder = _folder(tmp_path / f"past{past:g}", Qp, k[rows])
        with pytest.raises(ProblemError, match=r"outside its limits .* rad \(the robot cannot reach it\)"):
            read_recordings(problem, [str(folder)], "--candidates")
        if not ok:
            with pytest.raises(ProblemError, match=rf"hole_{k[rows][0]}\.csv: row 1: {problem.robot.joints[j]} = .* "
                                                   r"by more than --limit-tolerance 0\.001 \(rad\)"):
                read_recordings(problem, [str(folder)], limit_tolerance=LIMIT_TOLERANCE)
            assert read_recordings(problem, [str(folder)], limit_tolerance=0.01).N == len(rows)
            continue
        rec = read_recordings(problem, [str(folder)], limit_tolerance=LIMIT_TOLERANCE)
        assert len(rec.notes) == 1 and str(folder) in rec.notes[0] and problem.robot.joints[j] in rec.notes[0]
        assert "at most 0.0005 rad" in rec.notes[0]
        joints = ",".join(f"{n}_rad" for n in problem.robot.joints)
        text = [f"{joints},point,placement"] + [",".join(f"{v:.12g}" for v in q) + f",{p},0" for q, p in zip(Qp, k[rows])]
        (tmp_path / "past.csv").write_text("\n".join(text) + "\n")
        out = tmp_path / "out"
        assert main(["identify", str(PANDA), "--measurements", str(tmp_path / "past.csv"), "--model", "identifiable",
                     "--out", str(out)]) == 0
        said = capsys.readouterr().out
        assert said.count(f"{tmp_path / 'past.csv'}: column 'panda_joint4_rad': 1 reading past the joint limits by at "
                          "most 0.0005 rad (row 2)") == 1
        assert sum("past the joint limits" in n for n in json.loads((out / "identification.json").read_text())["notes"]) == 1
    assert main(["identify", str(PANDA), "--measurements", str(folder), "--limit-tolerance", "0.01", "--model",
                 "identifiable", "--out", str(tmp_path / "out2")]) == 0




def test_a_dh_robot_s_artefact_calibration_writes_its_calibrated_dh_table(tmp_path):
    """identify of an artefact's recordings by a DH robot measured at its flange (an ABB IRB
    6640's table) writes calibrated_dh.toml as the tracker's identify does: the calibrated DH
    table puts the ball where calibrated.urdf does at every recorded configuration. Before, only
    calibrated.urdf was written."""
    from casadi_design.robot.robots import frame_placement

    from tests.conftest import read_raw

    abb = read_raw(ROOT / "problems" / "abb_irb6640_machining.toml")["robot"]  # its DH table
    robot = {"frame": "flange", "tool_xyz_m": [0.0, 0.0, 0.05], "dh": abb["dh"]}
    path = ball_socket_file(tmp_path / "dh_socket.toml", "dh_socket", robot,
                            [[0.1, 0.3, -0.2, 0.0, 1.2, 0.0], [-0.2, 0.5, -0.4, 0.3, 1.0, 0.2]])
    problem = load_problem(path)
    _, Q, k, _ = recordings(problem, 5, 12, 5e-5, placements=((np.eye(3), np.array([1.6, 0.0, 0.3])),))
    front = _folder(tmp_path / "front", Q, k)
    out = tmp_path / "out"
    assert main(["identify", str(path), "--measurements", str(front), "--out", str(out)]) == 0
    assert json.loads((out / "identification.json").read_text())["files"]["dh_problem"] == "calibrated_dh.toml"
    dh, urdf = load_problem(out / "calibrated_dh.toml"), load_problem(out / "calibrated.toml")
    assert dh.spec.robot.source == "dh" and urdf.spec.robot.source == "urdf"
    for q in Q:
        assert np.allclose(frame_placement(dh.robot, q).translation, frame_placement(urdf.robot, q).translation,
                           atol=1e-9)
    nominal = np.array([frame_placement(problem.robot, q).translation for q in Q])
    calibrated = np.array([frame_placement(dh.robot, q).translation for q in Q])
    assert np.max(np.linalg.norm(calibrated - nominal, axis=1)) > 1e-4  # the table did change

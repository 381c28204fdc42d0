"""The virtual force sensor: observers, wrench mapping, free motion, a known static load, a singular pose."""

from __future__ import annotations

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from cell.sensing.observer import KalmanObserver
from cell.sensing.virtual_sensor import VirtualForceSource, build_virtual_source
from cell.sensing.wrench_map import ContactMap, JacobianMap, LearnedMap, fit_learned_axes
from drivers.interfaces import ArmState
from tests.vsfixtures import artefacts


@pytest.fixture(scope="module")
def vs():
    return artefacts()


def _source(vs, observer: str, mapping: str = "jacobian") -> VirtualForceSource:
    cfg = vs["cfg"]
    return build_virtual_source(cfg.virtual_sensor, vs["robot"], "wipe", cfg.loop.period_s, observer, mapping)


def _posture(robot, home, xyz):
    from cell.control.trajectory import tool_down_pose

    q, ok = robot.ik(tool_down_pose(np.asarray(xyz, float)), home)
    assert ok
    return q


def _sim(cfg, robot):
    from sim.cell import make_sim_cell
    from sim.hand import ScriptedHand

    holder = make_sim_cell(cfg, robot.limits, scene_kind="free", tool="wipe")
    return holder, ScriptedHand(holder.plant)


def _drive(holder, targets, sources, hand=None, wrench=None):
    """Send joint targets one period at a time; every source reads every sample.  Returns per source
    the (N, 6) estimates and the (N, 6) true sensor wrench (tool frame, tared by the caller)."""
    plant = holder.plant
    est: dict[str, list[np.ndarray]] = {k: [] for k in sources}
    truth = []
    if hand is not None:
        hand.set_tool_wrench(wrench) if wrench is not None else hand.release()
    for q in targets:
        plant.set_target(q)
        plant.step()
        st = plant.measured_state()
        for k, s in sources.items():
            est[k].append(s.read(st).vector)
        truth.append(plant.true_sensor_wrench())
    return {k: np.asarray(v) for k, v in est.items()}, np.asarray(truth)


def test_kalman_is_one_independent_state_per_joint(vs):
    """The observer's n-dimensional filterpy filter is exactly n scalar filters with its R and Q."""
    obs = _source(vs, "kalman").observer
    assert isinstance(obs, KalmanObserver)
    big, n = obs.kf, obs.n
    for m in (big.F, big.H, big.Q, big.R):
        assert np.allclose(m, np.diag(np.diag(m)))
    np.testing.assert_allclose(np.diag(big.R), obs.R)
    np.testing.assert_allclose(np.diag(big.Q), obs.Q)
    rng = np.random.default_rng(0)
    small = []
    for j in range(n):
        f = KalmanFilter(dim_x=1, dim_z=1)
        f.F, f.H, f.Q, f.R = np.eye(1), np.eye(1), np.eye(1) * obs.Q[j], np.eye(1) * obs.R[j]
        f.P = big.P[j:j + 1, j:j + 1].copy()
        f.x = big.x[j:j + 1].copy()
        small.append(f)
    for _ in range(200):
        z = rng.normal(size=n) * np.sqrt(obs.R) + 3.0
        big.predict()
        big.update(z.reshape(-1, 1))
        for j, f in enumerate(small):
            f.predict()
            f.update(z[j])
        assert np.allclose(big.x.ravel(), [f.x[0, 0] for f in small])
    assert np.allclose(big.P, np.diag(np.diag(big.P)))  # the joints never mix


def test_singular_pose_is_flagged_and_stays_bounded(robot):
    jac = JacobianMap(robot, np.array([0.0, 0.0, 0.035]), singular_sigma=0.03, max_damping=0.05)
    q_ok = np.array([0.1, 0.2, 1.5, 0.1, 1.4, 0.2])
    q_sing = np.array([0.1, 0.2, 1.5, 0.1, 0.0, 0.2])  # joint 5 at zero: wrist singularity
    q_near = np.array([0.1, 0.2, 1.5, 0.1, 1e-4, 0.2])  # a hair off it
    tau = np.array([0.3, -0.4, 0.2, 0.15, -0.1, 0.12])  # a little torque noise
    ok, sing, near = jac.map(q_ok, tau), jac.map(q_sing, tau), jac.map(q_near, tau)
    assert not ok.ill_conditioned and sing.ill_conditioned and near.ill_conditioned
    assert sing.sigma_min < 1e-6
    # The undamped solve explodes near the singularity; the damped one stays within the noise's scale.
    raw = np.linalg.solve(jac.jacobian(q_near).T, tau)
    assert np.linalg.norm(raw) > 100.0
    for m in (sing, near):
        assert np.all(np.isfinite(m.wrench)) and np.linalg.norm(m.wrench) < 25.0
    # Near (not at) the singularity the damping fades in smoothly: no jump between neighbours.
    pair = [jac.map(np.array([0.1, 0.2, 1.5, 0.1, a, 0.2]), tau).wrench for a in (0.02, 0.021)]
    assert np.linalg.norm(pair[0] - pair[1]) < 5.0


def _contact_map(robot, free_moment_nm):
    var = np.array([0.5, 0.6, 0.3, 0.03, 0.03, 0.09])  # a calibration's residual variances [N·m]^2
    return ContactMap(robot, np.array([0.0, 0.0, 0.035]), robot.tool.tcp_offset, free_moment_nm, var), var


def test_contact_map_reads_a_tip_force_exactly_and_model_errors_as_less_moment(robot):
    cm, var = _contact_map(robot, 0.3)
    jac = JacobianMap(robot, np.array([0.0, 0.0, 0.035]))
    q = np.array([0.1, 0.3, 1.6, -0.3, 1.5, 0.2])
    J = jac.jacobian(q)
    r = robot.tool.tcp_offset - np.array([0.0, 0.0, 0.035])
    F = np.array([4.0, -3.0, 20.0])
    tip = np.concatenate([F, np.cross(r, F)])  # a force at the TCP, read at the sensor's face
    assert np.allclose(cm.map(q, J.T @ tip).wrench, tip, atol=1e-6)
    # Joint-torque errors of the model's size: the exact inverse turns them into moments of their own,
    # the contact prior into (mostly) the force that would explain them.
    rng = np.random.default_rng(3)
    errs = rng.normal(size=(300, 6)) * np.sqrt(var)
    m_jac = np.array([jac.map(q, e).wrench[3:5] for e in errs])
    m_cm = np.array([cm.map(q, e).wrench[3:5] for e in errs])
    assert np.mean(np.abs(m_cm)) < 0.5 * np.mean(np.abs(m_jac))
    # A moment nothing at the tip explains is shrunk by the prior, and passes once the prior is wide.
    free = np.array([0.0, 0.0, 0.0, 0.0, 1.0, 0.0])
    assert 0.0 < cm.map(q, J.T @ free).wrench[4] < 0.9
    wide, _ = _contact_map(robot, 100.0)
    assert np.allclose(wide.map(q, J.T @ free).wrench, free, atol=1e-3)


def test_contact_map_stays_bounded_at_a_singularity(robot):
    cm, _ = _contact_map(robot, 0.3)
    tau = np.array([0.3, -0.4, 0.2, 0.15, -0.1, 0.12])
    for q5 in (0.0, 1e-4):
        m = cm.map(np.array([0.1, 0.2, 1.5, 0.1, q5, 0.2]), tau)
        assert m.ill_conditioned and np.all(np.isfinite(m.wrench)) and np.linalg.norm(m.wrench) < 25.0
    with pytest.raises(ValueError, match="free_moment_nm"):
        _contact_map(robot, 0.0)


def test_maps_at_one_point_share_the_pose_and_read_as_maps_of_their_own(robot):
    """The virtual sensor's map and the collision detector's share one Jacobian and SVD per pose: with poses
    alternating, each reads at a pose exactly what it read there first, and the Jacobian is the pose's own."""
    point = np.array([0.0, 0.0, 0.035])
    cm, _ = _contact_map(robot, 0.3)
    jac = JacobianMap(robot, point)
    assert jac.pose is cm.pose and JacobianMap(robot, np.zeros(3)).pose is not jac.pose
    poses = [np.array([0.1, 0.3, 1.6, -0.3, 1.5, 0.2]), np.array([-0.4, 0.1, 1.2, 0.5, 1.1, -0.3])]
    tau = np.array([0.3, -0.4, 0.2, 0.15, -0.1, 0.12])
    first: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    for k in range(6):
        i = k % 2
        q = poses[i]
        now = (jac.map(q, tau).wrench, cm.map(q, tau).wrench, jac.jacobian(q).copy())
        if i in first:
            assert all(np.array_equal(a, b) for a, b in zip(now, first[i], strict=True))
        first.setdefault(i, now)
        # Well-conditioned: the Jacobian route is the exact inverse of the pose's own Jacobian.
        assert np.allclose(now[0], np.linalg.solve(now[2].T, tau), atol=1e-9)
    assert not np.allclose(first[0][2], first[1][2])


def test_learned_map_serving_matches_xgboost(robot):
    rng = np.random.default_rng(1)
    q = rng.uniform(-1, 1, (600, 6))
    tau = rng.normal(size=(600, 6)) * 5
    w = np.column_stack([tau[:, 0], tau[:, 1], 10 * tau[:, 1] + q[:, 0], tau[:, 4], tau[:, 3], tau[:, 5]])
    bst = fit_learned_axes(q, tau, w, rounds=40)
    lm = LearnedMap(bst, JacobianMap(robot, np.zeros(3)), 6)
    batch = lm.predict_batch(q[:50], tau[:50])
    one = np.array([lm.predict(q[k], tau[k]) for k in range(50)])
    assert np.allclose(one, batch, atol=1e-3)
    # Fz, Mx, My land in their wrench slots; Fx, Fy, Mz come from the Jacobian route.
    m = lm.map(q[0], tau[0])
    assert np.allclose(m.wrench[[2, 3, 4]], one[0], atol=1e-6)


def test_free_motion_estimate_stays_near_zero(vs, home):
    """A fast move without contact: the virtual wrench must not invent a force."""
    cfg, robot = vs["cfg"], vs["robot"]
    holder, _ = _sim(cfg, robot)
    sources = {k: _source(vs, k) for k in ("kalman", "momentum")}
    a = _posture(robot, home, [0.40, -0.25, 0.20])
    b = _posture(robot, home, [0.50, 0.00, 0.30])
    dt = cfg.loop.period_s
    rest = [a] * int(0.8 / dt)
    s = np.linspace(0, 1, int(1.2 / dt))[:, None]
    blend = s**3 * (10 - 15 * s + 6 * s**2)
    move = list(a + (b - a) * blend) + list(b + (a - b) * blend)
    holder.open()
    try:
        # Reach the start, rest, re-bias in free space; then move fast there and back.
        from cell.control.trajectory import JointMove

        q0 = holder.plant.measured_state().q
        jm = JointMove(q0, a, robot.limits.velocity * 0.3)
        _drive(holder, [jm.at(k * dt) for k in range(int(jm.duration / dt) + 2)], sources)
        _drive(holder, rest, sources)
        for src in sources.values():
            src.rebias()
        est, truth = _drive(holder, move, sources)
        speed = np.max(np.abs(np.diff(np.asarray(move), axis=0)) / dt)
        assert speed > 0.5  # rad/s: a fast move, not a crawl
        assert np.max(np.abs(truth[:, :3])) < 25  # the sensor only feels the tool's own inertia
        for kind, e in est.items():
            fz = e[:, 2]
            assert np.mean(np.abs(fz)) < 4.0, f"{kind}: mean |Fz| {np.mean(np.abs(fz)):.2f} N in free motion"
            assert np.percentile(np.linalg.norm(e[:, :3], axis=1), 95) < 15.0, kind
    finally:
        holder.close()


@pytest.mark.parametrize("observer", ["kalman", "momentum"])
def test_known_static_load_is_read_correctly(vs, home, observer):
    """A 40 N press (and a twist) by the scripted hand in a posture not used for training."""
    cfg, robot = vs["cfg"], vs["robot"]
    holder, hand = _sim(cfg, robot)
    src = _source(vs, observer)
    q = _posture(robot, home, [0.47, -0.15, 0.13])
    dt = cfg.loop.period_s
    holder.open()
    try:
        from cell.control.trajectory import JointMove

        q0 = holder.plant.measured_state().q
        jm = JointMove(q0, q, robot.limits.velocity * 0.3)
        _drive(holder, [jm.at(k * dt) for k in range(int(jm.duration / dt) + 2)] + [q] * int(0.8 / dt), {"v": src})
        src.rebias()
        _, free = _drive(holder, [q] * 5, {"v": src})
        load = np.array([0.0, 0.0, 40.0, 0.0, 0.5, 0.0])
        est, truth = _drive(holder, [q] * int(1.5 / dt), {"v": src}, hand, load)
        w = est["v"][-60:].mean(axis=0)
        measured = truth[-60:].mean(axis=0) - free.mean(axis=0)
        assert measured[2] == pytest.approx(40.0, abs=0.5)  # the hand really pushes 40 N
        assert w[2] == pytest.approx(measured[2], abs=2.5)
        assert w[4] == pytest.approx(measured[4], abs=0.3)
        assert abs(w[0]) < 3.0 and abs(w[1]) < 3.0
        # Released: back to about zero.
        est, _ = _drive(holder, [q] * int(1.0 / dt), {"v": src}, hand, None)
        assert abs(est["v"][-30:, 2].mean()) < 2.5
    finally:
        holder.close()


def test_virtual_source_counts_singular_cycles(vs):
    robot = vs["robot"]
    src = _source(vs, "kalman")
    q = np.array([0.1, 0.2, 1.5, 0.1, 0.0, 0.2])
    for k in range(5):
        w = src.read(ArmState(t=k * 0.008, q=q, dq=np.zeros(6), tau=robot.gravity(q)))
        assert w.valid and np.linalg.norm(w.force) < 200
    assert src.ill_conditioned and src.summary()["ill_conditioned_cycles"] == 5


def test_kalman_observer_rebias_zeroes_a_constant_offset(vs):
    model_cfg = vs["cfg"]
    src = _source(vs, "kalman")
    obs = src.observer
    assert isinstance(obs, KalmanObserver)
    q = np.array([0.0, 0.3, 1.4, 0.0, 1.5, 0.0])
    tau = vs["robot"].gravity(q) + np.array([2.0, -3.0, 1.0, 0.5, 0.2, 0.1])
    for k in range(40):
        obs.update(ArmState(t=k * model_cfg.loop.period_s, q=q, dq=np.zeros(6), tau=tau))
    obs.rebias()
    out = obs.update(ArmState(t=1.0, q=q, dq=np.zeros(6), tau=tau))
    assert np.max(np.abs(out)) < 0.05


def test_kalman_gate_rejects_a_break_away_swing_but_passes_a_real_contact(vs):
    """An alternating +-8 N·m swing on joint 2 (stiction break-away) barely moves the estimate; a
    step that persists (a contact) comes through within a few periods."""
    obs = _source(vs, "kalman").observer
    q = np.array([0.0, 0.3, 1.4, 0.0, 1.5, 0.0])
    base = vs["robot"].gravity(q)
    k = 0

    def feed(extra):
        nonlocal k
        k += 1
        return obs.update(ArmState(t=k * 0.008, q=q, dq=np.zeros(6), tau=base + extra))

    for _ in range(40):
        feed(np.zeros(6))
    obs.rebias()
    swing = [feed(np.array([0, s, 0, 0, 0, 0], float))[1] for s in (8, -8, -8, 8, 8, -8)]
    assert max(abs(v) for v in swing) < 1.5
    settled = [feed(np.zeros(6))[1] for _ in range(20)][-1]
    step = [feed(np.array([0, 8.0, 0, 0, 0, 0]))[1] for _ in range(40)]
    assert step[-1] - settled > 6.0 and step[10] - settled > 3.0


def test_each_tool_gets_its_configured_settings():
    from cell.config import VirtualSensorConfig, load_config
    from drivers.configio import load_dataclass
    from drivers.errors import ConfigError

    # The shipped choice: the momentum observer zeroed at each tare for the wipe (and calibrate's default
    # report); for the peg the gated Kalman filter, smoother on joints 1-3, that keeps its model's zero.
    vs = load_config().virtual_sensor
    wipe, peg = vs.for_tool("wipe"), vs.for_tool("peg")
    assert (wipe.observer, wipe.zero_at_tare) == ("momentum", True)
    assert (peg.observer, peg.zero_at_tare) == ("kalman", False)
    assert peg.process_noise_nm[:3] == [0.05] * 3 and wipe.process_noise_nm == vs.process_noise_nm
    assert (wipe.mapping, peg.mapping) == ("jacobian", "contact")  # the peg is touched at its tip
    assert peg.momentum_gain == vs.momentum_gain and peg.data_dir == vs.data_dir  # the rest is shared
    one = load_dataclass(VirtualSensorConfig, {"observer": "momentum", "by_tool": {"peg": {"observer": "kalman"}}},
                         "vs")
    assert (one.for_tool("wipe").observer, one.for_tool("peg").observer) == ("momentum", "kalman")

    for bad, match in (({"drill": {"observer": "kalman"}}, r"vs\.by_tool.*unknown tool 'drill'"),
                       ({"peg": {"observer": "luenberger"}}, r"vs\.by_tool\.peg\.observer"),
                       ({"peg": {"colour": "red"}}, r"vs\.by_tool\.peg.*unknown key 'colour'"),
                       ({"peg": {"process_noise_nm": [0.1, 0.1]}}, r"vs\.by_tool\.peg\.process_noise_nm"),
                       ({"peg": {"innovation_gate": -1.0}}, r"vs\.by_tool\.peg\.innovation_gate"),
                       ({"peg": {"mapping": "nearest"}}, r"vs\.by_tool\.peg\.mapping"),
                       ({"peg": {"free_moment_nm": 0.0}}, r"vs\.by_tool\.peg\.free_moment_nm")):
        with pytest.raises(ConfigError, match=match):
            load_dataclass(VirtualSensorConfig, {"by_tool": bad}, "vs")


def test_a_tool_without_zero_at_tare_keeps_its_models_zero(vs):
    # A constant torque the model does not explain (a joint's static friction at rest): the wipe's
    # source zeroes it at a tare; one configured without the zero goes on reading it.
    from dataclasses import replace

    from cell.config import ToolSensorSettings

    cfg, robot = vs["cfg"], vs["robot"]
    keep = replace(cfg.virtual_sensor, by_tool={"wipe": ToolSensorSettings(observer="kalman", zero_at_tare=False)})
    sources = {"zeroed": _source(vs, "kalman"),
               "kept": build_virtual_source(keep, robot, "wipe", cfg.loop.period_s)}
    assert sources["kept"].label == "kalman+jacobian"
    q = np.array([0.0, 0.3, 1.4, 0.0, 1.5, 0.0])
    tau = robot.gravity(q) + np.array([0.0, 0.0, 0.0, 0.0, 0.6, 0.0])
    out = {}
    for name, src in sources.items():
        for k in range(60):
            src.read(ArmState(t=k * 0.008, q=q, dq=np.zeros(6), tau=tau))
        src.rebias()
        out[name] = src.read(ArmState(t=0.5, q=q, dq=np.zeros(6), tau=tau))
    assert np.linalg.norm(out["zeroed"].torque) < 0.05
    assert np.linalg.norm(out["kept"].torque) > 0.3


def test_a_model_made_at_another_period_is_refused_with_one_line(tmp_path):
    """Windows and causal derivative filters are defined in samples: a model made every 8 ms is refused at
    15.6 ms (one line naming both periods and what to do); at its own period, or unknown, it is accepted."""
    from cell.model.dynamics.base import ModelMeta
    from cell.sensing.virtual_sensor import period_mismatch

    meta = ModelMeta(kind="H1", robot="tm5-700", urdf_sha256="x", joints=6, features={"sample_period_s": 0.008})
    why = period_mismatch(tmp_path, meta, 0.0156)
    assert "8.0 ms" in why and "15.6 ms" in why and "prepare" in why and "\n" not in why
    assert period_mismatch(tmp_path, meta, 0.00805) == ""
    assert period_mismatch(tmp_path, ModelMeta(kind="H1", robot="tm5-700", urdf_sha256="x", joints=6), 0.0156) == ""

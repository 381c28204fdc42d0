"""The simulated TM5-700: MuJoCo rigid bodies with true losses, the arm's own joint servo, and its sensing."""

from __future__ import annotations

import collections
import collections.abc
import dataclasses
import logging
import math
from pathlib import Path

import mujoco
import numpy as np

from cell.config import SceneConfig
from drivers.interfaces import ArmState, ArmStatus
from sim.contacts import CONVEX_COLLIDER_GEOMS, RECOLLIDE_TOLERANCE, Penetration, failed_contact
from sim.mjcf import BuiltScene, build_mjcf
from sim.profile import PlantProfile

log = logging.getLogger(__name__)

# What a physics step restores to be taken again (everything mj_step reads, the solver's warm start too).
STEP_STATE = mujoco.mjtState.mjSTATE_INTEGRATION
def _hermite_basis(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cubic Hermite basis (value, d/du, d2/du2) at u = k/n, k = 1..n, for control rows
    [p_start, p_end, T*v_start, T*v_end]."""
    u = np.arange(1, n + 1) / n
    h = np.column_stack([2 * u**3 - 3 * u**2 + 1, -2 * u**3 + 3 * u**2, u**3 - 2 * u**2 + u, u**3 - u**2])
    h1 = np.column_stack([6 * u**2 - 6 * u, -6 * u**2 + 6 * u, 3 * u**2 - 4 * u + 1, 3 * u**2 - 2 * u])
    h2 = np.column_stack([12 * u - 6, -12 * u + 6, 6 * u - 4, 6 * u - 2])
    return h, h1, h2


class Plant:
    """A MuJoCo arm stepped one control period at a time (implements `sim.plant_api.PlantLike`).

    The servo interpolates linearly from the previous target to the new one over the period (as the
    real controller's interpolator does) and runs a PID plus its own model's bias torque every physics
    step.  The measured joint torque is the motor torque (which overcomes friction), with noise,
    quantisation and latency from the profile.  Friction magnitudes are updated every physics step
    into MuJoCo's dry-friction constraint, so sticking is handled by the solver, not by a stiff tanh.
    """

    def __init__(
        self,
        urdf: Path,
        profile: PlantProfile,
        scene: SceneConfig,
        q0: np.ndarray,
        physics_dt: float | None = None,
        fixture_tilt: tuple[float, float] = (0.0, 0.0),
        tool_kind: str | None = None,
    ) -> None:
        self.profile = profile
        self.fixture_tilt = fixture_tilt  # rad about world x, y: the peg scene's hole axis (bench randomisation)
        self.scene = scene
        self.dt = profile.sample_period_s
        h = physics_dt if physics_dt is not None else profile.physics_dt_s
        self.substeps = max(1, round(self.dt / h))
        self.built: BuiltScene = build_mjcf(urdf, profile, scene, self.dt / self.substeps, fixture_tilt,
                                               tool_kind)
        self._hb, self._hb1, self._hb2 = _hermite_basis(self.substeps)
        self.model = mujoco.MjModel.from_xml_string(self.built.xml)
        self.data = mujoco.MjData(self.model)
        self.n_joints = nj = 6
        self._arm = slice(0, nj)  # the arm's dofs come first; a tool may add its own (the pad slide)
        self.rng = np.random.default_rng(profile.seed)  # this run's noise
        specimen = np.random.default_rng(profile.seed if profile.specimen_seed is None else profile.specimen_seed)
        sp = profile.sensor
        self.sensor_offset = np.concatenate([
            specimen.uniform(-sp.offset_force_n, sp.offset_force_n, 3),
            specimen.uniform(-sp.offset_torque_nm, sp.offset_torque_nm, 3),
        ])
        self.ripple_phase = specimen.uniform(0, 2 * np.pi, 6)
        fr = profile.friction
        self._fc = np.array(fr.coulomb)
        self._fs = np.array(fr.stribeck)
        self._vs = np.array(fr.stribeck_velocity)
        self._ra = np.array(fr.ripple_amplitude)
        self._rc = np.array(fr.ripple_cycles)
        self._load = np.array(fr.load)
        self._effort = self._effort_limits()
        # The servo's and the friction's per-joint constants as Python floats, for the substep loop.
        self._coef = [np.asarray(c, float).tolist() for c in (
            profile.servo.kp, profile.servo.kd, profile.servo.ki, self._fc, self._load, self._effort, self._fs,
            self._vs, self._ra, self._rc, self.ripple_phase)]
        # A real controller faults on sustained motor saturation; so does this one.
        self.saturation_fault_s = 0.024
        self._saturated_s = np.zeros(6)
        self.peak_demand = np.zeros(6)  # largest |torque the servo asked for| since reset_peaks()
        self._kp = np.array(profile.servo.kp)
        self._kd = np.array(profile.servo.kd)
        self._ki = np.array(profile.servo.ki)
        self._noise = np.array(profile.torque_sensing.noise_std)
        self._quantum = profile.torque_sensing.quantum
        self._tcp_site = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "tcp")
        self._flange_body = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, "link_6")
        self._ft_site = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "ft_site")
        self.external_wrench: np.ndarray | None = None  # (6,) world-frame force/torque applied at the TCP
        self._xfrc_set = False  # a hand's wrench is in xfrc_applied
        self._pad_geom = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, "pad")
        self._pad_body = int(self.model.geom_bodyid[self._pad_geom]) if self._pad_geom >= 0 else -1
        self._pad_mu = profile.tool.pad_friction
        self._f6 = np.zeros(6)
        self._v6 = np.zeros(6)
        self._v3 = self._v6[3:]  # the pad's linear velocity (world frame), as mj_objectVelocity leaves it
        self._knots = np.empty((4, 6))  # step()'s Hermite control rows
        self._sensor_key: tuple[float, ...] | None = None  # the sensor figures _sensor_vectors was built from
        self._sensor_vectors = (np.zeros(6), np.ones(6), np.zeros(6), np.zeros(6))
        self._saved = np.empty(mujoco.mj_stateSize(self.model, STEP_STATE))
        # Per geom: whether its contacts can come from the convex collider.  A scene without such a geom
        # that can collide (the wiping table) has nothing for `_physics_step` to check or take again.
        m = self.model
        collides = (m.geom_contype != 0) | (m.geom_conaffinity != 0)
        self._convex_geom = np.isin(m.geom_type, CONVEX_COLLIDER_GEOMS) & collides
        self._check_contacts = bool(self._convex_geom.any())
        self.recollided = 0  # physics steps taken again after a failed collision detection (_physics_step)
        self.penetration = Penetration()  # the deepest contacts of the accepted physics steps (scenes with a hole)
        self._mouth_site = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_SITE, "hole_top")
        # Only the peg bench reads the depths, and only a scene with the hole has one to measure against: the
        # wiping table's every physics step has a contact, and tracking it there cost 4 % of the plant's time.
        self._track_penetration = self._mouth_site >= 0
        # Called after every physics step (the collision bench's obstacle watches its contact forces).
        self.after_physics_step: collections.abc.Callable[[], None] | None = None
        tool = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, "tool")
        self._tool_bodies = {b for b in range(self.model.nbody) if self._descends(b, tool)}
        self.reset(q0)

    def _effort_limits(self) -> np.ndarray:
        """The motors' torque limits, as the URDF (and so the MJCF's actuatorfrcrange) states them."""
        return np.array([self.model.jnt_actfrcrange[j][1] for j in range(self.n_joints)])

    # ----------------------------------------------------------------------------- state
    def reset(self, q0: np.ndarray) -> None:
        mujoco.mj_resetData(self.model, self.data)
        self.data.qpos[self._arm] = q0
        self._settle_tool()
        # The servo holds q0 from the first instant: position actuators at q0, motors at the bias.
        self.data.ctrl[:6] = q0
        self.data.ctrl[6:] = self.data.qfrc_bias[self._arm]
        mujoco.mj_forward(self.model, self.data)
        self.t = 0.0
        self.seq = 0
        self.target = np.array(q0, float)
        self._targets = (self.target.copy(), self.target.copy(), self.target.copy())  # k-3, k-2, k-1
        self._restart_command_queue(self.target)
        self._M = np.zeros((self.model.nv, self.model.nv))
        self._bind_views()
        self._integral = [0.0] * 6  # the servo's integral term (Python floats: step's substep loop)
        self._tau = np.array(self.data.qfrc_bias[self._arm])  # motor torque, static equilibrium
        self.holding = False
        self.status = ArmStatus()
        self._history: collections.deque[ArmState] = collections.deque(
            maxlen=self.profile.torque_sensing.latency_periods + 1
        )
        self._history.append(self._sample())

    def _bind_views(self) -> None:
        """Views of the MjData/MjModel arrays the substep loop touches: every attribute read of the
        bindings builds a new array, which the loop would pay several times a physics step."""
        m, d, arm = self.model, self.data, self._arm
        self._qpos, self._qvel, self._bias = d.qpos[arm], d.qvel[arm], d.qfrc_bias[arm]
        self._ctrl = d.ctrl[:12]  # the position servos' references, then the motors' torques
        self._act = d.actuator_force[:12]  # the position servos', then the motors'
        self._frictionloss = m.dof_frictionloss[arm]
        self._qfrc_actuator = d.qfrc_actuator[arm]
        self._xfrc, self._xipos = d.xfrc_applied, d.xipos
        self._sensordata = d.sensordata[:6]
        self._M_arm_T = self._M[arm, arm].T  # the arm's block of the mass matrix, as step() multiplies by it

    def _descends(self, body: int, ancestor: int) -> bool:
        while body > 0:
            if body == ancestor:
                return True
            body = int(self.model.body_parentid[body])
        return False

    def _settle_tool(self) -> None:
        """Put tool-internal dofs (the pad spring) at their static rest so a run starts without a jolt."""
        if self.model.nq > self.n_joints:
            self.data.qpos[self.n_joints:] = 0.0
            self.data.qvel[self.n_joints:] = 0.0
        mujoco.mj_forward(self.model, self.data)

    def set_target(self, q: np.ndarray) -> None:
        if self.holding:
            return
        self.target = np.array(q, float)

    def hold(self) -> None:
        """Protective stop: freeze the servo reference at the current position."""
        self.holding = True
        q = np.array(self.data.qpos[self._arm])
        self.target = q
        self._targets = (q.copy(), q.copy(), q.copy())
        self._restart_command_queue(q)
        self.status = ArmStatus(protective_stop=True)

    def reset_peaks(self) -> None:
        self.peak_demand[:] = 0.0

    def release(self) -> None:
        """Clear a protective stop or a saturation error (the operator acknowledged it)."""
        self.holding = False
        self._saturated_s[:] = 0.0
        q = np.array(self.data.qpos[self._arm])
        self.target = q
        self._targets = (q.copy(), q.copy(), q.copy())
        self._restart_command_queue(q)
        self.status = ArmStatus()

    def take_command_latency(self) -> int:
        """Hand the command channel's latency to whoever emulates that channel (a Listen node's queue): the
        plant stops delaying targets and returns the periods it delayed them by."""
        latency = self.profile.servo.command_latency_periods
        if latency:
            self.profile = dataclasses.replace(
                self.profile, servo=dataclasses.replace(self.profile.servo, command_latency_periods=0))
            self._restart_command_queue(np.array(self.target, float))
        return latency

    def _restart_command_queue(self, q: np.ndarray) -> None:
        """The command channel's latency: the servo takes the target set `command_latency_periods` ago."""
        latency = self.profile.servo.command_latency_periods
        self._command_queue: collections.deque[np.ndarray] = collections.deque(
            [q.copy() for _ in range(latency + 1)], maxlen=latency + 1)

    # ----------------------------------------------------------------------------- physics
    def step(self) -> None:
        m, d = self.model, self.data
        n = self.substeps
        h = m.opt.timestep
        T = self.dt
        # The controller buffers the streamed targets by one period and interpolates them with a
        # cubic Hermite spline (central-difference velocities), as arm controllers do with streamed
        # set-points: during this period the reference runs from target[k-2] to target[k-1].  The
        # servo feeds forward the spline's velocity and its own model's M(q) times its acceleration.
        p3, p2, p1 = self._targets
        self._command_queue.append(self.target.copy())
        p0 = self._command_queue[0]
        # Hermite control data: positions p2, p1 and central-difference velocities (scaled by T), written
        # into one array (np.stack of the same rows costs more than the rest of this preamble).
        knots = self._knots
        knots[0], knots[1] = p2, p1
        np.subtract(p1, p3, out=knots[2])
        np.subtract(p0, p2, out=knots[3])
        knots[2:] /= 2.0
        q_refs = self._hb @ knots
        dq_refs = self._hb1 @ knots / T
        mujoco.mj_fullM(m, d, self._M)
        ff_inertia = (self._hb2 @ knots / T**2) @ self._M_arm_T
        # The substep loop runs on Python floats: per joint, six numbers, where each numpy call on a
        # 6-vector costs as much as a dozen float operations.  Each expression keeps numpy's order of
        # operations, so the results are bit for bit those of the vectorised form.
        q_refs_l = q_refs.tolist()
        kd_dq_l = (self._kd * dq_refs).tolist()
        ffi_l = ff_inertia.tolist()
        kp, kd, ki, fc, load, effort, fs, vs, ra, rc, phase = self._coef
        integral = self._integral
        sat = self._saturated_s.tolist()
        peak = self.peak_demand.tolist()
        qpos, qvel, bias, act, ctrl = self._qpos, self._qvel, self._bias, self._act, self._ctrl
        ff, coulomb, stick, ripple = [0.0] * 6, [0.0] * 6, [0.0] * 6, [0.0] * 6
        joints = range(6)
        pad = self._pad_body >= 0
        for k in range(n):
            q_ref, kd_dq, ffi = q_refs_l[k], kd_dq_l[k], ffi_l[k]
            q, v, b = qpos.tolist(), qvel.tolist(), bias.tolist()
            for j in joints:
                e = q_ref[j] - q[j]
                integral[j] += e * h
                # PD (kp, kd) lives in the position actuators (ctrl[:6] = q_ref); the motors add the
                # velocity and inertial feedforward, the integral and the controller's own bias model.
                f = kd_dq[j] + ki[j] * integral[j] + b[j] + ffi[j]
                ff[j] = f
                tau_est = kp[j] * e - kd[j] * v[j] + f
                # Friction (MuJoCo's dry-friction constraint): load-dependent Coulomb, Stribeck, ripple.
                coulomb[j] = fc[j] * (1.0 + load[j] * abs(tau_est) / effort[j])
                x = v[j] / vs[j]
                stick[j] = -(x * x)
                ripple[j] = ra[j] * math.sin(rc[j] * q[j] + phase[j])
            stick_e = np.exp(stick).tolist()  # numpy's exp: it rounds differently from math.exp
            ctrl[:] = q_ref + ff
            self._frictionloss[:] = [coulomb[j] + fs[j] * stick_e[j] + ripple[j] for j in joints]
            if pad or self.external_wrench is not None or self._xfrc_set:
                # Cartesian body forces (xfrc_applied), not joint-space ones: the F/T sensor reads
                # body interaction forces and must feel both the friction and a hand on the tool.
                # (Cleared once more after a hand lets go: a tool without a pad, the peg, would
                # otherwise keep the last load forever.)
                self._xfrc.fill(0.0)
                self._xfrc_set = self.external_wrench is not None
                if pad:
                    self._wipe_friction()
                if self.external_wrench is not None:
                    self._apply_tcp_wrench(self.external_wrench)
            self._physics_step()
            if self.after_physics_step is not None:
                self.after_physics_step()
            # Motor saturation: |what the servo asked for| over the effort limit, for how long in a row.
            a = act.tolist()
            for j in joints:
                demand = abs(a[j] + a[j + 6])
                if demand > peak[j]:
                    peak[j] = demand
                sat[j] = sat[j] + h if demand > effort[j] else 0.0
        self._saturated_s[:] = sat
        self.peak_demand[:] = peak
        self._tau = self._qfrc_actuator.copy()  # clamped at the effort limit by MuJoCo
        if max(sat) >= self.saturation_fault_s and not self.status.error:
            j = int(np.argmax(self._saturated_s))
            log.error("plant: joint %d motor saturated for %.0f ms: controller error",
                      j + 1, 1e3 * self._saturated_s[j])
            self.hold()
            self.status = ArmStatus(error=True, protective_stop=True)
        self._targets = (p2, p1, p0.copy())
        self.t += self.dt
        if not self.status.protective_stop:
            self.seq += 1
        self._history.append(self._sample())

    def _physics_step(self) -> None:
        """One `mj_step`; a step whose collision detection failed is taken again, more precisely.

        MuJoCo's convex collider (CCD) now and then gets a contact wrong (`failed_contact`).  At its default
        1e-6 tolerance these were a 4.8 mm phantom at a survey touch (a 13 kN impulse), a 0.27 mm jump within
        1 ms as the peg slid along the wall (a 113 N spike) and reversed wall normals (~5 % of the peg bench's
        steps); at the plant's `CCD_TOLERANCE` (1e-9) 110-220 steps in a 50-trial bench remain.  Such a step
        is taken again from the state before it with `RECOLLIDE_TOLERANCE` (config/plants/README.md).  Only
        steps with a contact of a geom the convex collider handles are checked: the others' colliders are
        closed-form, and a scene without such geoms (the wiping table) saves no state to go back to."""
        m, d = self.model, self.data
        if not self._check_contacts:
            mujoco.mj_step(m, d)
            if d.ncon and self._track_penetration:
                self.penetration.update(d, self._mouth_site)
            return
        mujoco.mj_getState(m, d, self._saved, STEP_STATE)
        mujoco.mj_step(m, d)
        if not d.ncon:
            return
        why = failed_contact(m, d) if self._convex_geom[d.contact.geom].any() else None
        if why is not None:
            mujoco.mj_setState(m, d, self._saved, STEP_STATE)
            tol = m.opt.ccd_tolerance
            m.opt.ccd_tolerance = RECOLLIDE_TOLERANCE
            try:
                mujoco.mj_step(m, d)
            finally:
                m.opt.ccd_tolerance = tol
            self.recollided += 1
            log.debug("plant: %s at t=%.3f s: step taken again with ccd_tolerance %g",
                      why, d.time, RECOLLIDE_TOLERANCE)
        if self._track_penetration:
            self.penetration.update(d, self._mouth_site)

    def _wipe_friction(self, v_eps: float = 0.005) -> None:
        """Coulomb friction of the wiping head on the table, regularised below `v_eps` [m/s]:
        F = -mu * Fn * tanh(|v_t| / v_eps) * v_t / |v_t|, applied at the contact point."""
        m, d = self.model, self.data
        if not d.ncon:
            return
        contacts = d.contact
        pad, body = self._pad_geom, self._pad_body
        v = None  # the pad's velocity: the same at each of its contacts, taken at the first that pushes
        load: list[float] = []  # the pad's Cartesian load, summed over its contacts as _push adds them
        for i, pair in enumerate(contacts.geom.tolist()):
            if pad not in pair:
                continue
            mujoco.mj_contactForce(m, d, i, self._f6)
            fn = self._f6.item(0)
            if fn <= 0.0:
                continue
            if v is None:
                mujoco.mj_objectVelocity(m, d, mujoco.mjtObj.mjOBJ_BODY, body, self._v6, 0)
                v = self._v3
            normal = contacts.frame[i, :3]
            # (ndarray.dot: the same dot product as the @ operator, without the operator's dispatch.)
            vt = v - normal * v.dot(normal)
            speed = math.sqrt(vt.dot(vt))  # np.linalg.norm's own arithmetic, without its checks
            if speed < 1e-9:
                continue
            along = float(-self._pad_mu * fn * np.tanh(speed / v_eps))
            vx, vy, vz = vt.tolist()
            push = self._lever_load(body, (along * vx / speed, along * vy / speed, along * vz / speed),
                                    contacts.pos[i])
            if not load:
                load = self._xfrc[body].tolist()
            load = [s + f for s, f in zip(load, push, strict=True)]
        if load:
            self._xfrc[body] = load

    def _apply_tcp_wrench(self, wrench: np.ndarray) -> None:
        """Apply a world-frame wrench at the TCP (a scripted 'hand' on the tool)."""
        d = self.data
        tool_body = self.model.site_bodyid[self._tcp_site]
        self._push(int(tool_body), wrench[:3].tolist(), wrench[3:], d.site_xpos[self._tcp_site])

    def _push(self, body: int, force: list[float], torque: np.ndarray | None, point: np.ndarray) -> None:
        """Add a world-frame force applied at `point` (plus a torque) to a body's Cartesian load."""
        load = self._lever_load(body, force, point)
        if torque is not None:
            load[3:] = [t + mo for t, mo in zip(torque.tolist(), load[3:], strict=True)]
        self._xfrc[body] += load

    def _lever_load(self, body: int, force: collections.abc.Sequence[float], point: np.ndarray) -> list[float]:
        """A world-frame force at `point` as the body's Cartesian load: the force and its lever's moment r x F about
        the body's centre of mass, on Python floats (np.cross on 3-vectors costs more than the whole friction)."""
        fx, fy, fz = force
        (px, py, pz), (cx, cy, cz) = point.tolist(), self._xipos[body].tolist()
        rx, ry, rz = px - cx, py - cy, pz - cz
        return [fx, fy, fz, ry * fz - rz * fy, rz * fx - rx * fz, rx * fy - ry * fx]

    def _sample(self) -> ArmState:
        # In place on the noise's array: the same operations as tau + noise * std (a sum does not depend on
        # the order of its two terms), rounded to the quantum, without a new array each.
        tau = self.rng.normal(0.0, 1.0, 6)
        tau *= self._noise
        tau += self._tau
        if self._quantum > 0:
            tau /= self._quantum
            np.round(tau, out=tau)
            tau *= self._quantum
        return ArmState(t=self.t, q=self._qpos.copy(), dq=self._qvel.copy(), tau=tau, status=self.status,
                        seq=self.seq)

    # ----------------------------------------------------------------------------- views
    def measured_state(self) -> ArmState:
        """The delayed sample (torque-sensing latency), with the controller's status flags as they are now."""
        sample = self._history[0]
        return sample if sample.status == self.status else dataclasses.replace(sample, status=self.status)

    def true_state(self) -> ArmState:
        return self._history[-1]

    def true_motor_torque(self) -> np.ndarray:
        return np.array(self._tau)

    def flange_pose(self) -> tuple[np.ndarray, np.ndarray]:
        d = self.data
        return np.array(d.xpos[self._flange_body]), np.array(d.xmat[self._flange_body]).reshape(3, 3)

    def tool_pose(self) -> tuple[np.ndarray, np.ndarray]:
        d = self.data
        return np.array(d.site_xpos[self._tcp_site]), np.array(d.site_xmat[self._tcp_site]).reshape(3, 3)

    def true_sensor_wrench(self) -> np.ndarray:
        """Noiseless wrench at the sensor face, sensor frame, in the cell convention (tool on environment).

        MuJoCo's force/torque sensors give what the parent (sensor body) exerts on the child (tool):
        minus the tool's weight and inertial load, minus the contact force on the tool.  Once the tool
        weight is tared away that is exactly the force the tool exerts on the environment, so pressing
        the tool along its +z onto a surface reads +Fz, as the cell convention wants.
        """
        return np.array(self.data.sensordata[:6])

    def sensor_reading(self) -> np.ndarray:
        """What the WACOH sensor would report: true wrench + unloaded offset + noise, quantised, saturated."""
        noise, quantum, lo, hi = self._sensor_scales()
        w = np.add(self._sensordata, self.sensor_offset)  # (the view true_sensor_wrench copies)
        # One draw of six with per-axis scales: the generator takes the same standard normals in the same order
        # as a draw of three forces then three torques, and scales each alike.
        w += self.rng.normal(0.0, noise, 6)
        w /= quantum
        # Clipping only picks one of the three values: maximum and minimum do it without np.clip's overhead.
        return np.minimum(np.maximum(np.round(w, out=w) * quantum, lo), hi)

    def _sensor_scales(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The sensor's noise, quantum and saturation (low, high) per axis, forces then torques, built again
        whenever the profile's figures change."""
        sp = self.profile.sensor
        key = (sp.noise_force_n, sp.noise_torque_nm, sp.quantum_force_n, sp.quantum_torque_nm,
               sp.saturation_force_n, sp.saturation_torque_nm)
        if key != self._sensor_key:
            self._sensor_key = key
            force, torque = np.ones(3), np.ones(3)
            noise, quantum, saturation = (np.concatenate([force * key[i], torque * key[i + 1]]) for i in (0, 2, 4))
            self._sensor_vectors = (noise, quantum, -saturation, saturation)
        return self._sensor_vectors

    def contact_force_world(self) -> np.ndarray:
        """Sum of the contact forces the environment exerts on the tool (and its head), world frame."""
        total = np.zeros(3)
        f6 = np.zeros(6)
        for i in range(self.data.ncon):
            c = self.data.contact[i]
            b1 = int(self.model.geom_bodyid[c.geom1])
            b2 = int(self.model.geom_bodyid[c.geom2])
            if (b1 in self._tool_bodies) == (b2 in self._tool_bodies):
                continue
            mujoco.mj_contactForce(self.model, self.data, i, f6)
            f = c.frame.reshape(3, 3).T @ f6[:3]  # world frame, along the normal from geom1 to geom2
            total += f if b2 in self._tool_bodies else -f
        return total

"""The peg-in-hole task's settings: every threshold, speed and gain, with the per-force-source overrides."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from cell.config import check_task_motion
from cell.control.impedance import ImpedanceParams
from drivers.configio import load_dataclass, require
from drivers.errors import ConfigError


@dataclass
class PegConfig:
    hole_xy: list[float] | None = None  # nominal hole centre (x, y) [m], base frame; default scene.hole_center
    peg_diameter_m: float = 0.0214  # the tool's peg (only its radius places the tilted peg's lowest rim point)
    entry_tilt_deg: float = 12.0  # peg tilt for the entry: its lowest rim point leads into the hole
    lead_direction_deg: float = 180.0  # world-xy direction of the lowest rim point from the peg axis
    approach_height_m: float = 0.006  # start: lowest rim point this high above the nominal mouth
    approach_speed_mps: float = 0.007  # under guarded motion's bound (cell/control/guarded.py: 70 N / 9300 N per m/s)
    slow_height_m: float = 0.0015  # below this (lowest point above the mouth), approach slowly (stiff contact)
    slow_speed_mps: float = 0.0015
    max_approach_m: float = 0.015  # travel below the approach start with no contact: fail
    retare_before_approach: bool = True  # re-zero the force source at the approach start (see _approach)
    # Survey: the fixture's top face is machined square to the hole, so its normal is the hole's axis.
    # Touch it with the tilted peg's lowest rim point at a few points around the hole and fit the plane;
    # everything after works in that hole frame (a hole tilted by 2 deg wedges an upright peg ~10 mm in).
    survey: bool = True
    survey_radius_m: float = 0.0145  # touch points this far from the nominal centre (the face: 10.9-22.9 mm)
    # A point opposite an earlier one is predicted (the face passes near the nominal mouth centre), so its
    # descent is short: 90 and 270 first.
    survey_angles_deg: list[float] = field(default_factory=lambda: [90.0, 270.0, 180.0])
    survey_height_m: float = 0.0008  # start a touch this high above the nominal mouth plane (2 deg x 19 mm: 0.66)
    survey_predict_margin_m: float = 0.0003  # ... or this high above the height predicted from the opposite point
    survey_speed_mps: float = 0.0015  # down to the face (stiff contact: the impact grows with the speed)
    survey_depth_m: float = 0.003  # no face within this much below the start: fail
    survey_lift_m: float = 0.0002  # off the face before moving on (the arm sticks: a higher lift pulls harder)
    survey_move_speed_mps: float = 0.07
    survey_lift_speed_mps: float = 0.003  # the lift off a touch point, until the tip has risen survey_lift_m
    survey_max_lift_m: float = 0.002  # the reference this far above that with the tip still down: fail
    max_lead_m: float = 0.0001  # guarded moves: the reference at most this far ahead of the measured tip
    # ... and only this far once the descending tip has decelerated as on a contact (stall test below): a
    # face is far stiffer than the servo (~3 N/um), and the virtual sensor's Fz needs a few cycles to show a
    # touch, during which a 0.1 mm lead pressed up to 330 N into the face.
    touch_lead_m: float = 0.00002
    touch_force_n: float = 3.0  # ... and then Fz above this (not contact_force_n) on survey/contact_cycles is a touch
    survey_cycles: int = 2  # Fz over contact_force_n on this many cycles of the confirm window: touching
    # The touch tests read the mean of the last this many Fz readings.  1: the reading itself.  2 cancels a
    # force source that rings at the control period (signs alternating cycle to cycle; the virtual sensor's
    # fast touch channel does so at a long period, its gain times the period above 1) while a touch, steady
    # or bouncing on and off the face, keeps half its peak or more.
    touch_mean_cycles: int = 1
    survey_confirm_s: float = 0.05  # hold still after a first crossing; no second one in this time: noise
    # Arrived above a touch point, the reference holds this long before the descent and its touch test: as the
    # joints come to rest they stick, and the virtual sensor's reading kicks along the last motion for a few
    # periods (9.5-11 N on its fast touch channel in free air), which read as a touch would fit a tilted face.
    survey_settle_s: float = 0.08
    surveyed_approach_height_m: float = 0.0005  # approach start above the surveyed mouth (known to ~0.1 mm)
    max_hole_tilt_deg: float = 5.0  # the surveyed face tilted further than this: fail (not the expected fixture)
    contact_force_n: float = 6.0  # Fz above this: touching (above the virtual sensor's free-motion error)
    contact_moment_nm: float = 0.6  # |(Mx, My)| above this: touching
    contact_cycles: int = 3  # approach: Fz over contact_force_n on this many cycles running is a contact
    inside_depth_m: float = 0.0001  # lowest rim point this far below the mouth: the lead edge is in the hole
    engage_depth_m: float = 0.0005  # highest rim point this far below the mouth: the whole face is in the hole
    # |(Mx, My)| above this with the peg in the hole: one side touching (above the virtual sensor's motion
    # errors, which grew to ~1.3 N·m in the fast feed with the Jacobian map; see comply_deadband_nm)
    side_moment_nm: float = 2.0
    probe_force_n: float = 10.0  # Fz held while a contact is classified
    probe_settle_s: float = 0.2
    probe_average_s: float = 0.1
    max_probe_s: float = 1.0  # the probe force not reached in this time: classify anyway
    backoff_m: float = 0.0015  # lift before a lateral shift (stuck outside)
    backoff_speed_mps: float = 0.006
    search_step_m: float = 0.0015  # stuck outside: the lowest point moves out on a ring this much per attempt
    max_probes: int = 8  # stuck-outside attempts before giving up
    max_offset_m: float = 0.006  # lateral search radius around the nominal hole: beyond it, fail
    slide_lift_m: float = 0.0002  # lift the face off the far rim before sliding (the lead edge stays in)
    slide_speed_mps: float = 0.008  # toward the lead side while the wall cannot be near
    slide_fast_m: float = 0.0065  # the wall is at least (hole radius - max lateral error) away
    slide_slow_speed_mps: float = 0.0025  # then slowly: contacts are stiff
    slide_block_m: float = 0.0006  # the tip lagging the slide reference by this much: blocked by the wall
    # or lifted this far above the reference: the wall (or the mouth's edge) carries the peg up as it is
    # pushed on.  A slide that ended on the moment had climbed 0.2-0.35 mm; one that did not (the moment
    # already above block_moment_nm / 2 as the phase began) climbed on to 0.6 mm and 70-190 N.
    slide_climb_m: float = 0.00015
    climb_return_speed_mps: float = 0.001  # after a climb, the reference's way back down (PegSearch.z_return)
    block_moment_nm: float = 1.0  # or the wall's push showing in (Mx, My) (above the Jacobian map's +-0.5 N·m
    # errors while sliding; the stall test below finds the wall first in most cases)
    # or the tip stalling: its speed along the move under this share of the commanded speed for
    # `stall_cycles` cycles (after `stall_after_s`, the servo's lag) -- independent of the wrench's errors
    stall_fraction: float = 0.3
    stall_cycles: int = 3
    stall_after_s: float = 0.2
    max_slide_m: float = 0.016  # slid this far without meeting the wall: fail
    chord_backoff_m: float = 0.001  # back from the wall before measuring the chord across the lead
    chord_speed_mps: float = 0.0035  # while the wall may be near
    min_chord_m: float = 0.0012  # a shorter chord is a false block: measure it again further back
    chord_free_margin_m: float = 0.0003  # the way back across the chord: fast up to this short of its start
    max_chord_retries: int = 2
    min_probe_travel_m: float = 0.0003  # a search move is not "blocked" before it has travelled this far
    rotate_rate_dps: float = 12.0  # rotation toward upright about the wall contact
    rotate_max_force_n: float = 20.0  # the rotation slows to a stop as Fz approaches this
    rotate_give_up_s: float = 3.0  # still blocked after this long: insert from the tilt reached
    insert_force_n: float = 15.0  # Fz setpoint while pushing in
    insert_speed_limit_mps: float = 0.015  # the impedance law's step is clipped to this speed
    free_insert_speed_mps: float = 0.016  # feed while the peg meets no resistance in the hole
    # ... but slower until the peg is entry_depth_m deep: a peg centred 0.1-0.15 mm off chatters on the
    # mouth's edge, harder the faster it goes (why: docs/peg.md, "Speeds").
    entry_speed_mps: float = 0.003
    entry_depth_m: float = 0.002
    # A peg can wedge only while it is shallower than about mu x D (Whitney's two-point-contact analysis);
    # a wedge met at the feed's speed is a head-on hit (a 182 N spike 2.4 mm in at 16 mm/s), so the feed
    # stays at guarded motion's speed until then.  mu: the nominal peg-on-bore friction of the materials.
    wedge_friction: float = 0.25
    wedge_speed_mps: float = 0.007
    hole_diameter_m: float = 0.0218  # the nominal hole (paper: 21.8 mm); with the peg, the nominal clearance
    # Upright with the lead side on the wall: step this far off it.  Default: the nominal radial clearance
    # (hole - peg) / 2, which puts the peg's axis on the hole's (0.2 mm for the paper's 21.4 in 21.8; half
    # of it left the peg rubbing the wall all the way in and dragging on it on the way out, 90-150 N spikes).
    wall_clearance_m: float | None = None
    centre_speed_mps: float = 0.002  # ... taken at this speed
    # Tight fits (tasks/peg/bore.py): with a nominal radial clearance at or below this, the upright peg is
    # centred on the bore by running it once round the wall before the feed, and again after each stall.
    # The paper's 0.2 mm radial clearance is above it: the chord's centre is close enough there.
    bore_centring_below_m: float = 0.0001
    bore_orbit_press_m: float = 0.00006  # the orbit this much wider than the bore: presses the wall ~k_servo x this
    bore_orbit_speed_mps: float = 0.001
    bore_orbit_deg: float = 360.0  # the orbit's path recorded over this much of the circle
    bore_radius_tolerance_m: float = 0.00003  # a free fit's radius this far from the radial clearance: not the bore
    # The free feed at tight fits: a peg that meets a wedge at the feed's speed stops within the servo's reaction
    # (~20 ms), so the peak force grows with the speed (225 N at 16 mm/s, a wedge 2.5 mm in at the 0.1 mm fit).
    tight_insert_speed_mps: float = 0.006
    # ... and at most this many radial clearances per second: the tighter the fit, the harder the stick-slip at the
    # wall (0.05 mm: 4 mm/s; why: docs/peg.md, "Tight fits").
    tight_feed_per_clearance_hz: float = 160.0
    # The retract while the peg is in a tight bore (retract_slow_speed_mps otherwise): stick-slip at the wall on the
    # way out grows with the speed, and the retract's time is not insertion time (why: docs/peg.md, "Tight fits").
    tight_retract_speed_mps: float = 0.003
    bore_hold_fraction: float = 0.5  # the compliant lateral shift kept within this share of the radial clearance
    # ... and the reference kept within this share of the radial clearance of the measured tip, laterally: the peg
    # cannot go further, so a reference beyond it only presses the wall, and the servo's integral turns that
    # lead into tens of newtons (compliance on the virtual moments led the tip by 0.1-0.6 mm at 0.1 mm: 100-130 N)
    bore_tether_fraction: float = 1.0
    # Twist at tight fits (tasks/peg/twist.py): the peg turns to and fro about its own axis while it is fed, realigned
    # and retracted, so its sliding at the wall is mostly round the bore and the wall's friction mostly opposes that,
    # not the feed (screw insertion); 0: no twist.
    twist_amplitude_deg: float = 10.0
    twist_frequency_hz: float = 0.5
    target_depth_m: float = 0.027  # success: the tip (face centre) this far below the mouth
    stall_s: float = 0.6  # depth gained less than stall_depth_m over this window: stuck
    stall_depth_m: float = 0.0003
    realign_time_s: float = 0.5  # stalled inside: lift and comply at a light force for this long
    realign_force_n: float = 4.0
    realign_lift_m: float = 0.0005
    max_realigns: int = 6
    # rad/s of compliant tilt per N·m of tool moment (about the tip).  0 by default: the surveyed hole axis
    # is within 0.1 deg, and tilting on the virtual sensor's moment errors jammed the peg at the mouth.
    rotation_gain: float = 0.0
    shift_gain: float = 0.004  # m/s of compliant tip shift per N·m of tool moment
    # |(Mx, My)| below this: no compliant motion and no slower feed -- the force source's error band.  With
    # the Jacobian map the virtual sensor erred by +-0.5 N·m while the arm moved slowly (friction at low
    # joint speeds) and up to ~1.3 N·m during the fast feed; at 0.3 its errors shifted the peg into the wall
    # (0.2 mm radial clearance) within ~0.1 s.  With the contact map its |M| in the free feed stays under
    # 0.54 N·m (99th percentile); a lower band bought nothing measurable, so it stays at 1.5 (docs/peg.md,
    # "Force-source thresholds").
    # The centred peg on the surveyed axis needs no compliance to go in.
    comply_deadband_nm: float = 1.5
    max_tilt_deg: float = 15.0  # the peg tilted further than this from vertical: fail
    release_time_s: float = 0.3  # ramp the push force to zero before retracting
    retract_height_m: float = 0.01  # tip this high above the mouth at the end
    retract_speed_mps: float = 0.02
    retract_slow_speed_mps: float = 0.006  # until the tip is 2 mm above the mouth
    max_pull_n: float = 40.0  # pull-out force (negative Fz) beyond this while retracting ...
    max_pull_s: float = 0.3  # ... for longer than this: fail
    max_force_n: float = 70.0  # task-level force limit (the cell's safety limit is separate)
    max_moment_nm: float = 5.0
    move_speed_fraction: float = 0.15  # of the joint speed limits, for the move to the start pose
    # Hold still this long before re-zeroing the force source (at the start and above the mouth before the
    # approach): after a move the joints creep for about a second and the hybrid model reads Coulomb
    # friction from that creep's sign: a longer hold lowers the virtual moments' errors during the
    # insertion (why: docs/peg.md, "Force-source thresholds").
    tare_time_s: float = 1.2
    max_duration_s: float = 40.0
    impedance: ImpedanceParams = field(default_factory=lambda: ImpedanceParams(m=1.0, b=50.0, k_tau=0.015, k_v=0.0))

    def feed_speed(self, depth: float, speed: float) -> float:
        """`speed`, held to wedge_speed_mps while the peg is shallow enough to wedge (depth < mu x D)."""
        return min(speed, self.wedge_speed_mps) if depth < self.wedge_friction * self.peg_diameter_m else speed

    def tight_feed_speed(self, radial_clearance: float) -> float:
        """The free feed's speed at a tight fit: tight_insert_speed_mps, slower still as the clearance shrinks."""
        return min(self.tight_insert_speed_mps, self.tight_feed_per_clearance_hz * radial_clearance)

    def retract_speed(self, depth: float, radial_clearance: float) -> float:
        """The retract's speed: slowly while the peg is in the hole or just above it (a stiff contact at the mouth
        turns speed into force spikes), at tight fits at tight_retract_speed_mps."""
        if depth < -0.002:
            return self.retract_speed_mps
        return self.tight_retract_speed_mps if radial_clearance <= self.bore_centring_below_m else \
            self.retract_slow_speed_mps

    def validate(self, where: str) -> None:
        if self.hole_xy is not None:
            require(len(self.hole_xy) == 2, f"{where}.hole_xy", f"must be (x, y), got {self.hole_xy}")
        require(0 < self.contact_force_n < self.probe_force_n < self.max_force_n, f"{where}.probe_force_n",
                "must lie between contact_force_n and max_force_n")
        require(self.touch_force_n <= self.contact_force_n, f"{where}.touch_force_n",
                f"must not exceed contact_force_n ({self.contact_force_n})")
        require(self.contact_force_n < self.insert_force_n < self.max_force_n, f"{where}.insert_force_n",
                "must lie between contact_force_n and max_force_n")
        require(self.contact_moment_nm < self.side_moment_nm < self.max_moment_nm, f"{where}.side_moment_nm",
                "must lie between contact_moment_nm and max_moment_nm")
        require(self.comply_deadband_nm < self.side_moment_nm, f"{where}.comply_deadband_nm",
                f"must be below side_moment_nm ({self.side_moment_nm})")
        require(self.inside_depth_m < self.target_depth_m, f"{where}.target_depth_m", "must exceed inside_depth_m")
        require(self.probe_settle_s + self.probe_average_s <= self.max_probe_s,
                f"{where}.max_probe_s", "must cover probe_settle_s + probe_average_s")
        require(self.contact_cycles >= 1, f"{where}.contact_cycles", "must be >= 1")
        require(1 <= self.touch_mean_cycles <= 4, f"{where}.touch_mean_cycles", "must lie in 1..4")
        require(self.max_probes >= 1 and self.max_realigns >= 0, f"{where}.max_probes", "must be >= 1")
        require(self.min_chord_m > 0 and self.max_chord_retries >= 0, f"{where}.min_chord_m",
                "must be > 0 (and max_chord_retries >= 0)")
        require(0 < self.entry_tilt_deg < self.max_tilt_deg, f"{where}.entry_tilt_deg",
                "must lie between 0 and max_tilt_deg")
        for name in ("peg_diameter_m", "approach_height_m", "approach_speed_mps", "slow_height_m", "slow_speed_mps",
                     "max_approach_m", "inside_depth_m", "engage_depth_m", "probe_settle_s", "probe_average_s",
                     "backoff_m", "backoff_speed_mps", "search_step_m", "max_offset_m", "slide_lift_m",
                     "slide_speed_mps", "slide_fast_m", "slide_slow_speed_mps", "slide_block_m", "slide_climb_m",
                     "climb_return_speed_mps",
                     "block_moment_nm", "max_slide_m", "chord_backoff_m", "chord_speed_mps", "chord_free_margin_m",
                     "min_probe_travel_m", "rotate_rate_dps", "rotate_max_force_n", "rotate_give_up_s",
                     "insert_speed_limit_mps", "free_insert_speed_mps", "centre_speed_mps", "entry_speed_mps",
                     "bore_orbit_press_m", "bore_orbit_speed_mps", "tight_insert_speed_mps", "bore_radius_tolerance_m",
                     "wedge_friction", "wedge_speed_mps",
                     "bore_hold_fraction", "bore_orbit_deg", "bore_tether_fraction", "twist_frequency_hz",
                     "tight_retract_speed_mps", "tight_feed_per_clearance_hz",
                     "entry_depth_m",
                     "stall_s", "stall_depth_m", "max_lead_m", "touch_lead_m", "touch_force_n", "comply_deadband_nm",
                     "realign_time_s", "realign_force_n", "realign_lift_m", "shift_gain",
                     "release_time_s", "retract_height_m", "retract_speed_mps", "retract_slow_speed_mps",
                     "max_pull_n", "max_pull_s",
                     "move_speed_fraction", "tare_time_s", "max_duration_s"):
            require(getattr(self, name) > 0, f"{where}.{name}", f"must be > 0, got {getattr(self, name)}")
        require(self.twist_amplitude_deg >= 0, f"{where}.twist_amplitude_deg", "must be >= 0")
        require(self.move_speed_fraction <= 1, f"{where}.move_speed_fraction", "must be <= 1")
        check_task_motion(self, where)
        require(self.hole_diameter_m > self.peg_diameter_m, f"{where}.hole_diameter_m",
                f"must exceed peg_diameter_m ({self.peg_diameter_m})")
        require(self.wall_clearance_m is None or self.wall_clearance_m >= 0, f"{where}.wall_clearance_m",
                "must be >= 0")
        if self.survey:
            require(len(self.survey_angles_deg) >= 3, f"{where}.survey_angles_deg",
                    "needs at least 3 points to fit the fixture's face")
            for name in ("survey_radius_m", "survey_height_m", "survey_speed_mps", "survey_depth_m",
                         "survey_lift_m", "survey_move_speed_mps", "survey_predict_margin_m",
                         "survey_lift_speed_mps", "survey_max_lift_m", "survey_cycles",
                         "survey_confirm_s",
                         "surveyed_approach_height_m", "max_hole_tilt_deg"):
                require(getattr(self, name) > 0, f"{where}.{name}", f"must be > 0, got {getattr(self, name)}")
            require(self.survey_settle_s >= 0, f"{where}.survey_settle_s", f"must be >= 0, got {self.survey_settle_s}")


FORCE_SOURCES = ("virtual", "sensor")


def load_peg_config(raw: dict[str, Any] | None, where: str, force_source: str = "virtual") -> PegConfig:
    """The task's config for `force_source`: `by_force_source.<source>` overrides the fields it names
    (the thresholds that sit above a source's error band differ: the F/T sensor's moments are good to
    ~0.05 N·m, the virtual sensor's to ~1 N·m while the arm moves)."""
    data = dict(raw or {})
    by_source = data.pop("by_force_source", None) or {}
    if not isinstance(by_source, dict):
        raise ConfigError(f"{where}.by_force_source must be a mapping of {' | '.join(FORCE_SOURCES)} to overrides")
    for name, overrides in by_source.items():
        if name not in FORCE_SOURCES:
            raise ConfigError(f"{where}.by_force_source: unknown force source '{name}' "
                              f"(known: {', '.join(FORCE_SOURCES)})")
        if not isinstance(overrides, dict):
            raise ConfigError(f"{where}.by_force_source.{name} must be a mapping of task fields")
    overrides = by_source.get(force_source, {})
    try:
        return load_dataclass(PegConfig, {**data, **overrides}, where)
    except ConfigError as exc:
        if overrides:
            raise ConfigError(f"{exc} (with the {where}.by_force_source.{force_source} overrides)") from None
        raise

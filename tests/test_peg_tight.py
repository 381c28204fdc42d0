"""Tight fits: the bore centring's orbit and fit, the clearance-bounded hold, and where the strategy engages."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from tasks.peg.bore import BoreCentring, arc_span, fit_circle
from tasks.peg.config import PegConfig, load_peg_config

DT = 0.008
RC = 0.00005  # radial clearance of the 21.7 mm peg in the 21.8 mm bore


def _pose(xy: np.ndarray) -> pin.SE3:
    return pin.SE3(np.eye(3), np.array([xy[0], xy[1], 0.05]))


def _run(bore: BoreCentring, tip_of, start: np.ndarray, steps: int = 3000) -> tuple[pin.SE3, pin.SE3]:
    """Step the centring with the tip a function of the reference (a bore, or free space)."""
    ref, tip = _pose(start), _pose(start)
    bore.begin(ref, tip)
    for _ in range(steps):
        if bore.step(ref, tip) == "centred":
            break
        tip = _pose(tip_of(ref.translation[:2]))
    return ref, tip


def test_a_circle_is_fitted_through_a_start_on_the_wall_and_a_short_arc():
    # The tip dwells where it started (on the wall) and then slides over part of the bore: both lie on it.
    centre = np.array([0.4500, -0.1200])
    angles = np.concatenate([np.full(30, 2.0), np.linspace(-0.6, 0.3, 40)])
    xy = centre + RC * np.column_stack([np.cos(angles), np.sin(angles)])
    c, r = fit_circle(xy)
    assert np.linalg.norm(c - centre) < 1e-7 and r == pytest.approx(RC, abs=1e-7)
    assert arc_span(xy, c) < math.radians(170)


def test_the_orbit_finds_the_bore_centre_from_a_start_on_its_wall():
    cfg = PegConfig(peg_diameter_m=0.0217)
    centre = np.array([0.45, -0.12])
    start = centre + np.array([0.0, -RC])  # the chord left the peg against one wall

    def in_bore(ref_xy: np.ndarray) -> np.ndarray:  # a stiff arm, no friction: the wall stops the tip
        off = ref_xy - centre
        r = float(np.linalg.norm(off))
        return ref_xy if r <= RC else centre + off * (RC / r)

    bore = BoreCentring(cfg, DT, RC)
    ref, _ = _run(bore, in_bore, start)
    assert not bore.active and bore.centre is not None
    assert np.linalg.norm(bore.centre - centre) < 2e-6
    assert np.linalg.norm(ref.translation[:2] - centre) < 2e-6  # and the reference was taken there


def test_a_peg_that_meets_no_wall_is_left_where_it_started():
    # Free space: the tip follows the orbit, whose radius is not the bore's: the fit is not used.
    cfg = PegConfig(peg_diameter_m=0.0217)
    start = np.array([0.45, -0.12])
    bore = BoreCentring(cfg, DT, RC)
    ref, _ = _run(bore, lambda xy: xy, start)
    assert bore.centre is None
    assert np.linalg.norm(ref.translation[:2] - start) < 1e-9


def test_the_hold_keeps_the_compliant_shift_within_the_clearance():
    cfg = PegConfig(peg_diameter_m=0.0217)
    bore = BoreCentring(cfg, DT, RC)
    bore.centre = np.array([0.45, -0.12])
    ref = _pose(np.array([0.45 + 0.001, -0.12]))  # a millimetre off: only presses the wall
    bore.hold(ref, ref)
    assert np.linalg.norm(ref.translation[:2] - bore.centre) == pytest.approx(cfg.bore_hold_fraction * RC)


def test_the_paper_geometry_does_not_engage_the_tight_fit_centring(cfg):
    pcfg = load_peg_config(cfg.tasks.get("peg"), "tasks.peg")
    assert (pcfg.hole_diameter_m - pcfg.peg_diameter_m) / 2 > pcfg.bore_centring_below_m
    for peg in (0.0217, 0.02175):
        assert (pcfg.hole_diameter_m - peg) / 2 <= pcfg.bore_centring_below_m


def test_the_tether_keeps_the_reference_within_the_clearance_of_the_tip():
    # No bore measured (the orbit's fit was rejected): compliance may still not lead the blocked tip by a millimetre.
    cfg = PegConfig(peg_diameter_m=0.0217)
    bore = BoreCentring(cfg, DT, RC)
    tip = _pose(np.array([0.45, -0.12]))
    ref = _pose(np.array([0.45 + 0.0006, -0.12 + 0.0002]))
    bore.hold(ref, tip)
    lead = ref.translation[:2] - tip.translation[:2]
    assert np.linalg.norm(lead) == pytest.approx(cfg.bore_tether_fraction * RC)
    assert lead[1] / lead[0] == pytest.approx(1 / 3)  # drawn straight back toward the tip
    near = _pose(np.array([0.45 + 0.2 * RC, -0.12]))
    bore.hold(near, tip)
    assert near.translation[0] == pytest.approx(0.45 + 0.2 * RC)  # within the clearance: left alone


def test_the_twist_turns_the_peg_about_its_own_axis_only():
    cfg = PegConfig(peg_diameter_m=0.0217, twist_amplitude_deg=5.0, twist_frequency_hz=2.0)
    bore = BoreCentring(cfg, DT, RC)
    tilted = pin.SE3(pin.exp3(np.array([0.01, -0.02, 0.3])), np.array([0.45, -0.12, 0.05]))
    ref = tilted.copy()
    angles = []
    for _ in range(int(round(1 / (cfg.twist_frequency_hz * DT)))):  # one period
        bore.hold(ref, ref)
        rel = tilted.rotation.T @ ref.rotation
        angles.append(math.degrees(math.atan2(rel[1, 0], rel[0, 0])))
        assert np.allclose(ref.rotation[:, 2], tilted.rotation[:, 2], atol=1e-12)  # the peg's axis stays
        assert np.allclose(ref.translation, tilted.translation)
    assert max(angles) == pytest.approx(5.0, abs=0.1) and min(angles) == pytest.approx(-5.0, abs=0.1)
    assert abs(angles[-1]) < 0.5  # back where it began after a period


def test_the_paper_geometry_is_neither_held_nor_twisted():
    cfg = PegConfig(peg_diameter_m=0.0214, twist_amplitude_deg=5.0)
    rc = (cfg.hole_diameter_m - cfg.peg_diameter_m) / 2
    bore = BoreCentring(cfg, DT, rc)
    bore.centre = np.array([0.45, -0.12])
    tip = _pose(np.array([0.45, -0.12]))
    ref = pin.SE3(np.eye(3), np.array([0.451, -0.12, 0.05]))
    for _ in range(10):
        bore.hold(ref, tip)
    assert np.allclose(ref.rotation, np.eye(3)) and ref.translation[0] == pytest.approx(0.451)


def test_the_retract_is_slower_only_in_a_tight_bore():
    cfg = PegConfig(peg_diameter_m=0.0217, tight_retract_speed_mps=0.003)
    paper = (cfg.hole_diameter_m - 0.0214) / 2
    assert cfg.retract_speed(0.01, paper) == cfg.retract_slow_speed_mps  # the paper's path is unchanged
    assert cfg.retract_speed(0.01, RC) == 0.003
    assert cfg.retract_speed(-0.005, RC) == cfg.retract_speed(-0.005, paper) == cfg.retract_speed_mps

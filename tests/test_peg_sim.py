"""The simulator at tight peg fits: the collider's bore, contact penetration and where a tilted peg wedges."""

from __future__ import annotations

import pytest

from bench.peg_failures import count_kinds, failure_kind
from sim.peg_fit import Fit, bore_error, predicted_jam_depth, wedge

FITS = [Fit(peg_d=0.0217), Fit(peg_d=0.02175)]  # 0.1 mm and 0.05 mm diametral clearance in the 21.8 mm bore


@pytest.mark.parametrize("fit", FITS, ids=["0.1mm", "0.05mm"])
def test_the_collider_sees_the_bore_within_a_tenth_of_the_clearance(fit):
    # The wall is a ring of 32 prisms: a round peg moved out of the centre in any direction meets it where a
    # true cylinder would, to a tenth of the fit.
    assert bore_error(fit) < fit.clearance / 10


@pytest.mark.parametrize("fit", FITS, ids=["0.1mm", "0.05mm"])
@pytest.mark.parametrize("tilt_deg", [0.5, 1.0, 2.0])
def test_a_tilted_peg_wedges_where_geometry_says_and_penetrates_under_a_tenth_of_the_fit(fit, tilt_deg):
    # Pushed at the task's insertion force (15 N), a peg held at a tilt stops where the bore leaves no room:
    # clearance / tan(tilt) at the higher corner.  It stops a little deeper, by the contacts' yield.
    w = wedge(fit, tilt_deg, push_n=15.0, side_n=3.0)
    assert w.max_penetration_m < fit.clearance / 10
    assert w.depth_m == pytest.approx(w.predicted_depth_m, rel=0.12)
    assert w.depth_m >= w.predicted_depth_m - 0.05e-3  # never shallower than geometry allows


def test_the_predicted_wedge_is_the_classic_clearance_over_tan_tilt():
    fit = Fit(peg_d=0.0217)
    # Small tilts: c / tan(a), less the peg's own D (1/cos a - 1) / tan(a), plus r sin(a) to the face centre.
    assert predicted_jam_depth(fit, 0.01) == pytest.approx(0.1e-3 / 0.01, rel=0.02)
    assert predicted_jam_depth(fit, 0.02) < predicted_jam_depth(fit, 0.01) / 1.9


def test_failure_reasons_are_counted_by_kind():
    failures = [("failed", "jammed at depth 5.2 mm after 6 realignments (Fz 7.2 N, |M| 1.09 N·m)"),
                ("safety_stop", "tool force 195.6 N exceeds limit 150.0 N"),
                ("timeout", "task did not finish within 40.0 s"),
                ("failed", "jammed at depth 1.5 mm after 6 realignments"),
                ("collision", "joint 2 residual 9.1 N·m over 6.0: protective stop")]
    assert failure_kind(*failures[1]) == "safety_stop_force"
    assert count_kinds(failures) == {"jammed": 2, "safety_stop_force": 1, "timeout": 1, "collision_detection": 1}


def test_penetration_is_counted_on_walls_and_in_the_bore_apart_from_top_touches():
    """A box sinks 0.5 mm into the floor, another 0.2 mm into a wall: the side and bore figures are the wall's,
    and the bore's only where the contact is below the hole's mouth."""
    import mujoco

    from sim.plant import Penetration

    def contacts(mouth_z: float) -> Penetration:
        m = mujoco.MjModel.from_xml_string(f"""<mujoco><worldbody>
          <geom name="floor" type="plane" size="1 1 .1"/>
          <geom name="wall" type="box" pos="1 0 .5" size=".1 1 .5"/>
          <site name="hole_top" pos="1 0 {mouth_z}"/>
          <body pos="0 0 .0995"><freejoint/><geom type="box" size=".1 .1 .1"/></body>
          <body pos=".8002 0 .5"><freejoint/><geom type="box" size=".1 .1 .1"/></body>
        </worldbody></mujoco>""")
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        pen = Penetration()
        pen.update(d, mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, "hole_top"))
        return pen

    deep = contacts(mouth_z=1.0)  # the wall contact is 0.5 m below the mouth: in the bore
    assert deep.any == pytest.approx(0.5e-3, rel=1e-3)
    assert deep.side == pytest.approx(0.2e-3, rel=1e-3) and deep.bore == deep.side
    above = contacts(mouth_z=0.3)  # the same contact above the mouth: on the wall, not in the bore
    assert above.side == pytest.approx(0.2e-3, rel=1e-3) and above.bore == 0.0

"""VP carried from one visit to another through their registration (kept clinic frames).

Clinic tuning person 1 of ``benchmarks/clinic_comparison.py``: at A (hair over the nape) the
analysis refuses VP, at E (another day's dress and hair, a posture sway) it finds it. The
frames are kept (``tests/data/scenes/person-1-{A,E}.npz``) so that every processor sees them.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from kept_visits import kept_visit

from rasterserver.comparison import CARRY_REACH, Registration, carry_vp, register


@pytest.fixture(scope="module")
def person_1() -> dict[str, object]:
    a, station = kept_visit("person-1-A", "1:A")
    e, _ = kept_visit("person-1-E", "1:E")
    return {"A": a, "E": e, "station": station, "registration": register(a, e)}


def true_vp(person: int) -> np.ndarray:
    """Where the simulator put C7 for acquisition A (the person as drawn)."""
    from rasterserver.simulator.body import make_body, random_body

    return np.asarray(make_body(random_body(person)).landmarks["vertebra_prominens"])


def test_vp_of_one_visit_is_carried_to_the_visit_without(person_1) -> None:
    a, e, reg = person_1["A"], person_1["E"], person_1["registration"]
    assert a.shape.landmark("VP") is None and e.shape.landmark("VP") is not None
    carried = carry_vp(e, a, reg, source_is_a=False)
    assert carried.reason == "" and carried.source == "1:E"
    assert carried.point is not None
    # E's own VP lies 0.8 mm from its truth; carried, 1.0 mm from A's
    assert np.linalg.norm(carried.point - true_vp(1)) < 2.0
    assert carried.surface_distance <= CARRY_REACH


def test_what_is_not_carried_says_why(person_1) -> None:
    a, e, reg = person_1["A"], person_1["E"], person_1["registration"]
    assert "has no VP to carry" in carry_vp(a, e, reg, source_is_a=True).reason
    assert "has its own VP" in carry_vp(e, e, reg, source_is_a=False).reason
    # a registration that puts VP 10 cm off A's measured surface carries nothing there
    moved = np.eye(4)
    moved[2, 3] = -100.0
    far = dataclasses.replace(reg, transform=moved @ reg.transform)
    refused = carry_vp(e, a, far, source_is_a=False)
    assert refused.point is None and "from the measured surface" in refused.reason
    assert refused.surface_distance > CARRY_REACH


def test_the_midline_is_measured_with_a_carried_vp_and_vps_own_position_is_not(person_1) -> None:
    from rasterserver_plugins.back_shape import CARRIED, VP_POSITION, analyse_back

    from rasterserver.simulator.back_truth import truth
    from rasterserver.simulator.body import make_body, random_body

    a, e, reg = person_1["A"], person_1["E"], person_1["registration"]
    point = carry_vp(e, a, reg, source_is_a=False).point
    gravity = person_1["station"].gravity
    own = a.shape.parameter_table()
    shape = analyse_back(a.surface, gravity, vp_carried=point)
    got, reasons = shape.parameter_table(), shape.reason_table()
    expected = truth(make_body(random_body(1)))["parameters"]
    assert "lateral_deviation_max_mm" not in own
    for name, tolerance in (
        ("lateral_deviation_rms_mm", 1.0),
        ("surface_rotation_rms_deg", 0.5),
        ("scoliosis_angle_deg", 3.0),
    ):
        assert abs(got[name]["value"] - expected[name]["value"]) < tolerance, name
    for name in VP_POSITION:
        assert name not in got and reasons[name] == CARRIED
    assert reasons["frame"] == CARRIED and not np.isfinite(shape.frame_origin).any()
    assert "carried from another visit" in reasons["VP"]  # said, though VP is given
    # the dimples and the pelvis are this visit's own, unchanged
    for name in ("pelvic_tilt_mm", "pelvic_rotation_deg"):
        assert got[name] == own[name]
    # a visit that found its own VP ignores a carried one
    mine = analyse_back(e.surface, gravity, vp_carried=point)
    assert mine.parameter_table() == e.shape.parameter_table()


def test_registration_direction_is_respected(person_1) -> None:
    a, e = person_1["A"], person_1["E"]
    reg = register(e, a)  # A moved onto E this time: E is visit A of the pair
    carried = carry_vp(e, a, reg, source_is_a=True)
    assert carried.point is not None
    assert np.linalg.norm(carried.point - true_vp(1)) < 2.0
    assert isinstance(reg, Registration)

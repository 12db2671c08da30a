"""Clinic scenes: head with hair, arm postures, clothing, random draws (fixed seeds)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from rasterserver.errors import InputError
from rasterserver.simulator.body import (
    BodyParameters,
    HairAlbedo,
    clinic_station,
    make_body,
    random_body,
)


def test_random_body_is_reproducible_and_serialisable() -> None:
    a, b = random_body(7), random_body(7)
    assert a == b
    assert random_body(8) != a
    again = BodyParameters.from_dict(json.loads(json.dumps(a.to_dict())))
    assert again == a


@pytest.mark.parametrize("posture", ["close", "away", "hips"])
def test_scene_has_head_arms_and_clothing(posture: str) -> None:
    scene = make_body(BodyParameters(arm_posture=posture, waistband=1.2), spacing=4.0)
    names = [o.name for o in scene.objects]
    assert names == ["head", "trunk", "left-arm", "right-arm", "clothing"]
    head = np.asarray(scene.objects[0].mesh.vertices)
    trunk = np.asarray(scene.objects[1].mesh.vertices)
    vp = scene.landmarks["vertebra_prominens"]
    # the head sits above C7 (Y down), the trunk reaches below the buttocks
    assert head[:, 1].max() < vp[1] and head[:, 1].min() < vp[1] - 150.0
    assert trunk[:, 1].max() > scene.landmarks["sacrum_point"][1]
    assert scene.metadata["kind"] == "body" and scene.metadata["body"]["arm_posture"] == posture
    right = np.asarray(scene.objects[3].mesh.vertices)
    if posture == "away":  # the hand is far out to the side
        assert right[:, 0].max() > trunk[:, 0].max() + 100.0


def test_hair_is_dark_and_uneven() -> None:
    hair = HairAlbedo(0.1, 0.6, seed=3)
    pts = np.column_stack([np.linspace(-50, 50, 2000), np.full(2000, -500.0), np.zeros(2000)])
    albedo = hair(pts)
    assert 0.05 < np.median(albedo) < 0.2
    assert 0.3 < np.std(np.log(albedo)) < 1.0


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(InputError, match="arm_posture"):
        BodyParameters(arm_posture="waving")  # type: ignore[arg-type]
    with pytest.raises(InputError, match="hair_albedo"):
        BodyParameters(hair_albedo=0.0)
    with pytest.raises(InputError, match="waistband"):
        BodyParameters(waistband=3.0)
    with pytest.raises(InputError, match="head_tilt"):
        BodyParameters(head_tilt=float("nan"))
    with pytest.raises(InputError, match="unknown body parameters"):
        BodyParameters.from_dict({"wings": 2})


def test_scene_without_head_or_clothing() -> None:
    scene = make_body(BodyParameters(head=False, waistband=None), spacing=4.0)
    assert [o.name for o in scene.objects] == ["trunk", "left-arm", "right-arm"]


def test_clinic_station_takes_the_held_out_raster() -> None:
    st = clinic_station(3, "mseq8-35to65")
    assert st.raster_definition.name == "mseq8-35to65"
    assert st.raster_definition.n_lines == 136


def test_clinic_station_sees_a_tall_field() -> None:
    st = clinic_station(3, "mseq7")
    assert st.raster_definition.name == "mseq7"
    assert (st.camera.width, st.camera.height) == (640, 800)
    # a point 400 mm above and below the origin on the back plane is inside the frame
    pix = st.camera.project(np.array([[0.0, -400.0, 0.0], [0.0, 400.0, 0.0]]))
    assert np.all((pix[:, 1] > 0) & (pix[:, 1] < 800))

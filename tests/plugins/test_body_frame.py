"""The body-fixed frame from VP, DL and DR."""

from __future__ import annotations

import numpy as np
from rasterserver_plugins.body_frame import body_frame


def test_frame_axes() -> None:
    vp = np.array([5.0, -230.0, 20.0])
    dl = np.array([-50.0, 210.0, 5.0])
    dr = np.array([52.0, 214.0, 3.0])
    frame = body_frame(vp, dl, dr)
    assert frame is not None
    origin, axes = frame
    np.testing.assert_allclose(origin, 0.5 * (dl + dr))
    np.testing.assert_allclose(axes @ axes.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(axes) > 0.999  # right-handed
    transverse, vertical, sagittal = axes
    np.testing.assert_allclose(vertical, (vp - origin) / np.linalg.norm(vp - origin))
    assert transverse[0] > 0.99  # towards the patient's right
    assert sagittal[2] < -0.99  # posterior: towards the camera


def test_degenerate_points() -> None:
    p = np.array([0.0, 0.0, 0.0])
    assert body_frame(p, np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])) is None
    vp = np.array([0.0, -100.0, 0.0])
    assert body_frame(vp, np.array([0.0, 10.0, 0.0]), np.array([0.0, -10.0, 0.0])) is None

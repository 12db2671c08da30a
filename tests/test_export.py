"""The numbering overlay: lines coloured by number, and the reasons for what is unnumbered."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from rasterserver.export import overlay_image


def _lines(reason: str) -> SimpleNamespace:
    col = np.repeat(np.arange(20, 60), 2)
    row = np.tile([20.0, 30.0], 40)
    number = np.tile([5, -1], 40).astype(np.int32)
    line_id = np.tile([0, 1], 40).astype(np.int32)
    return SimpleNamespace(col=col, row=row, number=number, line_id=line_id, reason=reason)


def test_reasons_are_printed_under_the_frame() -> None:
    frame = np.zeros((60, 80), np.uint8)
    plain = overlay_image(frame, _lines(""))
    assert plain.shape == (120, 160, 3)  # nothing unnumbered said: the frame alone
    one = overlay_image(frame, _lines("no peaks"))
    two = overlay_image(frame, _lines("no peaks; 3 line(s) left unnumbered"))
    assert one.shape[1] == two.shape[1] == 160
    assert 120 < one.shape[0] < two.shape[0]
    panel = two[120:]
    assert panel.mean() > 200 and np.count_nonzero(panel.max(axis=2) < 100) > 20
    # the frame part is the same with or without the panel
    assert np.array_equal(two[:120], plain)
    assert overlay_image(frame, _lines("no peaks"), reasons=False).shape == (120, 160, 3)


def test_a_long_reason_is_wrapped_to_the_width() -> None:
    frame = np.zeros((60, 80), np.uint8)
    short = overlay_image(frame, _lines("a component refused"))
    long = overlay_image(frame, _lines("a component refused " * 12))
    assert long.shape[1] == short.shape[1] == 160
    assert long.shape[0] > short.shape[0] + 36  # several wrapped rows

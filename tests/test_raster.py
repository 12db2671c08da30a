"""Raster diapositive definition: the window code and its JSON form."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rasterserver.documents import load_raster_document, raster_from_document
from rasterserver.errors import InputError
from rasterserver.raster import (
    DEFAULT_CODE,
    RASTER_FORMAT,
    Raster,
    code_min_distance,
    default_raster,
    generate_window_code,
    get_raster,
    make_raster,
    window_code_position,
)


def test_default_raster_layout() -> None:
    r = default_raster()
    assert r.n_lines == 90
    assert r.spacing == pytest.approx(10.0)
    assert set(r.kinds) == {"light", "heavy"}
    light = r.widths[r.code == 0]
    heavy = r.widths[r.code == 1]
    assert np.all(light / heavy[0] == pytest.approx(40 / 60))
    assert r.numbers[0] == 1 and np.all(np.diff(r.numbers) == 1)
    assert get_raster("default") is r


def test_default_code_is_the_searched_one() -> None:
    bits = generate_window_code(90, window=9, min_distance=2, seed=0)
    assert "".join(map(str, bits)) == DEFAULT_CODE


def test_code_windows_unique_with_distance_two() -> None:
    r = default_raster()
    assert r.window == 9 and r.min_distance == 2
    assert code_min_distance(r.code, r.window) >= 2
    for start in range(r.n_lines - r.window + 1):
        window = list(r.kinds[start : start + r.window])
        np.testing.assert_array_equal(window_code_position(r, window), [start])
        # any single misread line yields no valid window: detected, never mis-numbered
        for flip in range(r.window):
            bad = r.code[start : start + r.window].copy()
            bad[flip] ^= 1
            assert window_code_position(r, bad).size == 0
            assert start in window_code_position(r, bad, max_mismatches=1)


def test_longest_run() -> None:
    text = DEFAULT_CODE
    assert "00000" not in text and "11111" not in text


def test_raster_json_round_trip(tmp_path) -> None:  # type: ignore[no-untyped-def]
    r = default_raster()
    data = json.loads(r.to_json())
    assert data["format"] == RASTER_FORMAT
    assert data["lines"][0] == {
        "number": 1,
        "v": float(r.positions[0]),
        "kind": r.kinds[0],
        "width": float(r.widths[0]),
    }
    back = load_raster_document(Path(r.save(tmp_path / "raster.json")))
    np.testing.assert_array_equal(back.positions, r.positions)
    np.testing.assert_array_equal(back.numbers, r.numbers)
    np.testing.assert_array_equal(back.widths, r.widths)
    assert back.kinds == r.kinds and back.window == r.window and back.name == r.name


def test_custom_raster_and_validation() -> None:
    r = make_raster(30, window=7, min_distance=2, spacing=8.0, name="small")
    assert r.n_lines == 30 and code_min_distance(r.code, 7) >= 2
    with pytest.raises(ValueError, match="increasing"):
        Raster("x", [1, 2], [5.0, 4.0], ("light", "heavy"), [1.0, 1.0], window=1)
    with pytest.raises(ValueError, match="kinds"):
        Raster("x", [1], [5.0], ("bold",), [1.0], window=1)
    with pytest.raises(InputError, match="format"):
        raster_from_document({"format": "nope"})
    with pytest.raises(KeyError):
        get_raster("nope")


def test_the_held_out_raster_differs_from_every_tuning_one() -> None:
    """The raster held out from the numbering's tuning: another window, line count, spacing
    and light:heavy ratio than the clinic rasters, and a code whose windows may differ in one
    line only (every window of eight lines still unique)."""
    from rasterserver.raster import CLINIC_RASTERS, HELD_OUT_RASTERS, m_sequence

    assert HELD_OUT_RASTERS == ("mseq8-35to65",)
    r = get_raster("mseq8-35to65")
    assert get_raster("mseq8-35to65") is r
    assert r.n_lines == 136 and r.window == 8 and r.min_distance == 1
    assert r.spacing == pytest.approx(7.2)
    np.testing.assert_array_equal(r.code, m_sequence(8)[:136])
    words = {tuple(r.code[i : i + 8]) for i in range(r.n_lines - 7)}
    assert len(words) == r.n_lines - 7
    ratio = r.widths[r.code == 1][0] / r.widths[r.code == 0][0]
    assert ratio == pytest.approx(1.3 / 0.7)
    for name in ("default", *CLINIC_RASTERS):
        other = get_raster(name)
        assert name not in HELD_OUT_RASTERS
        assert (other.n_lines, other.window) != (r.n_lines, r.window)
        assert other.widths.max() / other.widths.min() != pytest.approx(ratio)


def test_the_held_out_rasters_tuning_twin_shares_its_kind_not_its_code() -> None:
    """The twin (for tuning) has the held-out raster's window, distance and light:heavy
    ratio, but another code (another primitive polynomial), line count and spacing: no code
    window of the held-out raster is learnt by tuning on it."""
    from rasterserver.raster import HELD_OUT_RASTERS, TUNING_RASTERS, m_sequence

    assert TUNING_RASTERS == ("mseq8b-35to65",)
    twin, held = get_raster("mseq8b-35to65"), get_raster(HELD_OUT_RASTERS[0])
    assert (twin.window, twin.min_distance) == (held.window, held.min_distance) == (8, 1)
    assert twin.n_lines != held.n_lines and twin.spacing != pytest.approx(held.spacing)
    np.testing.assert_array_equal(twin.code, m_sequence(8, taps=(8, 6, 5, 3))[:132])
    words = [tuple(twin.code[i : i + 8]) for i in range(twin.n_lines - 7)]
    assert len(set(words)) == len(words)  # every window unique
    # no run of 16 lines of the held-out code occurs in the twin's (another sequence)
    held_runs = {tuple(held.code[i : i + 16]) for i in range(held.n_lines - 15)}
    assert not any(tuple(twin.code[i : i + 16]) in held_runs for i in range(twin.n_lines - 15))
    ratio = lambda r: r.widths[r.code == 1][0] / r.widths[r.code == 0][0]  # noqa: E731
    assert ratio(twin) == pytest.approx(ratio(held))

"""The one ingest request shaping of the command line and the HTTP route."""

from __future__ import annotations

import io

import numpy as np
import pytest

from rasterserver.archive import Archive
from rasterserver.config import Settings
from rasterserver.errors import ConflictError, InputError
from rasterserver.ingest_request import frame_roles, ingest_request, parse_shape


def _npy() -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.zeros((8, 8), np.uint8))
    return buffer.getvalue()


def test_roles_shape_and_kind_are_checked_and_spelled_as_the_front_end_does() -> None:
    assert frame_roles(None, 2) == ["raster", "raster"]
    assert frame_roles(["dark"], 3) == ["dark"] * 3
    with pytest.raises(InputError, match=r"^2 files but 3 --role values$"):
        ingest_request([(b"", "a"), (b"", "b")], roles=["raster"] * 3,
                       spelling={"roles": "--role values"})
    assert parse_shape("604X576") == (604, 576) and parse_shape("") is None
    with pytest.raises(InputError, match=r"^--shape '6x': expected ROWSxCOLUMNS"):
        ingest_request([(b"", "a")], shape="6x", spelling={"shape": "--shape"})
    with pytest.raises(InputError, match="kind must be one of patient, calibration, test"):
        ingest_request([(b"", "a")], kind="holiday")
    request = ingest_request([(b"x", "a.npy"), (b"y", "b.npy")], roles=["projector-on",
                             "projector-off"], shape="2x3", dtype="uint8", patient="P1",
                             idempotency_key="k", source="cli")
    assert [(f.name, f.role) for f in request.spec.frames] == [
        ("a.npy", "projector-on"), ("b.npy", "projector-off")]
    assert (request.shape, request.dtype, request.spec.source) == ((2, 3), "uint8", "cli")


def test_store_with_and_without_a_key(settings: Settings) -> None:
    with Archive.create(settings) as archive:
        archive.add_patient("P1")
        acq, replayed = ingest_request([(_npy(), "f.npy")], patient="P1").store(archive)
        assert not replayed and len(acq.frames) == 1
        keyed = ingest_request([(_npy(), "f.npy")], patient="P1", idempotency_key="k1",
                               source="station-1")
        first, replayed = keyed.store(archive)
        assert not replayed
        again, replayed = keyed.store(archive)
        assert replayed and again.uid == first.uid
        with pytest.raises(ConflictError):
            ingest_request([(_npy(), "f.npy")], patient="P1", notes="other",
                           idempotency_key="k1", source="station-1").store(archive)

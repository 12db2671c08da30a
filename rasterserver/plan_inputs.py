"""What a plan needs from the catalogue besides the chain: the frame, the calibration and
raster documents in force, and the results already stored under the plan's chain keys.

Calibration rows never change once stored, so :class:`InputsCache` parses each one once per
:class:`~rasterserver.pipeline.Pipeline`: a job plans thousands of acquisitions with a few.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session, selectinload

from rasterserver.archive import Archive
from rasterserver.catalog.models import Acquisition, Calibration, Frame, StageResult
from rasterserver.catalog.models import Station as StationRow
from rasterserver.chain import CachedResult
from rasterserver.documents import calibration_raster, stored_calibration
from rasterserver.errors import InputError, NotFoundError
from rasterserver.hashing import canonical_json_sha256
from rasterserver.optics import Station
from rasterserver.raster import Raster

__all__ = [
    "ChainInputs",
    "InputsCache",
    "acquisitions_by_uid",
    "load_calibration",
    "raster_frame",
    "stored_results",
    "stored_results_many",
]


@dataclass(frozen=True)
class ChainInputs:
    """A calibration row's parsed documents and the checksums that enter chain keys."""

    row_id: int
    sha256: str
    station: Station
    raster: Raster
    raster_sha256: str


class InputsCache:
    """:class:`ChainInputs` per calibration row, parsed once.

    Parameters
    ----------
    archive : Archive
        Where calibration rows are read.
    """

    def __init__(self, archive: Archive) -> None:
        self.archive = archive
        self._by_row: dict[int, ChainInputs] = {}

    def get(
        self, acquisition: Acquisition, wanted: tuple[str, int | None] | None
    ) -> ChainInputs:
        """The inputs of ``acquisition`` (see :func:`load_calibration`)."""
        attached = acquisition.calibration_id
        if wanted is None and attached is not None and attached in self._by_row:
            return self._by_row[attached]
        row, station, raster = load_calibration(self.archive, acquisition, wanted)
        inputs = self._by_row.get(row.id)
        if inputs is None:
            raster_sha = canonical_json_sha256(raster.to_dict())
            inputs = ChainInputs(row.id, row.sha256, station, raster, raster_sha)
            self._by_row[row.id] = inputs
        return inputs


def stored_results(s: Session, acquisition_id: int, keys: list[str]) -> dict[str, CachedResult]:
    """The stored results of ``acquisition_id`` among the chain ``keys``."""
    query = select(
        StageResult.chain_key,
        StageResult.id,
        StageResult.store_path,
        StageResult.output_checksum,
        StageResult.reason,
    ).where(StageResult.acquisition_id == acquisition_id, StageResult.chain_key.in_(keys))
    return {
        key: CachedResult(result_id, store_path, checksum, reason)
        for key, result_id, store_path, checksum, reason in s.execute(query)
    }


def acquisitions_by_uid(s: Session, uids: Sequence[str]) -> dict[str, Acquisition]:
    """The acquisitions among ``uids`` that exist, with their frames, in one query."""
    query = (
        select(Acquisition)
        .options(selectinload(Acquisition.frames))
        .where(Acquisition.uid.in_(list(uids)))
    )
    return {row.uid: row for row in s.scalars(query)}


def stored_results_many(
    s: Session, wanted: Mapping[int, list[str]], *, page: int = 40
) -> dict[int, dict[str, CachedResult]]:
    """:func:`stored_results` for many acquisitions (id → chain keys), a few queries in all.

    ``page`` acquisitions per query: databases limit the parameters of a statement; the
    query goes by acquisition id first, the unique index's leading column.

    Returns
    -------
    dict
        Acquisition id → chain key → stored result (only acquisitions with some).
    """
    found: dict[int, dict[str, CachedResult]] = {}
    ids = sorted(i for i, keys in wanted.items() if keys)
    for start in range(0, len(ids), page):
        chunk = ids[start : start + page]
        keys = sorted({key for i in chunk for key in wanted[i]})
        query = select(
            StageResult.acquisition_id,
            StageResult.chain_key,
            StageResult.id,
            StageResult.store_path,
            StageResult.output_checksum,
            StageResult.reason,
        ).where(StageResult.acquisition_id.in_(chunk), StageResult.chain_key.in_(keys))
        for acquisition_id, key, result_id, store_path, checksum, reason in s.execute(query):
            if key in wanted[acquisition_id]:
                found.setdefault(acquisition_id, {})[key] = CachedResult(
                    result_id, store_path, checksum, reason
                )
    return found


def raster_frame(acquisition: Acquisition, index: int | None) -> Frame:
    """The frame to process: ``index``, or the acquisition's first ``raster`` frame.

    Raises
    ------
    NotFoundError, InputError
        No such frame; no raster frame.
    """
    frames = sorted(acquisition.frames, key=lambda f: f.index)
    if index is not None:
        for frame in frames:
            if frame.index == index:
                return frame
        raise NotFoundError(f"acquisition {acquisition.uid} has no frame {index}")
    for frame in frames:
        if frame.role == "raster":
            return frame
    roles = ", ".join(sorted({f.role for f in frames})) or "none"
    raise InputError(
        f"acquisition {acquisition.uid} has no raster frame (frame roles: {roles}); "
        "give the frame index to process another one"
    )


def load_calibration(
    archive: Archive, acquisition: Acquisition, wanted: tuple[str, int | None] | None
) -> tuple[Calibration, Station, Raster]:
    """The calibration row that applies to ``acquisition``, with its parsed documents.

    ``wanted`` (station, version or None for the newest) overrides the one attached at
    ingest; it must be of the acquisition's station.

    Raises
    ------
    NotFoundError
        Unknown station or calibration; none attached and none given.
    InputError
        A calibration of another station; an invalid document.
    """
    with archive.session() as s:
        if wanted is not None:
            station_name, version = wanted
            row = archive.calibration(station_name, version, s)
            if acquisition.station_id is not None and row.station_id != acquisition.station_id:
                own_row = s.get(StationRow, acquisition.station_id)
                own = own_row.name if own_row is not None else "?"
                raise InputError(
                    f"calibration {station_name}:{row.version} belongs to station "
                    f"{station_name!r} but acquisition {acquisition.uid} was recorded at "
                    f"station {own!r}"
                )
        elif acquisition.calibration_id is not None:
            own_calibration = s.get(Calibration, acquisition.calibration_id)
            assert own_calibration is not None
            row = own_calibration
        else:
            raise NotFoundError(
                f"acquisition {acquisition.uid} has no calibration: give one with "
                "--calibration STATION:VERSION (or ingest with --station after storing a "
                "calibration of that station)"
            )
        raster_definition = row.raster.definition if row.raster is not None else None
        station_name = row.station.name
    label = f"{station_name}:{row.version}"
    station = stored_calibration(row.parameters, label=label)
    raster = calibration_raster(station, raster_definition, source=f"calibration {label}")
    return row, station, raster

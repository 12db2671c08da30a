"""Which acquisitions a processing job (or a diff) covers: a :class:`Selection` and its
resolution against the catalogue."""

from __future__ import annotations

import datetime as dt
from dataclasses import asdict, dataclass
from typing import Any

from sqlalchemy import exists, select

from rasterserver.archive import Archive
from rasterserver.catalog.models import Acquisition, Frame, PipelineRun, StageResult
from rasterserver.errors import InputError

__all__ = ["Selection", "resolve_selection"]

#: Named uids looked up at a time (bounded ``IN`` lists).
_PAGE = 500


@dataclass(frozen=True)
class Selection:
    """Which acquisitions a job processes: named ones, and those matching every filter given.

    Attributes
    ----------
    uids : tuple of str
        Named acquisitions, first, in this order.
    all : bool
        Every acquisition with a raster frame (narrowed by the filters).
    unprocessed : bool
        Only those without a successful pipeline run.
    patient : str, optional
        Only this patient's.
    since, before : datetime, optional
        Only those acquired at or after ``since`` and before ``before`` (UTC).
    station : str, optional
        Only those taken at this station.
    plugin, plugin_version : str, optional
        Only those with a stored result of this plugin (of this algorithm version): the
        acquisitions a fixed plugin's old results came from.
    """

    uids: tuple[str, ...] = ()
    all: bool = False
    unprocessed: bool = False
    patient: str | None = None
    since: dt.datetime | None = None
    before: dt.datetime | None = None
    station: str | None = None
    plugin: str | None = None
    plugin_version: str | None = None

    @property
    def filtered(self) -> bool:
        """Whether anything besides named uids is selected."""
        return bool(
            self.all
            or self.unprocessed
            or self.patient
            or self.since
            or self.before
            or self.station
            or self.plugin
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready, without the unset filters."""
        out: dict[str, Any] = {}
        for key, value in asdict(self).items():
            if value in (None, False, ()):
                continue
            if isinstance(value, dt.datetime):
                value = value.isoformat()
            out[key] = list(value) if isinstance(value, tuple) else value
        return out

    def describe(self) -> str:
        """One line for ``jobs list`` and ``jobs show``."""
        parts = []
        if self.uids:
            parts.append(f"{len(self.uids)} named")
        if self.all:
            parts.append("all")
        if self.unprocessed:
            parts.append("unprocessed")
        for key in ("patient", "station"):
            if getattr(self, key):
                parts.append(f"{key} {getattr(self, key)}")
        if self.since:
            parts.append(f"since {self.since.isoformat()}")
        if self.before:
            parts.append(f"before {self.before.isoformat()}")
        if self.plugin:
            version = f" {self.plugin_version}" if self.plugin_version else ""
            parts.append(f"results of {self.plugin}{version}")
        return ", ".join(parts) or "nothing"


def resolve_selection(archive: Archive, selection: Selection) -> list[tuple[str, int | None]]:
    """The acquisitions ``selection`` names now: (uid, id or None for an unknown uid).

    Named uids come first, in their order; then the filtered ones, oldest first. Each once.

    Raises
    ------
    NotFoundError
        An unknown patient or station (an unknown uid is kept: its task fails, as with
        ``process``).
    InputError
        ``since`` not before ``before``.
    """
    if selection.since and selection.before and selection.since >= selection.before:
        raise InputError("the date range is empty: --since must be before --before")
    found: dict[str, int | None] = {}
    with archive.session() as s:
        uids = list(dict.fromkeys(selection.uids))
        known: dict[str, int] = {}
        for start in range(0, len(uids), _PAGE):
            chunk = uids[start : start + _PAGE]
            known.update(
                (uid, acquisition_id)
                for uid, acquisition_id in s.execute(
                    select(Acquisition.uid, Acquisition.id).where(Acquisition.uid.in_(chunk))
                )
            )
        for uid in uids:
            found[uid] = known.get(uid)
        if selection.filtered:
            has_raster = exists().where(
                Frame.acquisition_id == Acquisition.id, Frame.role == "raster"
            )
            query = select(Acquisition.uid, Acquisition.id).where(has_raster)
            if selection.unprocessed:
                query = query.where(
                    ~exists().where(
                        PipelineRun.acquisition_id == Acquisition.id,
                        PipelineRun.status == "done",
                    )
                )
            if selection.patient:
                query = query.where(
                    Acquisition.patient_id == archive.patient(selection.patient, s).id
                )
            if selection.station:
                query = query.where(
                    Acquisition.station_id == archive.station(selection.station, s).id
                )
            if selection.since:
                query = query.where(Acquisition.acquired_at >= selection.since)
            if selection.before:
                query = query.where(Acquisition.acquired_at < selection.before)
            if selection.plugin:
                made = exists().where(
                    StageResult.acquisition_id == Acquisition.id,
                    StageResult.plugin == selection.plugin,
                )
                if selection.plugin_version:
                    made = made.where(StageResult.plugin_version == selection.plugin_version)
                query = query.where(made)
            query = query.order_by(Acquisition.acquired_at, Acquisition.id)
            for uid, acquisition_id in s.execute(query):
                found.setdefault(uid, acquisition_id)
    return list(found.items())

"""Pseudonyms for the researcher role: keyed, stable, and interval-preserving.

A patient's pseudonym is ``PS-`` and the first 20 hex digits of HMAC-SHA256(key,
``"patient:" + identifier``): stable across requests, restarts and workers, and impossible to
invert or to recompute without the key. Every date of that patient is shifted by the same
offset, -365 ... +365 days, also derived from the key (HMAC over ``"shift:" + identifier``), so
intervals between visits survive exactly while the calendar dates do not. Names, birth dates,
operators and notes are never shown to researchers.

The key comes from ``RASTERSERVER_PSEUDONYM_KEY`` (hex) if set, else from a key file outside
the catalogue (:mod:`rasterserver.pseudonym_key`), where it is made on first use: a copy of
the catalogue does not re-identify anyone.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import hmac
import threading
from typing import TYPE_CHECKING

from sqlalchemy import select

from rasterserver import pseudonym_key
from rasterserver.catalog.models import Patient
from rasterserver.errors import NotFoundError

if TYPE_CHECKING:
    from rasterserver.archive import Archive

PREFIX = "PS-"
MAX_SHIFT_DAYS = 365


def load_key(archive: Archive) -> bytes:
    """Return the pseudonym key of ``archive``: from ``RASTERSERVER_PSEUDONYM_KEY``, else the
    key file (made on first use), never from the catalogue; see
    :mod:`rasterserver.pseudonym_key`."""
    return pseudonym_key.load_key(archive.settings)


class Pseudonymiser:
    """Maps identifiers to pseudonyms and back, and shifts dates, with one key.

    Parameters
    ----------
    archive : Archive
        Where the key and the patients are.
    key : bytes, optional
        The key; by default :func:`load_key`.
    """

    def __init__(self, archive: Archive, key: bytes | None = None) -> None:
        self.archive = archive
        self._key = key
        self._reverse: dict[str, str] = {}
        self._seen = 0  # the highest patient id in _reverse
        self._lock = threading.Lock()

    @property
    def key(self) -> bytes:
        """The key, loaded on first use."""
        if self._key is None:
            self._key = load_key(self.archive)
        return self._key

    def _mac(self, text: str) -> bytes:
        return hmac.new(self.key, text.encode(), hashlib.sha256).digest()

    def pseudonym(self, identifier: str) -> str:
        """The stable pseudonym of the patient with site ``identifier``."""
        return PREFIX + self._mac("patient:" + identifier).hex()[:20]

    def shift_days(self, identifier: str) -> int:
        """The patient's date offset in days, in [-365, 365]."""
        value = int.from_bytes(self._mac("shift:" + identifier)[:8], "big")
        return value % (2 * MAX_SHIFT_DAYS + 1) - MAX_SHIFT_DAYS

    def shift_date(self, identifier: str, day: dt.date | None) -> dt.date | None:
        """Shift a date of the patient by their offset."""
        if day is None:
            return None
        try:
            return day + dt.timedelta(days=self.shift_days(identifier))
        except OverflowError:  # a date at the calendar's end: clamp rather than fail
            return dt.date.max if self.shift_days(identifier) > 0 else dt.date.min

    def shift_time(self, identifier: str, when: dt.datetime | None) -> dt.datetime | None:
        """Shift a time of the patient by their offset (whole days: time of day kept)."""
        if when is None:
            return None
        try:
            return when + dt.timedelta(days=self.shift_days(identifier))
        except OverflowError:
            edge = dt.datetime.max if self.shift_days(identifier) > 0 else dt.datetime.min
            return edge.replace(tzinfo=when.tzinfo)

    def identifier(self, pseudonym: str) -> str:
        """The site identifier behind ``pseudonym``.

        Raises
        ------
        NotFoundError
            No patient has this pseudonym.
        """
        if not pseudonym.startswith(PREFIX):
            raise NotFoundError("unknown pseudonym")
        with self._lock:
            found = self._reverse.get(pseudonym)
            if found is None:
                self._catch_up()
                found = self._reverse.get(pseudonym)
        if found is None:
            raise NotFoundError("unknown pseudonym")
        return found

    def warm(self) -> None:
        """Fill the reverse table now (the server does it in the background at start-up,
        so that the first researcher's request does not wait for every patient's HMAC)."""
        with self._lock:
            self._catch_up()

    def _catch_up(self) -> None:
        # Patients are only ever added, so a miss needs only those registered since the
        # last look-up: one indexed query, however many patients there are, and a stream
        # of unknown pseudonyms cannot make the server rebuild its table.
        for patient_id, identifier in self._patients_after(self._seen):
            self._reverse[self.pseudonym(identifier)] = identifier
            self._seen = patient_id

    def _patients_after(self, patient_id: int) -> list[tuple[int, str]]:
        query = (select(Patient.id, Patient.identifier).where(Patient.id > patient_id)
                 .order_by(Patient.id))
        with self.archive.engine.connect() as conn:
            return [(i, ident) for i, ident in conn.execute(query)]

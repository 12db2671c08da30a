"""The rules for names: NFC, printable, no path characters, bounded; look-alikes compare equal."""

from __future__ import annotations

import pytest

from rasterserver.config import Settings
from rasterserver.errors import ConflictError, InputError
from rasterserver.identifiers import NAME_MAX, PATIENT_MAX, check_name, lookup_key


@pytest.mark.parametrize(
    ("given", "stored"),
    [
        ("P-00017", "P-00017"),
        ("MRN 4711", "MRN 4711"),
        ("e\u0301l\u00e8ve", "\u00e9l\u00e8ve"),  # decomposed é stored composed
        ("Müller#3:a?b%c", "Müller#3:a?b%c"),
        ("患者-7", "患者-7"),
        ("x" * PATIENT_MAX, "x" * PATIENT_MAX),
        ("...", "..."),
    ],
)
def test_valid_names_are_stored_nfc(given: str, stored: str) -> None:
    assert check_name(given, "a patient identifier", max_length=PATIENT_MAX) == stored


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ("", "empty"),
        ("x" * (PATIENT_MAX + 1), "at most 64"),
        ("a\x00b", "U+0000"),
        ("a\nb", "U+000A"),
        ("a\tb", "U+0009"),
        ("a\x7fb", "U+007F"),
        ("a\u200bb", "ZERO WIDTH SPACE"),
        ("a\u202eb", "RIGHT-TO-LEFT OVERRIDE"),
        ("a\u00a0b", "NO-BREAK SPACE"),
        ("a\u2028b", "LINE SEPARATOR"),
        ("a\ue000b", "U+E000"),
        ("a\U000e0001b", "LANGUAGE TAG"),
        (" P-1", "begin or end with a space"),
        ("P-1 ", "begin or end with a space"),
        ("SL/01", "'/'"),
        ("SL\\01", "'\\\\'"),
        (".", "'.' or '..'"),
        ("..", "'.' or '..'"),
        (17, "must be text"),
        (None, "must be text"),
    ],
)
def test_invalid_names_are_refused_without_repeating_them(given: object, message: str) -> None:
    with pytest.raises(InputError, match=r"^a patient identifier ") as caught:
        check_name(given, "a patient identifier", max_length=PATIENT_MAX)
    assert message in str(caught.value)
    if isinstance(given, str) and len(given) > 2:
        assert given not in str(caught.value)  # may be a patient's identifier


def test_other_names_may_be_longer() -> None:
    assert check_name("s" * NAME_MAX, "a station name") == "s" * NAME_MAX
    with pytest.raises(InputError, match="at most 100"):
        check_name("s" * (NAME_MAX + 1), "a station name")


@pytest.mark.parametrize(
    ("a", "b"),
    [
        ("P-1", "p-1"),
        ("P-1", "\uff30-1"),  # full-width P
        ("\u00e9", "e\u0301"),
        ("\u00c9", "e\u0301"),
        ("Straße", "STRASSE"),
        ("ﬁle", "FILE"),  # the ligature
    ],
)
def test_look_alikes_have_one_key(a: str, b: str) -> None:
    assert lookup_key(a) == lookup_key(b)


def test_different_names_have_different_keys() -> None:
    keys = {lookup_key(n) for n in ("P-1", "P-2", "P1", "P 1", "P_1", "e", "é")}
    assert len(keys) == 7


def test_the_archive_and_the_accounts_apply_the_rules(settings: Settings) -> None:
    from rasterserver.archive import Archive
    from rasterserver.optics import default_station
    from rasterserver.services import auth

    with Archive.create(settings) as archive:
        patient = archive.add_patient("e\u0301-P1")
        assert patient.identifier == "\u00e9-P1"
        for make in (
            lambda n: archive.add_patient(n),
            lambda n: archive.add_station(n),
            lambda n: archive.add_raster(n, default_station().raster_definition.to_dict()),
            lambda n: auth.add_account(archive, n, role="admin"),
        ):
            for bad in ("SL/01", "a\x00b", "a\nb", " x", ""):
                with pytest.raises(InputError):
                    make(bad)
        # case and look-alikes: one name, found whichever way it is typed
        with pytest.raises(ConflictError):
            archive.add_patient("\u00c9-p1")
        assert archive.patient("\u00c9-p1").identifier == "\u00e9-P1"
        archive.add_station("Clinic-1")
        with pytest.raises(ConflictError, match="Clinic-1"):
            archive.add_station("clinic-1")
        assert archive.station("CLINIC-1").name == "Clinic-1"
        auth.add_account(archive, "Alice", role="admin")
        with pytest.raises(ConflictError):
            auth.add_account(archive, "alice", role="clinician")
        assert auth.create_token(archive, "ALICE").startswith(auth.TOKEN_PREFIX)
        assert [p.name for p in auth.accounts(archive)] == ["Alice"]

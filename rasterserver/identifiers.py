"""The rules for names people type: patient identifiers, station, raster and account names.

One function, :func:`check_name`, applies them wherever such a name is created (the archive
service and the accounts, under both the CLI and the HTTP API); :func:`lookup_key` is how
names are compared.

The rules:

* **Unicode NFC.** A name is stored composed: ``"e" + U+0301`` and ``"é"`` are the same name
  (they look the same and are typed either way by different systems).
* **Printable characters only.** No control characters (NUL, newline, tab, DEL, ...), no
  invisible format characters (zero-width space, bidirectional overrides), no private-use or
  unassigned code points, and no space other than the ordinary one (a no-break space looks
  like a space but is another name). Such characters are refused, never removed.
* **No space at either end**, refused rather than trimmed: the site's systems hold the name
  as sent, and a silently changed identifier no longer matches them.
* **No ``/`` or ``\\``, and not ``.`` or ``..``.** Names are path segments of the HTTP API
  (``/patients/{patient}``): an HTTP server decodes ``%2F`` before routing, and reverse proxies
  (Apache by default, nginx with a URI in ``proxy_pass``) refuse or rewrite it; clients drop
  ``.`` and ``..`` segments; ``\\`` is turned into ``/`` by some of them. Every name the rules
  admit is reachable as one percent-encoded segment.
* **At most** :data:`PATIENT_MAX` characters for a patient identifier (the catalogue's
  column), :data:`NAME_MAX` for the other names.
* **Case is kept, but look-alikes are one name.** ``P-1`` is stored as typed; ``p-1``, or
  ``Ｐ-1`` (full-width), is then refused as a duplicate, and a look-up of ``p-1`` finds
  ``P-1``. A clinic's identifiers come from its own systems, which show them with their case,
  but two patients that differ only in case or in a look-alike character are a mix-up waiting
  to happen: the wrong patient's data. The comparison key is Unicode's NFKC case fold
  (:func:`lookup_key`).

Names stored before these rules may break them (a ``/``, a newline, two look-alike patients).
They stay readable: a look-up tries the exact name first and the comparison key only after,
so each keeps its rows (see :meth:`rasterserver.archive.Archive.patient`).
"""

from __future__ import annotations

import unicodedata

from rasterserver.errors import InputError

__all__ = ["NAME_MAX", "PATIENT_MAX", "check_name", "lookup_key"]

#: Longest patient identifier (``patient.identifier`` is ``VARCHAR(64)``).
PATIENT_MAX = 64
#: Longest station, raster or account name (``VARCHAR(100)``).
NAME_MAX = 100
#: Longest comparison key stored (``patient.identifier_key``); case folding can lengthen a
#: name (``ß`` is ``ss``), so it has room beyond :data:`PATIENT_MAX`.
KEY_MAX = 255

# Unicode general categories refused anywhere in a name: control, format, surrogate,
# private use, unassigned, line and paragraph separators. Space separators (Zs) other than
# U+0020 are refused separately.
_REFUSED_CATEGORIES = frozenset({"Cc", "Cf", "Cs", "Co", "Cn", "Zl", "Zp"})
_PATH_CHARACTERS = ("/", "\\")


def lookup_key(name: str) -> str:
    """The key under which names are compared: NFKC, case-folded, NFKC again.

    ``P-1``, ``p-1`` and ``Ｐ-1`` have the same key; so do composed and decomposed accents.

    Parameters
    ----------
    name : str
        Any text.

    Returns
    -------
    str
    """
    folded = unicodedata.normalize("NFKC", name).casefold()
    return unicodedata.normalize("NFKC", folded)


def _describe(char: str) -> str:
    name = unicodedata.name(char, "")
    return f"U+{ord(char):04X}" + (f" {name}" if name else "")


def check_name(value: object, what: str, *, max_length: int = NAME_MAX) -> str:
    """Return ``value`` in its stored form (NFC) if it is a valid name, else refuse it.

    Parameters
    ----------
    value : object
        The name as given.
    what : str
        What it names, for the message ("a patient identifier", "a station name").
    max_length : int
        Most characters allowed (after NFC).

    Returns
    -------
    str
        The name, NFC-normalised.

    Raises
    ------
    InputError
        The name breaks a rule; the message says which (and never repeats the name, which
        may be a patient's identifier).
    """
    if not isinstance(value, str):
        raise InputError(f"{what} must be text")
    name = unicodedata.normalize("NFC", value)
    if not name:
        raise InputError(f"{what} must not be empty")
    if len(name) > max_length:
        raise InputError(f"{what} must have at most {max_length} characters, not {len(name)}")
    for char in name:
        category = unicodedata.category(char)
        if category in _REFUSED_CATEGORIES or (category == "Zs" and char != " "):
            raise InputError(f"{what} must hold printable characters only, not {_describe(char)}")
        if char in _PATH_CHARACTERS:
            raise InputError(
                f"{what} must not contain {char!r}: it is a path segment of the HTTP API"
            )
    if name != name.strip():
        raise InputError(f"{what} must not begin or end with a space")
    if name in (".", ".."):
        raise InputError(f"{what} must not be '.' or '..' (URLs drop such segments)")
    if len(lookup_key(name)) > KEY_MAX:
        raise InputError(f"{what} is too long once case-folded")
    return name

"""Errors that reach a user: each carries the message and the CLI exit code it stands for.

The CLI and the HTTP API translate these, and only these, into a message and an exit code or
a 4xx status; anything else is a bug and is allowed to surface as one.
"""

from __future__ import annotations


class RasterServerError(Exception):
    """Base of every error meant for the user; ``exit_code`` is what the CLI exits with."""

    exit_code: int = 1
    http_status: int = 400


class InputError(RasterServerError):
    """The user's input is unusable (a corrupt image, wrong dimensions, bad parameters)."""

    exit_code = 2
    http_status = 422


class NotFoundError(RasterServerError):
    """A named thing (patient, acquisition, calibration, plugin) does not exist."""

    exit_code = 3
    http_status = 404


class ConflictError(RasterServerError):
    """The request contradicts what the archive holds (a duplicate identifier, say)."""

    exit_code = 4
    http_status = 409


class IntegrityError(RasterServerError):
    """The archive is inconsistent: a missing, corrupt or orphaned file."""

    exit_code = 5
    http_status = 500


class UnavailableError(RasterServerError):
    """The archive cannot be used: its catalogue database cannot be reached or opened, or
    its folder cannot be created or written (a server down, a wrong URL, a read-only disk)."""

    exit_code = 8
    http_status = 503

"""The error a processing command ends with when some acquisitions failed.

Apart from :mod:`rasterserver.commands.process` so that ``jobs``, ``diff`` and ``demo`` raise
it without importing the ``process`` command (which imports ``jobs``: no cycle).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from rasterserver.errors import RasterServerError

if TYPE_CHECKING:
    from rasterserver.jobs import JobOutcome


class ProcessingFailedError(RasterServerError):
    """Some acquisitions of a ``process`` command failed; each is listed with its reason.

    The exit code says what kind of failure it was when they are all of one kind (3 for
    unknown acquisitions or a missing calibration, 2 for frames that do not fit), else 1.
    """

    def __init__(self, message: str, *, exit_code: int) -> None:
        super().__init__(message)
        self.exit_code = exit_code

    @staticmethod
    def code_of(failed: list[JobOutcome]) -> int:
        """The failures' common exit code, or 1 when they differ."""
        codes = {o.exit_code or 1 for o in failed}
        return codes.pop() if len(codes) == 1 else 1


def raise_for_failures(failed: list[JobOutcome], total: int) -> None:
    """End a processing command with :class:`ProcessingFailedError` if any acquisition failed.

    Parameters
    ----------
    failed : list of JobOutcome
        The failed acquisitions' outcomes (each already listed to the user).
    total : int
        How many acquisitions the command processed, for the message.

    Raises
    ------
    ProcessingFailedError
        ``failed`` is not empty; its exit code is the failures' common one, else 1.
    """
    if failed:
        raise ProcessingFailedError(
            f"{len(failed)} of {total} acquisition(s) failed, see above",
            exit_code=ProcessingFailedError.code_of(failed),
        )

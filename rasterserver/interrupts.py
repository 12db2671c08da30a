"""Ctrl-C that cannot be lost: a command interrupted by SIGINT always ends with exit 130.

Python turns SIGINT into a ``KeyboardInterrupt`` raised wherever the main thread happens to
be. Raised inside a finaliser (a ``__del__``, a weak-reference callback such as those of
``concurrent.futures``), it is printed as "Exception ignored" and swallowed, and the command
goes on to finish with exit 0 as if no one had pressed Ctrl-C. The handler here remembers
the interrupt as well as raising it: the command's next progress step raises it again
(:func:`raise_if_interrupted`), and :func:`rasterserver.cli.main` reports 130 even when the
work ran to its end.
"""

from __future__ import annotations

import signal
from types import FrameType

__all__ = ["install", "interrupted", "raise_if_interrupted"]

_seen = False


def _on_sigint(signum: int, frame: FrameType | None) -> None:
    global _seen
    _seen = True
    raise KeyboardInterrupt


def install() -> None:
    """Handle SIGINT here, unless something other than Python's default handles it.

    A process started with SIGINT ignored (``nohup``, a background job of some shells) keeps
    ignoring it; a server that installs its own handler (uvicorn) replaces this one.
    """
    if signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _on_sigint)


def interrupted() -> bool:
    """Whether SIGINT reached this process since :func:`install`."""
    return _seen


def raise_if_interrupted() -> None:
    """Raise ``KeyboardInterrupt`` if SIGINT came, even if its first raise was swallowed.

    Raises
    ------
    KeyboardInterrupt
        When :func:`interrupted` is true.
    """
    if _seen:
        raise KeyboardInterrupt

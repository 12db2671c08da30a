"""numba's ``njit`` as the chain's compiled loops use it.

Machine code is cached on disk where numba can write (beside the module, else in the user's
cache folder), so a process loads a kernel in milliseconds instead of compiling it for a
second or two. Where neither is writable (a read-only package and home, as a hardened
container may have), ``njit(cache=True)`` refuses at import; the kernel is then compiled in
each process instead of failing.

numba is imported when a kernel module is (importing numba costs ~0.3 s): the modules that
hold kernels are imported by the functions that call them, never at start-up.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal, TypeVar, cast

F = TypeVar("F", bound=Callable[..., Any])

__all__ = ["kernel"]


def kernel(*, error_model: Literal["python", "numpy"] = "python") -> Callable[[F], F]:
    """Decorator: compile a function with numba (no Python objects, GIL released, cached).

    Parameters
    ----------
    error_model : {"python", "numpy"}
        ``"numpy"``: a float division by zero gives inf or NaN as in numpy instead of raising.

    Returns
    -------
    Callable
        The decorator.
    """
    from numba import njit

    def wrap(function: F) -> F:
        # a numba Dispatcher calls like the function it compiles: typed as that function
        try:
            return cast(F, njit(cache=True, nogil=True, error_model=error_model)(function))
        except RuntimeError:  # "cannot cache function ...: no locator available"
            return cast(F, njit(cache=False, nogil=True, error_model=error_model)(function))

    return wrap

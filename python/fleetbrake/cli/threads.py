"""BLAS threads of the commands that run many tiny matrix products (the reduced model's
matrices are about 40 x 40): extra threads would only wait for each other there, so these
commands run BLAS on one thread, for the duration of the work (``threadpoolctl``; the
process's environment is left alone)."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

__all__ = ["blas_single_thread"]


@contextlib.contextmanager
def blas_single_thread() -> Iterator[None]:
    """Limit the BLAS libraries of numpy and scipy to one thread inside the block (both
    are loaded first: threadpoolctl limits the libraries loaded when it is called)."""
    import numpy  # noqa: F401
    import scipy.linalg  # noqa: F401
    from threadpoolctl import (  # type: ignore[import-untyped]  # ships no type information
        threadpool_limits,
    )

    with threadpool_limits(limits=1, user_api="blas"):
        yield

"""The C allocator's handling of large blocks while the diagnosis runs.

The diagnosis allocates and frees many tensors of tens to hundreds of megabytes (images of the
held-out and training views, placebo bases [P, N, 3] in float64, residual tables). glibc's
malloc serves every block above its mmap threshold (at most 32 MiB) with a fresh mmap and gives
it back on free, so each such tensor pays for page faults on first touch: on the shared real
capture (384 px) that was a fifth of the diagnosis' CPU time, spent in the kernel. Serving them
from the heap and keeping freed memory (no mmap, no trimming) makes a freed block reusable by
the next tensor of that size. It changes no result (the same arithmetic on the same numbers);
the process keeps its peak memory until the diagnosis ends.

On a C library without glibc's mallopt (macOS, musl) nothing changes.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from collections.abc import Iterator
from contextlib import contextmanager

# glibc's mallopt parameters (malloc.h) and the defaults restored afterwards.
M_TRIM_THRESHOLD = -1
M_MMAP_MAX = -4
DEFAULT_TRIM_THRESHOLD = 128 * 1024
DEFAULT_MMAP_MAX = 65536
# The largest trim threshold mallopt takes (an int): up to 2 GiB of free memory at the top of
# the heap stays with the process.
NEVER_TRIM = 2**31 - 1


def _glibc():
    """The C library if it has glibc's mallopt and malloc_trim, else None."""
    try:
        library = ctypes.CDLL(ctypes.util.find_library("c") or None)
    except OSError:
        return None
    if not hasattr(library, "mallopt") or not hasattr(library, "malloc_trim"):
        return None
    library.mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    library.mallopt.restype = ctypes.c_int
    library.malloc_trim.argtypes = [ctypes.c_size_t]
    library.malloc_trim.restype = ctypes.c_int
    return library


@contextmanager
def reuse_freed_memory() -> Iterator[bool]:
    """Within the block, large allocations come from the heap and freed memory stays with the
    process (see the module docstring); afterwards glibc's defaults are set again and the
    freed memory is given back. Yields whether the setting took effect."""
    library = _glibc()
    applied = bool(
        library is not None
        and library.mallopt(M_MMAP_MAX, 0)
        and library.mallopt(M_TRIM_THRESHOLD, NEVER_TRIM)
    )
    try:
        yield applied
    finally:
        if library is not None:
            library.mallopt(M_MMAP_MAX, DEFAULT_MMAP_MAX)
            library.mallopt(M_TRIM_THRESHOLD, DEFAULT_TRIM_THRESHOLD)
            library.malloc_trim(0)

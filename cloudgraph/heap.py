"""The heap of a process that precomputes: glibc's malloc told to keep what it frees.

A precompute makes and drops arrays of tens to hundreds of MB, chunk after chunk (the field's
light march, its fit, the multiple-scattering gather). glibc maps every block over 32 MB afresh
and unmaps it when freed, so each new array pays its page faults again on first touch (the
system zeroing every page, 4 KB or 2 MB a fault); on a virtual machine, where a fault costs
more, that was most of the field's bake on smoke1. With large blocks taken from the heap and
freed memory kept (M_MMAP_MAX 0, a trim threshold of 1 GiB) the next array reuses pages already
mapped: smoke1's warm precompute on a 2-core VM 11.4-12.5 s -> 7.6-8.1 s, its peak resident
memory 1.41 -> 1.51 GB (docs/measurements.md, "The heap"). A worker gives the memory back after
each job (:func:`release_freed_memory`). Elsewhere than glibc both do nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from functools import cache

#: mallopt's parameters (glibc's malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_MAX = -4
#: Freed memory above this at the heap's top is given back to the system
TRIM_THRESHOLD = 1 << 30


@cache
def _glibc():
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        libc.gnu_get_libc_version  # noqa: B018  (glibc only)
    except (OSError, AttributeError):
        return None
    return libc


def keep_freed_memory() -> bool:
    """Large blocks from the heap, freed memory kept for the next (this process, from now on).
    True where it took effect (glibc)."""
    libc = _glibc()
    if libc is None:
        return False
    return bool(libc.mallopt(_M_MMAP_MAX, 0)) and bool(libc.mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))


def release_freed_memory() -> None:
    """Gives the freed memory back to the system (after a job: the next may be small)."""
    libc = _glibc()
    if libc is not None:
        libc.malloc_trim(0)

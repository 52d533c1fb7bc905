"""glibc's allocator set for large numerical work, once per process.

By default glibc maps every allocation above a threshold (128 KB, rising with what was freed)
afresh and unmaps it when freed, so a job that makes arrays of tens of megabytes again and again
(the adjustment's iterations at a million points, a georeferencing chunk) has the kernel fault in
and zero fresh pages every time: kernel (sys) time and page faults. :func:`tune_allocator` raises
the mmap threshold to glibc's largest (32 MB) and keeps up to 512 MB of freed heap for the next
use: the same bytes computed, the kernel's share cut. Elsewhere than glibc nothing is changed.
"""

from __future__ import annotations

import functools

#: glibc's mallopt parameters, and what :func:`tune_allocator` sets them to
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
MMAP_THRESHOLD_BYTES = 32 << 20  # glibc's largest: arrays up to 32 MB come from the heap
TRIM_THRESHOLD_BYTES = 512 << 20  # freed heap kept for the next use, up to 512 MB


@functools.cache
def tune_allocator() -> bool:
    """Once per process (module docstring); False where the C library is not glibc."""
    import ctypes

    try:
        libc = ctypes.CDLL("libc.so.6")
        ok = bool(libc.mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))
        return bool(libc.mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD_BYTES)) and ok
    except (OSError, AttributeError):
        return False

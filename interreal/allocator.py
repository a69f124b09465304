"""glibc's allocator told to keep freed blocks for reuse, for the commands that churn through image-sized arrays.

Every frame of `interreal masks` makes and frees dozens of 0.1-10 MB temporaries (soft maps, flows, warps). glibc
serves blocks that size with a fresh mmap each time, so each one costs page faults over all its pages and an
munmap: on DAVIS at 854x480, 450 k page faults and a sixth of the command's CPU time in the kernel. A fixed mmap
threshold keeps them on the heap, where a freed block is reused: 57 k faults, the system time 1.8 -> 0.7 s and
the whole command 4 % faster (recipes/bench_masks.py sequences, interleaved runs). The price is a little memory
held between reuses: peak RSS 247 -> 280 MB on that 80-frame run.
"""

from __future__ import annotations

import ctypes
import os

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
MMAP_THRESHOLD = 64 << 20  # blocks under this come from the heap
TRIM_THRESHOLD = 256 << 20  # free memory at the heap's top kept before it is given back to the system


def keep_freed_blocks() -> bool:
    """Set the thresholds on this process; True where they took (glibc), False elsewhere or where the user set
    glibc's own MALLOC_MMAP_THRESHOLD_ / MALLOC_TRIM_THRESHOLD_ (theirs wins)."""
    if "MALLOC_MMAP_THRESHOLD_" in os.environ or "MALLOC_TRIM_THRESHOLD_" in os.environ:
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc (macOS, musl without it): nothing to tune
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))

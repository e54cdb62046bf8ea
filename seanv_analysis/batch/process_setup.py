"""Process-wide settings of the command-line tool (not applied on import).

:func:`return_large_blocks_to_os` is called by the CLI entry point and by
the batch worker processes; a notebook user may call it too.
:func:`die_with_parent` is called by each local batch worker.
"""
from __future__ import annotations

import ctypes
import os
import signal
import sys

__all__ = ["return_large_blocks_to_os", "die_with_parent"]

_M_TRIM_THRESHOLD = -1   # glibc <malloc.h>
_M_TOP_PAD = -2
_M_MMAP_THRESHOLD = -3
#: free memory at the top of a heap glibc keeps for the next allocations
#: (:func:`return_large_blocks_to_os`) [bytes]
KEEP_FREE_BYTES = 64 << 20
#: what the heap grows by beyond a request when it must grow
#: (:func:`return_large_blocks_to_os`) [bytes]
GROW_BY_BYTES = 16 << 20
_PR_SET_PDEATHSIG = 1    # <linux/prctl.h>
_DONE = False


def return_large_blocks_to_os(threshold_bytes: int = 4 << 20) -> bool:
    """Make glibc's malloc serve every block of at least ``threshold_bytes``
    (default 4 MiB) with its own mapping, returned to the OS when freed.

    By default glibc raises this threshold after the first large block is
    freed (up to 32 MiB), so later log-length arrays (29 MB per column for
    an hour at 1 kHz) come from the heap and freed temporaries stay
    resident, more so with several threads (one heap each). Measured on a
    60-minute 1 kHz run, ingest + derive: peak RSS 666-701 MB with the
    default, 623-632 MB with a fixed 4 MiB threshold, at the same speed
    (numpy asks for huge pages on such blocks, so mapping them is cheap).


    A fixed threshold also turns off glibc's matching rise of the trim
    threshold (2 x the mmap threshold), which stayed at 128 KiB: the heap
    was given back to the OS after every free at its top and taken again
    by the next allocation, every page of it a fault. A closed-loop replay
    of a 60 s position-control run (identify's and discover's searches
    replay hundreds) made and freed its columns, overlays and derived
    signals so: 3500-4000 minor page faults each (3.1 M in a first ``run
    paper``). The heap now keeps up to :data:`KEEP_FREE_BYTES` free at its
    top for the next replay: 5 faults each, the same numbers; blocks of
    ``threshold_bytes`` or more are still mapped and given back, unless the
    free top of the heap holds them: it grows by :data:`GROW_BY_BYTES` more
    than it must, so a replay's kernel output (5.3 MB for 95 s, mapped and
    faulted in afresh each time, 1300 faults, when the replay's own
    temporaries were too small to leave such a top) comes from it.

    Returns True when the setting was applied (glibc only; elsewhere it is
    a no-op returning False). Calling it again does nothing.
    """
    global _DONE
    if _DONE:
        return True
    if not sys.platform.startswith("linux"):
        return False
    try:
        # the running process's own symbols (libc among them): no
        # ctypes.util.find_library, which runs ldconfig (~15 ms a start)
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False  # not glibc (e.g. musl has no mallopt)
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    _DONE = bool(mallopt(_M_MMAP_THRESHOLD, int(threshold_bytes)))
    if _DONE:
        mallopt(_M_TRIM_THRESHOLD, int(max(KEEP_FREE_BYTES, 2 * threshold_bytes)))
        mallopt(_M_TOP_PAD, int(GROW_BY_BYTES))
    return _DONE


def die_with_parent(parent_pid: int, sig: int = signal.SIGKILL) -> bool:
    """Ask the Linux kernel to send ``sig`` to this process when its parent
    dies (``prctl(PR_SET_PDEATHSIG)``), whatever this process is doing (a
    watchdog thread needs the GIL; a C call holding it delays the thread,
    not the kernel). Exits at once when ``parent_pid`` is already gone.

    The kernel sends the signal when the *thread* that forked this process
    ends, so call it only in a process forked by a thread that outlives it
    (the batch pool is started by the thread that uses it: the main thread).

    Returns True when the setting was applied (Linux only; elsewhere a
    no-op returning False).
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)  # the process's own symbols: libc
        prctl = libc.prctl
    except (OSError, AttributeError):
        return False
    prctl.argtypes = [ctypes.c_int, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_ulong,
                      ctypes.c_ulong]
    prctl.restype = ctypes.c_int
    ok = prctl(_PR_SET_PDEATHSIG, int(sig), 0, 0, 0) == 0
    if os.getppid() != parent_pid:   # the parent died before the call: no signal comes
        os._exit(1)
    return ok

"""Worker processes that end with the process that started them.

A worker of a process pool blocks reading its next task, or writing a result, from a pipe
that it shares with its parent. When the parent is killed (``kill -9``, the out-of-memory
killer) nothing closes that pipe, so the worker waits for ever, holding its memory. Each
pool of geofeat calls `end_with_parent` when a worker starts.
"""

from __future__ import annotations

import ctypes
import logging
import os
import signal
import sys

log = logging.getLogger(__name__)

#: ``prctl`` option: the signal the calling process receives when its parent ends (Linux).
PR_SET_PDEATHSIG = 1


def end_with_parent(parent_pid: int) -> None:
    """In a worker process: be killed (``SIGKILL``) when the parent process ends.

    Parameters
    ----------
    parent_pid : int
        ``os.getpid()`` of the parent, read there before it starts the worker. A worker whose
        parent already ended before this call exits at once.

    Notes
    -----
    On Linux this is ``prctl(PR_SET_PDEATHSIG, SIGKILL)``. The kernel sends the signal when
    the *thread* that started the worker ends, so a pool must be started and closed by the
    same thread (every pool of geofeat is). Elsewhere nothing is set, and a pool's own
    checks apply (PyTorch's data-loader workers poll their parent every few seconds).
    """
    if sys.platform.startswith("linux"):
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:  # pragma: no cover - never fails on Linux
            log.debug("prctl(PR_SET_PDEATHSIG) failed: %s", os.strerror(ctypes.get_errno()))
    if os.getppid() != parent_pid:
        os._exit(1)

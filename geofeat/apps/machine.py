"""The one-line machine description every benchmark result records.

Imports no other geofeat module and no torch: ``benchmarks/speed/dsmk_ulrssm.py``, which
runs in another project's environment, loads this file by its path, so that it describes the
machine the same way as the others.
"""

from __future__ import annotations

import os
import platform
from pathlib import Path

import numpy as np
import scipy


def machine(*extra: str) -> str:
    """CPU model, core count, OS and the numerical library versions, in one line.

    Parameters
    ----------
    extra : str
        Further items (for example ``"torch 2.13.0"``), appended after the library versions.
    """
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    items = [
        cpu,
        f"{os.cpu_count()} cores",
        f"{platform.system()} {platform.machine()}",
        f"Python {platform.python_version()}",
        f"numpy {np.__version__}",
        f"scipy {scipy.__version__}",
        *extra,
    ]
    return ", ".join(items)

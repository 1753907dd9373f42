#!/usr/bin/env python
"""pyshot's SHOT on arrays from an .npz, for `benchmarks.parity.shot` and `benchmarks.speed.shot`.

Runs in pyshot's own environment, not geofeat's. pyshot (``uhlmanngroup/pyshot``, a Cython
wrapper of the original C++ code; built here from commit 18ff0f25768cf93c62dba847fa002944518a0f2f)
builds from source on Debian with ``libeigen3-dev``, ``libflann-dev`` and ``liblz4-dev``:

    python -m venv pyshot-venv && pyshot-venv/bin/pip install numpy cython setuptools
    git clone https://github.com/uhlmanngroup/pyshot && cd pyshot
    # setup.py names src/shot_descriptor.cpp as "./src/shot_descriptor.cpp" while pyshot.pyx's
    # "distutils: sources" names it "src/shot_descriptor.cpp": the file is compiled twice and the
    # link fails; spell it "src/shot_descriptor.cpp" in setup.py too.
    ../pyshot-venv/bin/pip install --no-build-isolation .

    pyshot-venv/bin/python pyshot_harness.py IN.npz OUT.npz '{"radius": 0.3, ...}'

IN.npz holds ``verts`` (V, 3) and optionally ``faces`` (F, 3); without faces (or with none)
the shape is a point cloud, to which pyshot gives zero normals. The JSON parameters are
``get_descriptors``'s (defaults: DeepShapeMatchingKit's call, radius 0.3, min_neighbors 3,
n_bins 5, 32 volumes, interpolation and normalisation on; ``local_rf_radius``, which pyshot
does not use, follows ``radius``) and ``repeats``, the number of timed calls. OUT.npz holds
``descriptors`` (V, L) float64, ``wall_time`` (the fastest call, seconds), ``wall_times``,
``deterministic`` (every call gave the same array) and ``n_warnings`` (the warning lines the
C++ code printed on the standard output, which the harness captures).
"""

import ctypes
import json
import os
import sys
import tempfile
import time

import numpy as np
import pyshot

DEFAULTS = {
    "radius": 0.3,
    "min_neighbors": 3,
    "n_bins": 5,
    "double_volumes_sectors": True,
    "use_interpolation": True,
    "use_normalization": True,
    "repeats": 1,
}


def quiet_call(function):
    """``function()`` with file descriptor 1 redirected; returns its result and the text it printed there."""
    libc = ctypes.CDLL(None)
    sys.stdout.flush()
    libc.fflush(None)
    saved = os.dup(1)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 1)
        try:
            result = function()
        finally:
            libc.fflush(None)
            os.dup2(saved, 1)
            os.close(saved)
        sink.seek(0)
        return result, sink.read().decode(errors="replace")


def describe(verts, faces, params):
    """pyshot's descriptors of one shape, timed; see the module docstring for the outputs."""
    unknown = set(params) - set(DEFAULTS)
    if unknown:
        raise SystemExit(f"unknown parameter(s): {sorted(unknown)}")
    p = {**DEFAULTS, **params}
    verts = np.ascontiguousarray(verts, dtype=np.float64)
    faces = np.zeros((0, 3), dtype=np.int64) if faces is None else np.ascontiguousarray(faces, dtype=np.int64).reshape(-1, 3)
    if faces.size and (faces.min() < 0 or faces.max() >= len(verts)):
        raise SystemExit("faces index missing vertices")  # the C++ code would read out of bounds
    args = (verts, faces, float(p["radius"]), float(p["radius"]), int(p["min_neighbors"]), int(p["n_bins"]),
            bool(p["double_volumes_sectors"]), bool(p["use_interpolation"]), bool(p["use_normalization"]))  # fmt: skip
    times, outputs, printed = [], [], ""
    for _ in range(max(1, int(p["repeats"]))):
        start = time.perf_counter()
        descriptors, printed = quiet_call(lambda: pyshot.get_descriptors(*args))
        times.append(time.perf_counter() - start)
        outputs.append(descriptors)
    return {
        "descriptors": outputs[0],
        "wall_time": np.float64(min(times)),
        "wall_times": np.array(times),
        "deterministic": np.bool_(all(np.array_equal(outputs[0], o, equal_nan=True) for o in outputs[1:])),
        "n_warnings": np.int64(sum("[WARNING]" in line for line in printed.splitlines())),
    }


def main(argv):
    if len(argv) not in (3, 4):
        raise SystemExit(__doc__)
    params = json.loads(argv[3]) if len(argv) == 4 else {}
    with np.load(argv[1]) as data:
        faces = data["faces"] if "faces" in data.files else None
        result = describe(data["verts"], faces, params)
    np.savez(argv[2], **result)


if __name__ == "__main__":
    main(sys.argv)

"""Benchmark command lines over geofeat, run from the repository root (``python -m benchmarks.speed.spectral``).

``run.py`` (the main job and single benchmark runs, ``python benchmarks/run.py``), the
scripts shared helpers (`benchmarks.common`), timings (`benchmarks.speed`), stage-by-stage
comparisons with the authors' code (`benchmarks.parity`) and the tables of the docs
(`benchmarks.tables`). Their output lands in ``benchmarks/results/``. This file and those of
the sub-packages import nothing, so that a script run in another project's environment
(`benchmarks.speed.dsmk_ulrssm`) can be started as a module too.
"""

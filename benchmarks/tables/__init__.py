"""The tables and figures of the docs, made from result files and runs (``python -m benchmarks.tables.NAME``)."""

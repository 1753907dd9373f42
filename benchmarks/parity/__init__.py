"""Stage-by-stage comparisons with the authors' code, imported from the user's clones (``python -m benchmarks.parity``)."""

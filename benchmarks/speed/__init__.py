"""Timings: descriptors, geodesics, the multi-view DINO path, GeoLoRA training, the heads, extraction (``python -m benchmarks.speed.NAME``)."""

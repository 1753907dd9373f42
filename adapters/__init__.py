"""Matching heads (DiffusionNet, functional maps, ULRSSM, DPFM, EchoMatch), installed as ``geofeat.adapters``.

This folder is the heads layer of the design: it takes any geofeat descriptor as input.
It is installed under the name ``geofeat.adapters``, never as a top-level ``adapters``
module (an unrelated PyPI package has that name).
"""

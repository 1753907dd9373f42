"""GeoLoRA training: contrastive losses (and, beside them, the trainer and its CLI)."""

from geofeat.train.losses import (
    DEFAULT_OFFSET,
    DEFAULT_TEMPERATURE,
    geodesic_point_info_nce,
    observed_rows,
    point_info_nce,
)

__all__ = [
    "DEFAULT_OFFSET",
    "DEFAULT_TEMPERATURE",
    "geodesic_point_info_nce",
    "observed_rows",
    "point_info_nce",
]

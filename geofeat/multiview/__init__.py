"""The one multi-view feature path: render a mesh from several cameras, run the backbone, and
bring the patch features back to the vertices.

>>> from geofeat.multiview import multiview_features
>>> features = multiview_features(mesh, backbone, cameras)   # doctest: +SKIP

`pipeline` holds `multiview_features` (the path the DINO and GeoLoRA descriptors and the
GeoLoRA trainer share); `backproject` holds the back-projection of pixel features to vertices.
"""

from geofeat.multiview.pipeline import MultiviewFeatures, multiview_features

__all__ = ["MultiviewFeatures", "multiview_features"]

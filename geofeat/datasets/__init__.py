"""Benchmark datasets: loaders for every format, converted at the boundary to `ShapePair` records."""

from geofeat.datasets.base import PairDataset
from geofeat.datasets.becos import BeCoS
from geofeat.datasets.cp2p24 import CP2P24
from geofeat.datasets.depth_camera import DepthCamera, Scan, scan_mesh
from geofeat.datasets.derived import DerivedPartialBenchmark, TemplateCollection
from geofeat.datasets.faust import FaustRemeshed, ScapeRemeshed
from geofeat.datasets.pfaust import PFaust
from geofeat.datasets.psmal import PartialSmal
from geofeat.datasets.records import Match, ShapePair
from geofeat.datasets.registry import dataset_description, dataset_names, load_dataset, register_dataset
from geofeat.datasets.scans import ScanBenchmark
from geofeat.datasets.shrec16 import Shrec16Partial
from geofeat.datasets.synthetic import SyntheticHumans

__all__ = [
    "CP2P24",
    "BeCoS",
    "DepthCamera",
    "DerivedPartialBenchmark",
    "FaustRemeshed",
    "Match",
    "PFaust",
    "PairDataset",
    "PartialSmal",
    "Scan",
    "ScanBenchmark",
    "ScapeRemeshed",
    "ShapePair",
    "Shrec16Partial",
    "SyntheticHumans",
    "TemplateCollection",
    "dataset_description",
    "dataset_names",
    "load_dataset",
    "register_dataset",
    "scan_mesh",
]

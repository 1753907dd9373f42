"""DPFM (Attaiki, Pai and Ovsjanikov 2021): its settings (`config`), farthest-point samples and their
interpolation (`sampling`), the network (`networks`), the losses (`losses`) and the head (`head`).
"""

from geofeat.adapters.dpfm.config import DPFMConfig
from geofeat.adapters.dpfm.head import DPFMHead

__all__ = ["DPFMConfig", "DPFMHead"]

"""EchoMatch (Xie et al., CVPR 2025): its settings (`config`), the correspondence reflection
(`reflection`), the losses (`losses`), the network (`networks`) and the head (`head`).
"""

from geofeat.adapters.echomatch.config import EchoMatchConfig
from geofeat.adapters.echomatch.head import EchoMatchHead

__all__ = ["EchoMatchConfig", "EchoMatchHead"]

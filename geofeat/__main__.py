"""``python -m geofeat ...``: the ``geofeat`` command, also as ``torchrun -m geofeat extract ...``."""

import sys

from geofeat.apps.cli import main

if __name__ == "__main__":
    sys.exit(main())

"""The main job and single benchmark runs: ``python benchmarks/run.py --help``.

The command is `geofeat.apps.benchmark` (the main job: `geofeat.apps.main_job`); this
file gives it the repository's ``runs/`` folder, where runs write without ``--out``.
"""

import sys
from pathlib import Path

from geofeat.apps.benchmark import main

#: Where runs write without --out (ignored by git).
RUNS = Path(__file__).resolve().parents[1] / "runs"

if __name__ == "__main__":
    sys.exit(main(runs=RUNS))

"""CPU time to prepare one GeoLoRA training sample, geofeat's generators beside the reference ones.

A sample is one full shape turned about the up axis with its two partial shapes (see
`geofeat.train.samples`). Both generator sets prepare the same sample indices of the same
FAUST_r training shapes in this process, one after the other; the geodesic matrices are
computed and stored before the clock starts, so the time is the partial-shape work alone
(what a sample worker does besides reading the stored matrix). The GPU step must not wait:
``workers`` processes keep up with ``steps_per_second`` when ``workers / seconds_per_sample``
is at least that, which the table states for the H100 figure of 5 steps/s.

    python -m benchmarks.speed.samples --samples 40

Writes ``benchmarks/results/speed_samples.json`` and ``.md``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import DEFAULT_DATA, RESULTS, data_folder, machine
from geofeat.train.config import TrainConfig
from geofeat.train.geodesics import TorchGeodesicStore
from geofeat.train.samples import prepare_sample
from geofeat.train.shapes import load_training_shapes

GENERATORS = ("geofeat", "reference")
#: GeoLoRA steps per second on an H100 that sample preparation must keep up with.
GPU_STEPS_PER_SECOND = 5.0


def time_samples(config: TrainConfig, shapes, store: TorchGeodesicStore, indices: range) -> list[float]:
    """Seconds of `prepare_sample` for each index (the geodesic matrices already stored)."""
    seconds = []
    for index in indices:
        start = time.perf_counter()
        prepare_sample(config, shapes, index, store)
        seconds.append(time.perf_counter() - start)
    return seconds


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--samples", type=int, default=40, help="samples timed per generator set")
    parser.add_argument("--shapes", type=int, default=10, help="FAUST_r training shapes used (the first N)")
    parser.add_argument("--data-root", default=DEFAULT_DATA, help="the folder holding FAUST_r/ (default $GEOFEAT_DATA)")
    parser.add_argument("--out", type=Path, default=RESULTS / "speed_samples")
    args = parser.parse_args(argv)
    data_root = str(data_folder(args.data_root, "--data-root"))

    with tempfile.TemporaryDirectory() as tmp:
        base = dict(data="faust_r", data_root=data_root, first=args.shapes, out=tmp, progress=False)
        shapes = load_training_shapes("faust_r", root=data_root, first=args.shapes, progress=False)
        store = TorchGeodesicStore(Path(tmp) / "geodesics")
        for mesh in shapes:
            store.ensure(mesh)
        rows = []
        for generators in GENERATORS:
            config = TrainConfig(**base, partial_generators=generators)
            seconds = time_samples(config, shapes, store, range(args.samples))
            median = float(np.median(seconds))
            rows.append(
                {
                    "generators": generators,
                    "samples": len(seconds),
                    "median_s": median,
                    "mean_s": float(np.mean(seconds)),
                    "p90_s": float(np.percentile(seconds, 90)),
                    "workers_for_gpu": math.ceil(GPU_STEPS_PER_SECOND * median),
                }
            )
    ratio = rows[1]["median_s"] / rows[0]["median_s"]
    lines = [
        f"{machine()}, {datetime.date.today().isoformat()}. Sample preparation (full shape turned, two partial "
        f"shapes) on the first {args.shapes} FAUST_r training shapes (5,000 vertices), one process, geodesic "
        "matrices already stored. Workers for the GPU: sample workers of this speed that keep up with "
        f"{GPU_STEPS_PER_SECOND:g} steps/s (one shape per step).",
        "",
        "| generators | samples | median s / sample | mean | 90th percentile | workers for 5 steps/s |",
        "|---|---|---|---|---|---|",
        *(
            f"| {r['generators']} | {r['samples']} | {r['median_s']:.3f} | {r['mean_s']:.3f} | {r['p90_s']:.3f} | "
            f"{r['workers_for_gpu']} |"
            for r in rows
        ),
        "",
        f"The reference generators take {ratio:.2f} times the time of geofeat's (medians, same run).",
    ]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.with_suffix(".json").write_text(json.dumps({"machine": machine(), "rows": rows, "ratio": ratio}, indent=1) + "\n")
    args.out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""Transfer of DPFM's SHREC'16 release checkpoints to geofeat's partial FAUST_r benchmarks.

Loads ``shrec_cuts.pth`` / ``shrec_holes.pth`` (``pvnieo/DPFM``, ``dpfm/data/saved_models``;
not part of geofeat) into our DPFM head with the matching preset
(``reference_shrec16_cuts`` / ``reference_shrec16_holes``: n_fmap 50 / 30, sampling ratio
0.4 / 0.3, functional map from the DiffusionNet / refined features) and evaluates it on
``faust_r_cuts`` / ``faust_r_holes`` (test split) with the metrics of ``benchmarks/run.py``.

The reference trained on SHREC'16 shapes as stored: every full shape at unit area, each
partial shape in the frame and at the scale of its full shape. The presets do the same to a
pair (``mesh_normalization="unit_area"``, `geofeat.adapters.inputs.normalized_pair`) and feed
the coordinates as they are (``descriptor_params={"normalize": False}``).

Each checkpoint is run with the presets' interpolation of the refined features
(``"reference"``, the reference code's) and with ``"nearest"`` (the nearest samples, which
these weights work better with; see `geofeat.adapters.dpfm`).

    python -m benchmarks.transfer_dpfm_partial --models PATH/TO/DPFM/dpfm/data/saved_models --limit 50
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
import time
from pathlib import Path

from tqdm.auto import tqdm

from benchmarks.common import DEFAULT_DATA, data_folder, machine
from geofeat.adapters.dpfm import DPFMHead
from geofeat.adapters.heads import load_head
from geofeat.datasets import load_dataset
from geofeat.evaluation.protocol import evaluate_pair, summarize

#: dataset -> (checkpoint file, preset)
RUNS = {
    "faust_r_cuts": ("shrec_cuts.pth", "reference_shrec16_cuts"),
    "faust_r_holes": ("shrec_holes.pth", "reference_shrec16_holes"),
}
INTERPOLATIONS = ("reference", "nearest")


def transfer(
    models: Path, data_root: Path, dataset_name: str, interpolation: str = "reference", limit: int = 50, progress: bool = True
) -> dict:
    """Summary (as ``benchmarks/run.py``) of one checkpoint on the first ``limit`` test pairs.

    ``interpolation``: the head's setting (``"reference"``: the reference code's, as the
    presets; ``"nearest"``: the nearest samples).
    """
    checkpoint, preset = RUNS[dataset_name]
    dataset = load_dataset(dataset_name, root=data_root, split="test")
    reference = DPFMHead.PRESETS["reference"]
    settings = {k: v for k, v in DPFMHead.PRESETS[preset].items() if reference.get(k) != v}
    head = load_head(
        "dpfm", checkpoint=models / checkpoint, progress=False, augmentation=False, interpolation=interpolation, **settings
    )
    n_pairs = min(limit, len(dataset))
    start = time.perf_counter()
    records = []
    for i in tqdm(range(n_pairs), desc=f"dpfm {checkpoint} on {dataset_name} ({interpolation})", disable=not progress):
        pair = dataset[i]
        records.append(evaluate_pair(pair, head.match(pair)))
    summary = summarize(records)
    return {
        "dataset": dataset_name,
        "checkpoint": checkpoint,
        "interpolation": interpolation,
        "seconds": time.perf_counter() - start,
        "date": datetime.date.today().isoformat(),
        "machine": machine(),
        "head": head.config.to_dict(),
        **{k: v for k, v in summary.to_dict().items() if k not in ("pck", "pck_thresholds")},
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--models", required=True, help="folder with shrec_cuts.pth and shrec_holes.pth")
    parser.add_argument("--data-root", default=DEFAULT_DATA, help="the folder holding the datasets (default $GEOFEAT_DATA)")
    parser.add_argument("--dataset", choices=sorted(RUNS), action="append")
    parser.add_argument("--interpolation", choices=INTERPOLATIONS, action="append")
    parser.add_argument("--limit", type=int, default=50)
    parser.add_argument("--out", default=None, help="write the results as JSON here")
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    data_root = data_folder(args.data_root, "--data-root")
    results = []
    for name in args.dataset or sorted(RUNS):
        for interpolation in args.interpolation or INTERPOLATIONS:
            r = transfer(Path(args.models), data_root, name, interpolation, args.limit, not args.no_progress)
            results.append(r)
            print(
                f"{r['checkpoint']} on {name} (interpolation {interpolation}, {r['n_pairs']} pairs): geodesic error x100 "
                f"{r['geodesic_error']:.2f}, PCK AUC {r['pck_auc']:.3f}, mIoU {r.get('miou', float('nan')):.3f}, "
                f"overlap AUC {r.get('overlap_auc', float('nan')):.3f}, chirality {r.get('chirality_accuracy', float('nan')):.3f}, "
                f"{r['seconds']:.0f} s",
                flush=True,
            )
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Stage-by-stage parity of geofeat's heads with the authors' code, imported from your clones.

    python -m benchmarks.parity --ulrssm-repo PATH --dpfm-repo PATH --dsmk-repo PATH
    python -m benchmarks.parity --geolora-repo PATH --dinov3-repo PATH [--dinov2-repo PATH] [--dsmk-repo PATH]

Each ``--*-repo`` is a local clone of a reference repository (skip a check by leaving its
option out). The features (``--geolora-repo``, with the DINO model code of ``--dinov3-repo``
/ ``--dinov2-repo``, and DeepShapeMatchingKit's DINO features with ``--dsmk-repo``) are
checked by `benchmarks.parity.geolora` (see its docstring for what it needs; tables in
``benchmarks/results/parity/parity_geolora.md``). The heads:

* ``--ulrssm-repo``: dongliangcao/Unsupervised-Learning-of-Robust-Spectral-Shape-Matching
  (MIT), with its release checkpoint ``faust_scape.pth`` (default: from ``--checkpoints``);
* ``--dpfm-repo``: pvnieo/DPFM (GPL-3.0), with ``faust.pth``;
* ``--dsmk-repo``: xieyizheng/DeepShapeMatchingKit (GPL), for EchoMatch (no release
  weights: both models get the same random weights).

The reference code is imported at run time from the clone; nothing of it is copied into
geofeat. For every stage (operators, input features, network output, refined features,
functional map, point map, losses, gradients of one training step) the table gives the
largest absolute difference between the two implementations fed the same mesh, operators
and weights, and the largest magnitude of the reference's values. It also times inference
and one training step of both on the same pair. The tables go to stdout and to
``benchmarks/results/parity/parity.md``.
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
from pathlib import Path

from benchmarks.common import DEFAULT_DATA, REPO, RESULTS, data_folder, machine
from benchmarks.parity.common import markdown
from benchmarks.parity.geolora import add_arguments as add_feature_arguments


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.parity", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--ulrssm-repo", type=Path, default=None)
    parser.add_argument("--dpfm-repo", type=Path, default=None)
    add_feature_arguments(parser)  # --geolora-repo, --dinov3-repo, --dinov2-repo, --dsmk-repo (EchoMatch too), ...
    parser.add_argument(
        "--checkpoints",
        type=Path,
        default=Path(os.environ.get("GEOFEAT_CHECKPOINTS", REPO.parent / "shared" / "checkpoints")),
        help="folder with ulrssm/faust_scape.pth and dpfm/faust.pth",
    )
    parser.add_argument(
        "--data-root", type=Path, default=DEFAULT_DATA, help="the folder holding the datasets (default $GEOFEAT_DATA)"
    )
    parser.add_argument("--no-timing", action="store_true")
    parser.add_argument("--out", type=Path, default=RESULTS / "parity" / "parity.md")
    parser.add_argument(
        "--features-out",
        type=Path,
        default=RESULTS / "parity" / "parity_geolora.md",
        help="tables of the feature checks",
    )
    args = parser.parse_args(argv)
    if not (args.ulrssm_repo or args.dpfm_repo or args.dsmk_repo or args.geolora_repo):
        parser.error("give at least one of --ulrssm-repo, --dpfm-repo, --dsmk-repo, --geolora-repo")
    args.data_root = data_folder(args.data_root, "--data-root")
    if args.geolora_repo:
        from benchmarks.parity import geolora

        geolora.main(_feature_argv(args))
    if not (args.ulrssm_repo or args.dpfm_repo or (args.dsmk_repo and not args.geolora_repo)):
        return 0
    timing = not args.no_timing
    sections = [f"Run {datetime.date.today().isoformat()} on {machine()}.\n"]
    if args.ulrssm_repo:
        from benchmarks.parity.ulrssm import ulrssm_stages

        rows, times = ulrssm_stages(
            args.ulrssm_repo, args.checkpoints / "ulrssm" / "faust_scape.pth", args.data_root, timing=timing
        )
        sections.append(markdown(rows, "ULRSSM (faust_scape.pth, FAUST_r tr_reg_081 -> tr_reg_080)") + _times(times))
    if args.dpfm_repo:
        from benchmarks.parity.dpfm import dpfm_stages

        result = dpfm_stages(args.dpfm_repo, args.checkpoints / "dpfm" / "faust.pth", args.data_root, timing=timing)
        rows, times = result if timing else (result, {})
        sections.append(markdown(rows, "DPFM (faust.pth, FAUST_r)") + _times(times))
    if args.dsmk_repo:
        from benchmarks.parity.echomatch import echomatch_stages

        for pair in ("full", "partial"):
            rows, times = echomatch_stages(args.dsmk_repo, args.data_root, pair=pair, timing=timing)
            sections.append(markdown(rows, f"EchoMatch (identical random weights, {pair} pair)") + _times(times))
    text = "\n".join(sections)
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    return 0


def _feature_argv(args: argparse.Namespace) -> list[str]:
    """The options of `benchmarks.parity.geolora` from this command line's."""
    argv = ["--geolora-repo", str(args.geolora_repo), "--data-root", str(args.data_root), "--out", str(args.features_out)]
    for name in ("dinov3_repo", "dinov2_repo", "dsmk_repo"):
        if getattr(args, name):
            argv += [f"--{name.replace('_', '-')}", str(getattr(args, name))]
    for name in ("shape", "views", "dsmk_views", "views_full", "views_partial", "differences", "other", "full_views", "partials"):
        argv += [f"--{name.replace('_', '-')}", str(getattr(args, name))]
    return argv if args.step else [*argv, "--no-step"]


def _times(times: dict[str, float]) -> str:
    if not times:
        return ""
    return "\n" + "\n".join(f"- {key}: {value:.3f}" for key, value in times.items()) + "\n"


if __name__ == "__main__":
    sys.exit(main())

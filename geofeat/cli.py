"""The ``geofeat`` command line: ``cache info|verify|clear``, ``descriptors``, ``demo``, ``train-geolora``, ``extract``."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import tempfile

from geofeat.cache import FeatureCache
from geofeat.errors import GeofeatError, StoreError
from geofeat.files import EntryFolder


def _out(line: str = "") -> None:
    sys.stdout.write(line + "\n")


def _report_others(store: EntryFolder, others) -> None:
    if others:
        _out(f"skipped {len(others)} path(s) in {store.root} that are not entries (left as they are):")
        for path in others[:20]:
            _out(f"  not an entry: {path}" + ("/" if path.is_dir() else ""))
        if len(others) > 20:
            _out(f"  ... and {len(others) - 20} more")


def _cache_stores(args: argparse.Namespace) -> list[tuple[str, EntryFolder]]:
    """The stores ``geofeat cache`` works on, with their headings: both default ones, or only those named."""
    from geofeat.geometry.geodesic import GeodesicStore

    if args.dir is None and args.geodesic_dir is None:
        return [("cache", FeatureCache()), ("geodesic store", GeodesicStore())]
    named = [("cache", FeatureCache(args.dir))] if args.dir is not None else []
    return named + ([("geodesic store", GeodesicStore(args.geodesic_dir))] if args.geodesic_dir is not None else [])


def _cache_command(args: argparse.Namespace) -> int:
    stores = _cache_stores(args)
    status = 0
    for heading, store in stores:
        if args.action == "info" or len(stores) > 1:
            _out(f"{heading}: {store.root}")
        try:
            status = max(status, _cache_action(args, store))
        except StoreError:
            raise
        except OSError as err:  # e.g. a store folder that cannot be listed
            raise store.error(f"cannot {args.action} {store.label} {store.root}: {err}") from err
    return status


def _cache_action(args: argparse.Namespace, store: EntryFolder) -> int:
    """``info``, ``verify`` or ``clear`` on one store; returns the exit status."""
    if args.action == "info":
        info = store.info()
        _out(f"entries: {info.entries}")
        _out(f"size: {info.bytes / 2**20:.2f} MiB")
        _out(f"temporary files: {info.temporary_files}")
        _report_others(store, info.other_paths)
    elif args.action == "verify":
        n_ok, damaged = store.verify(remove=not args.keep)
        kept = [p for p in damaged if p.exists()] if not args.keep else damaged
        removed = "" if args.keep else f" ({len(damaged) - len(kept)} removed" + (f", {len(kept)} could not be)" if kept else ")")
        _out(f"{n_ok} entries ok, {len(damaged)} damaged" + (removed if damaged else ""))
        for path in damaged:
            _out(f"  damaged: {path}")
        _report_others(store, store.other_paths())
        return 1 if damaged and args.keep else 0
    else:
        _out(f"removed {store.clear()} entries from {store.root}")
        _report_others(store, store.other_paths())
    return 0


def _descriptors_command(args: argparse.Namespace) -> int:
    from geofeat.descriptors import descriptors

    for info in descriptors():
        status = "available" if info.available else f"unavailable ({info.reason})"
        _out(f"{info.name:10s} {status}: {info.summary}")
        if info.params:
            _out("           " + ", ".join(f"{k}={v!r}" for k, v in info.params.items()))
    return 0


def _demo_command(args: argparse.Namespace) -> int:
    from geofeat.demo import run_demo

    with tempfile.TemporaryDirectory(prefix="geofeat-demo-") as tmp:
        rows = run_demo(args.cache_dir or tmp, seed=args.seed, progress=not args.no_progress)
    _out("Nearest-neighbour matching of a coarse blob (2,562 vertices) to a finer rotated copy (10,242 vertices)")
    _out(f"{'descriptor':>10} {'dim':>4} {'compute (2 shapes)':>19} {'cache hit':>10} {'mean error x100':>16}")
    for row in rows:
        _out(
            f"{row.descriptor:>10} {row.dim:>4} {row.seconds:>18.3f}s {row.cache_hit_seconds * 1e3:>8.2f}ms {row.mean_error_x100:>16.2f}"
        )
    return 0


def _flag_type(default):
    """argparse type of a TrainConfig field, from its default value."""
    if isinstance(default, bool):
        return None
    if isinstance(default, int):
        return int
    if isinstance(default, float):
        return float
    if isinstance(default, tuple):
        return lambda text: tuple(part.strip() for part in text.split(",") if part.strip())
    return str


def _add_train_flags(parser: argparse.ArgumentParser) -> None:
    """One ``--flag`` per `TrainConfig` setting (its docstring documents them); defaults stay None = not given."""
    from geofeat.train.config import TrainConfig

    defaults = TrainConfig.__dataclass_fields__
    numeric_or_none = {"first": int, "max_minutes": float}
    for name in TrainConfig.field_names():
        default = (
            defaults[name].default if defaults[name].default is not dataclasses.MISSING else defaults[name].default_factory()
        )
        flag = "--" + name.replace("_", "-")
        if isinstance(default, bool):
            parser.add_argument(flag, dest=name, action=argparse.BooleanOptionalAction, default=None, help=f"(default {default})")
        else:
            kind = numeric_or_none.get(name) or _flag_type(default)
            shown = ",".join(default) if isinstance(default, tuple) else default
            parser.add_argument(flag, dest=name, type=kind, default=None, help=f"(default {shown})")


def _train_command(args: argparse.Namespace) -> int:
    from geofeat import distributed
    from geofeat.train.config import TrainConfig
    from geofeat.train.trainer import GeoLoraTrainer

    given = {name: getattr(args, name) for name in TrainConfig.field_names() if getattr(args, name) is not None}
    config = TrainConfig.from_file(args.config, **given) if args.config else TrainConfig(**given)  # warns of unknown keys
    try:  # under torchrun: one DDP rank (gloo on the CPU, NCCL on a GPU), the group ended at the end
        with distributed.process_group(config.device):
            checkpoint = GeoLoraTrainer(config).fit()
            main = distributed.is_main()
    except KeyboardInterrupt:
        return 130
    if main:
        _out(f"adapter: {checkpoint}")
    return 0


def _extract_command(args: argparse.Namespace) -> int:
    from pathlib import Path

    from geofeat import distributed
    from geofeat.extract import ExportSpec, ExtractError, dataset_shapes, extract, folder_shapes, params_digest, parse_params

    params = parse_params(args.param or [])
    if args.data is not None:
        shapes = folder_shapes(args.data)
    else:
        shapes, _ = dataset_shapes(args.dataset, args.data_root, split=args.split)
    export = None
    if args.export is not None:
        to = Path(args.export_to) if args.export_to else None
        export = ExportSpec(args.export, args.layout, to, args.feature_folder)
    elif args.export_to or args.feature_folder:
        raise ExtractError("--export-to and --feature-folder need --export npy|h5.")
    manifest = args.manifest or f"{args.descriptor}-{params_digest(args.descriptor, params)}.manifest.json"
    result = extract(
        shapes, args.descriptor, params, store=args.out, manifest=manifest, export=export,
        device=args.device, progress=not args.no_progress,
    )  # fmt: skip
    if distributed.is_main():
        _out(
            f"{result['n_shapes']} shapes: {result['n_computed']} computed, {result['n_present']} already in the store, "
            f"{result['n_failed']} failed ({result['world_size']} process(es))"
        )
        _out(f"store: {result['store']}")
        _out(f"manifest: {result['manifest']}")
        for record in [r for r in result["shapes"] if r["status"] == "failed"][:20]:
            _out(f"  failed: {record['shape']}: {record['error']}")
    return 1 if result["n_failed"] else 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``geofeat`` command."""
    parser = argparse.ArgumentParser(prog="geofeat", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="command", required=True)
    cache = sub.add_parser(
        "cache",
        help="inspect, verify or clear the feature cache and the geodesic store",
        description="Without --dir or --geodesic-dir: the feature cache <cache>/features and the geodesic store "
        "<cache>/geodesics, <cache> being $GEOFEAT_CACHE_DIR or the user cache. With either: only the folders named.",
    )
    cache.add_argument("action", choices=["info", "verify", "clear"])
    cache.add_argument("--dir", help="a feature cache folder (default: <cache>/features)")
    cache.add_argument("--geodesic-dir", help="a geodesic store folder (default: <cache>/geodesics)")
    cache.add_argument("--keep", action="store_true", help="verify: report damaged entries without removing them")
    cache.set_defaults(func=_cache_command)
    desc = sub.add_parser("descriptors", help="list descriptors, their availability and parameters")
    desc.set_defaults(func=_descriptors_command)
    demo = sub.add_parser("demo", help="compute and compare HKS and WKS on shapes built in code (offline)")
    demo.add_argument("--seed", type=int, default=0)
    demo.add_argument("--cache-dir", help="cache directory (default: a temporary one)")
    demo.add_argument("--no-progress", action="store_true", help="hide progress bars")
    demo.set_defaults(func=_demo_command)
    train = sub.add_parser(
        "train-geolora",
        help="train a GeoLoRA adapter (self-supervised, on synthetic partial shapes)",
        description="Train a LoRA adapter on a frozen DINOv3 with the GeoLoRA recipe. Settings come from --config "
        "(JSON or YAML) and the flags below (flags win). Running again with the same --out resumes from its newest checkpoint.",
    )
    train.add_argument("--config", help="settings file (.json, .yaml); keys are the flag names with underscores")
    _add_train_flags(train)
    train.set_defaults(func=_train_command)
    ext = sub.add_parser(
        "extract",
        help="compute a descriptor for every shape of a folder or dataset into the feature store (torchrun: sharded)",
        description="Compute features for a collection into the content-keyed feature store, skipping entries already "
        "there, and write a manifest. Under torchrun (torchrun --nproc_per_node=N -m geofeat extract ...) every rank "
        "takes every N-th shape of the sorted collection.",
    )
    ext.add_argument("--descriptor", required=True, help="descriptor name (see 'geofeat descriptors')")
    ext.add_argument("--param", action="append", metavar="KEY=VALUE", help="descriptor parameter; repeat it (JSON values)")
    source = ext.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", metavar="FOLDER", help="every .off/.obj/.ply file below FOLDER")
    source.add_argument("--dataset", metavar="NAME", help="a geofeat dataset name (faust_r, scape_r, ...)")
    ext.add_argument("--split", default="all", help="--dataset: which split (default all)")
    ext.add_argument("--data-root", help="--dataset: the data folder (default $GEOFEAT_DATA)")
    ext.add_argument("--out", metavar="DIR", help="feature store folder (default: the feature cache)")
    ext.add_argument("--manifest", metavar="FILE", help="manifest JSON (default ./<descriptor>-<params digest>.manifest.json)")
    ext.add_argument("--export", choices=["npy", "h5"], help="also write per-shape .npy files or one HDF5 file")
    ext.add_argument("--layout", choices=["mirror", "beside"], default="mirror", help="npy export layout (default mirror)")
    ext.add_argument("--export-to", metavar="PATH", help="export folder (npy) or file (h5)")
    ext.add_argument("--feature-folder", metavar="NAME", help="--layout beside: folder name (default the descriptor name)")
    ext.add_argument("--device", default="auto", help="auto (the rank's local GPU, else cpu), cpu, cuda, cuda:N")
    ext.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    ext.set_defaults(func=_extract_command)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``geofeat`` command."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    try:
        return args.func(args)
    except GeofeatError as err:
        sys.stderr.write(f"geofeat: error: {err}\n")
        return 2


if __name__ == "__main__":
    sys.exit(main())

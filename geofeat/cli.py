"""The ``geofeat`` command line: ``cache info|verify|clear``, ``descriptors``, ``demo``, ``train-geolora``."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
import tempfile

from geofeat.cache import CacheError, FeatureCache
from geofeat.errors import GeofeatError


def _out(line: str = "") -> None:
    sys.stdout.write(line + "\n")


def _report_others(store: FeatureCache, others) -> None:
    if others:
        _out(f"skipped {len(others)} path(s) in {store.root} that are not cache entries (left as they are):")
        for path in others[:20]:
            _out(f"  not an entry: {path}" + ("/" if path.is_dir() else ""))
        if len(others) > 20:
            _out(f"  ... and {len(others) - 20} more")


def _cache_command(args: argparse.Namespace) -> int:
    store = FeatureCache(args.dir) if args.dir else FeatureCache()
    try:
        if args.action == "info":
            info = store.info()
            _out(f"cache: {info.root}")
            _out(f"entries: {info.entries}")
            _out(f"size: {info.bytes / 2**20:.2f} MiB")
            _out(f"temporary files: {info.temporary_files}")
            _report_others(store, info.other_paths)
        elif args.action == "verify":
            n_ok, damaged = store.verify(remove=not args.keep)
            kept = [p for p in damaged if p.exists()] if not args.keep else damaged
            removed = (
                "" if args.keep else f" ({len(damaged) - len(kept)} removed" + (f", {len(kept)} could not be)" if kept else ")")
            )
            _out(f"{n_ok} entries ok, {len(damaged)} damaged" + (removed if damaged else ""))
            for path in damaged:
                _out(f"  damaged: {path}")
            _report_others(store, store.other_paths())
            return 1 if damaged and args.keep else 0
        else:
            _out(f"removed {store.clear()} entries from {store.root}")
            _report_others(store, store.other_paths())
    except CacheError:
        raise
    except OSError as err:  # e.g. a store folder that cannot be listed
        raise CacheError(f"cannot {args.action} the feature cache {store.root}: {err}") from err
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
    from geofeat.train.config import TrainConfig
    from geofeat.train.trainer import GeoLoraTrainer

    given = {name: getattr(args, name) for name in TrainConfig.field_names() if getattr(args, name) is not None}
    config = TrainConfig.from_file(args.config, **given) if args.config else TrainConfig(**given)  # warns of unknown keys
    try:
        checkpoint = GeoLoraTrainer(config).fit()
    except KeyboardInterrupt:
        return 130
    _out(f"adapter: {checkpoint}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``geofeat`` command."""
    parser = argparse.ArgumentParser(prog="geofeat", description=__doc__)
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    sub = parser.add_subparsers(dest="command", required=True)
    cache = sub.add_parser("cache", help="inspect, verify or clear the feature cache")
    cache.add_argument("action", choices=["info", "verify", "clear"])
    cache.add_argument("--dir", help="cache directory (default: $GEOFEAT_CACHE_DIR or the user cache)")
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

"""The ``geofeat`` command line (``geofeat --version`` prints the version): ``cache info|verify|clear``, ``descriptors``, ``demo``, ``train-geolora``, ``extract``, ``data check|prepare``.

Help texts are plain text (no markup): `build_parser` holds them, and the settings of
``train-geolora`` take theirs from the `geofeat.train.config.TrainConfig` docstring.
Progress bars are drawn only when stderr is a terminal (`geofeat.runtime.progress`); ``--no-progress``
hides them there too.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import inspect
import logging
import os
import re
import sys
import tempfile
import textwrap
from pathlib import Path

from geofeat._version import __version__
from geofeat.descriptors.cache import FeatureCache
from geofeat.errors import ExtractError, GeofeatError, StoreError
from geofeat.runtime.progress import hidden_progress
from geofeat.storage.entry_folder import EntryFolder

#: What ``geofeat --help`` says about the command (plain text: argparse prints it as it is).
DESCRIPTION = (
    "geofeat: per-vertex shape descriptors (HKS, WKS, DINOv2, DINOv3, GeoLoRA) with a content-keyed feature cache, "
    "for non-rigid and partial 3D shape matching."
)
EPILOG = (
    "Run 'geofeat COMMAND --help' for the options of a command. Caches live in $GEOFEAT_CACHE_DIR (default: the user "
    "cache folder, e.g. ~/.cache/geofeat). Progress bars are drawn only when stderr is a terminal."
)


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
    from geofeat.geometry.geodesic_store import GeodesicStore

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


#: The backbone each DINO-based descriptor runs on.
_BACKBONE_OF = {"dinov2": "dinov2", "dinov3": "dinov3", "geolora": "dinov3"}
#: Which checkpoint each backbone kind takes and where a user gets it.
_WEIGHTS_SOURCE = {
    "dinov2": (
        "a DINOv2 model (patch 14), e.g. facebook/dinov2-base (or -small, -large, -giant) from Hugging Face: "
        "'hf download facebook/dinov2-base --local-dir dinov2-base'; or one of Meta's .pth checkpoints listed at "
        "https://github.com/facebookresearch/dinov2"
    ),
    "dinov3": (
        "a DINOv3 ViT model (patch 16); GeoLoRA uses ViT-B/16, facebook/dinov3-vitb16-pretrain-lvd1689m on Hugging Face, "
        "which is gated: accept Meta's licence on its page, log in ('hf auth login'), then "
        "'hf download facebook/dinov3-vitb16-pretrain-lvd1689m --local-dir dinov3-vitb16'; or Meta's release .pth "
        "(dinov3_vitb16_pretrain_lvd1689m-*.pth, access form at https://github.com/facebookresearch/dinov3)"
    ),
}
_LORA_SOURCE = (
    "checkpoint=, given per call: a folder written by 'geofeat train-geolora' (<run>/checkpoints/step_NNNNNNN), or a "
    "release .pth of the GeoLoRA authors (saved_models/faust.pth, becos.pth, smal.pth, ... in "
    "https://github.com/vikiehm/geo-lora)"
)
_LABEL_WIDTH = 10


def _hub_id_cached(repo_id: str) -> bool:
    """Whether the Hub model ``repo_id`` is in the local Hugging Face cache (its config.json; no network)."""
    try:
        from huggingface_hub import try_to_load_from_cache
    except ImportError:
        return False
    try:
        found = try_to_load_from_cache(repo_id, "config.json")
    except Exception:  # a malformed id: the hub validates it
        return False
    return isinstance(found, str)


def weights_status(kind: str) -> tuple[bool, str]:
    """Whether the backbone ``kind`` finds usable weights here when ``weights=`` is not given, and why (nothing is loaded).

    Parameters
    ----------
    kind : {"dinov2", "dinov3"}

    Returns
    -------
    found : bool
        True when ``$GEOFEAT_DINOV2_WEIGHTS`` / ``$GEOFEAT_DINOV3_WEIGHTS`` names an existing
        official ``.pth``/``.pt``, a model folder holding ``config.json`` and weights, or a Hub
        id already in the local Hugging Face cache.
    why : str
        One line for ``geofeat descriptors``.
    """
    from geofeat.backbones.dino import WEIGHTS_ENV

    env = WEIGHTS_ENV[kind]
    value = os.environ.get(env, "").strip()
    if not value:
        return False, f"${env} is not set"
    path = Path(value).expanduser()
    if path.is_file():
        if path.suffix.lower() in (".pth", ".pt"):
            return True, f"${env}={value} (an official checkpoint)"
        return False, f"${env}={value} is a {path.suffix or 'suffix-less'} file, not a .pth/.pt or a model folder"
    if path.is_dir():
        weights = [*path.glob("*.safetensors"), *path.glob("pytorch_model*.bin")]
        if (path / "config.json").is_file() and weights:
            return True, f"${env}={value} (a model folder)"
        return False, f"${env}={value} is a folder without config.json and *.safetensors"
    if value.count("/") == 1 and not value.startswith((".", "/", "~")):
        if _hub_id_cached(value):
            return True, f"${env}={value} (a Hub id, in the local Hugging Face cache)"
        return False, f"${env}={value} is a Hub id not in the local Hugging Face cache (it would be downloaded on first use)"
    return False, f"${env}={value} does not exist"


def _labelled(label: str, text: str) -> list[str]:
    """``label: text`` wrapped to 100 columns, continuation lines aligned under the text."""
    indent = " " * _LABEL_WIDTH
    head = f"{indent}{label + ':':<9}"
    return textwrap.wrap(text, width=100, initial_indent=head, subsequent_indent=indent + " " * 9, break_on_hyphens=False)


def _descriptor_lines(info) -> tuple[str, list[str]]:
    """The status and the detail lines of one descriptor in ``geofeat descriptors``."""
    from geofeat.descriptors.registry import descriptor_entry

    entry = descriptor_entry(info.name)
    ready = info.available
    if entry.requires:
        install = f"pip install 'geofeat[{entry.extra}]'" if entry.extra else "pip install " + " ".join(entry.requires)
        missing = entry.missing()
        extra = install + (f" (not installed: {', '.join(missing)} missing)" if missing else " (installed)")
    else:
        extra = "none (the base install)"
    lines = _labelled("extra", extra)
    kind = _BACKBONE_OF.get(info.name)
    if kind is not None:
        found, why = weights_status(kind)
        ready = ready and found
        lines += _labelled("weights", ("found: " if found else "missing: ") + why)
        env = "GEOFEAT_DINOV2_WEIGHTS" if kind == "dinov2" else "GEOFEAT_DINOV3_WEIGHTS"
        lines += _labelled("get", f"{_WEIGHTS_SOURCE[kind]}. Then set {env} to the folder or .pth, or pass weights=.")
        if info.name == "geolora":
            lines += _labelled("LoRA", _LORA_SOURCE)
        import torch

        lines += _labelled("device", "cuda (a GPU is present)" if torch.cuda.is_available() else "cpu (no CUDA GPU here)")
    if info.params:
        lines += _labelled("params", ", ".join(f"{k}={v!r}" for k, v in info.params.items()))
    status = "ready" if ready else "not ready"
    if ready and info.name == "geolora":
        status = "ready, given a LoRA (checkpoint=)"
    return status, lines


def _descriptors_command(args: argparse.Namespace) -> int:
    from geofeat.descriptors import descriptors

    for info in descriptors():
        status, lines = _descriptor_lines(info)
        _out(f"{info.name:<{_LABEL_WIDTH}}{status}: {info.summary}")
        for line in lines:
            _out(line)
    _out()
    _out("ready: runs here as it is. Nothing was downloaded or loaded to find out.")
    return 0


def _quiet_if(hidden: bool):
    """`hidden_progress` when ``hidden`` (``--no-progress``), else nothing."""
    return hidden_progress() if hidden else contextlib.nullcontext()


def _demo_command(args: argparse.Namespace) -> int:
    from geofeat.apps.demo import run_demo

    with tempfile.TemporaryDirectory(prefix="geofeat-demo-") as tmp, _quiet_if(args.no_progress):
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


def plain_text(text: str) -> str:
    """Docstring markup as plain text: ``code`` and `reference` lose their backticks, whitespace is collapsed."""
    text = re.sub(r"``(.+?)``", r"\1", text)
    text = re.sub(r"`~?([^`]+)`", r"\1", text)
    return " ".join(text.split())


def numpydoc_parameters(doc: str) -> dict[str, str]:
    """Each name of the Parameters section of a numpydoc docstring, with its description as plain text.

    Names documented together (``rank, alpha : int, float``) share a description; an entry
    without a description gets its type line (``{"official", "uniform"}`` -> ``one of official, uniform``).
    """
    lines = inspect.cleandoc(doc).splitlines()
    found: dict[str, str] = {}
    try:
        start = lines.index("Parameters") + 2
    except ValueError:
        return found
    names: list[str] = []
    kind, text = "", []

    def flush() -> None:
        description = plain_text(" ".join(text))
        if not description and kind.startswith("{"):
            description = "one of " + ", ".join(part.strip().strip("\"'") for part in kind.strip("{}").split(","))
        for name in names:
            found[name] = description or plain_text(kind)

    for i, line in enumerate(lines[start:], start):
        if line and not line[0].isspace():
            if i + 1 < len(lines) and lines[i + 1].startswith("---"):
                break  # the next section
            flush()
            head, _, kind = line.partition(":")
            names, kind, text = [n.strip() for n in head.split(",")], kind.strip(), []
        elif line.strip():
            text.append(line.strip())
    flush()
    return found


#: Help of the settings that the TrainConfig docstring lists without a description of their own.
_TRAIN_HELP = {"val_split": "Split of val_dataset used for validation", "progress": "Show progress bars (on a terminal only)"}


def _train_help(name: str, description: str, default) -> str:
    """The help of one ``train-geolora`` flag: its description (as the docstring writes it) and its default."""
    about = _TRAIN_HELP.get(name) or description.rstrip(".") or name.replace("_", " ")
    if default == "":
        shown = "required, here or in --config"
    else:
        shown = "default " + (",".join(default) if isinstance(default, tuple) else str(default))
    return f"{about} ({shown})".replace("%", "%%")


def _add_train_flags(parser: argparse.ArgumentParser) -> None:
    """One ``--flag`` per `TrainConfig` setting, its help from the TrainConfig docstring; defaults stay None = not given."""
    from geofeat.train.config import TrainConfig

    defaults = TrainConfig.__dataclass_fields__
    documented = numpydoc_parameters(TrainConfig.__doc__ or "")
    numeric_or_none = {"first": int, "max_minutes": float}
    for name in TrainConfig.field_names():
        default = (
            defaults[name].default if defaults[name].default is not dataclasses.MISSING else defaults[name].default_factory()
        )
        flag = "--" + name.replace("_", "-")
        text = _train_help(name, documented.get(name, ""), default)
        if isinstance(default, bool):
            parser.add_argument(flag, dest=name, action=argparse.BooleanOptionalAction, default=None, help=text)
        else:
            kind = numeric_or_none.get(name) or _flag_type(default)
            parser.add_argument(flag, dest=name, type=kind, default=None, help=text)


def _train_command(args: argparse.Namespace) -> int:
    from geofeat.runtime import distributed
    from geofeat.train.config import TrainConfig
    from geofeat.train.trainer import GeoLoraTrainer

    given = {name: getattr(args, name) for name in TrainConfig.field_names() if getattr(args, name) is not None}
    config = TrainConfig.from_file(args.config, **given) if args.config else TrainConfig(**given)  # warns of unknown keys
    try:  # under torchrun: one DDP rank (gloo on the CPU, NCCL on a GPU), the group ended at the end
        with distributed.process_group(config.device), _quiet_if(not config.progress):
            checkpoint = GeoLoraTrainer(config).fit()
            main = distributed.is_main()
    except KeyboardInterrupt:
        return 130
    if main:
        _out(f"lora: {checkpoint}")
    return 0


def _extract_command(args: argparse.Namespace) -> int:
    from geofeat.apps.extract import ExportSpec, dataset_shapes, default_manifest_path, extract, folder_shapes, parse_params
    from geofeat.runtime import distributed

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
    manifest = args.manifest or default_manifest_path(args.descriptor, params, args.out)  # in the store, not in ./
    try:
        with _quiet_if(args.no_progress):
            result = extract(
                shapes,
                args.descriptor,
                params,
                store=args.out,
                manifest=manifest,
                export=export,
                device=args.device,
                prefetch=args.prefetch,
                progress=not args.no_progress,
            )
    except KeyboardInterrupt:
        sys.stderr.write(
            "geofeat: interrupted. The features computed so far are kept in the store; the same command "
            "computes only the others.\n"
        )
        return 130
    if distributed.is_main():
        _out(
            f"{result['n_shapes']} shapes: {result['n_computed']} computed, {result['n_present']} already in the store, "
            f"{result['n_failed']} failed ({result['world_size']} process(es))"
        )
        rate, slowest = result["shapes_per_second"], " (the slowest process)" if result["world_size"] > 1 else ""
        if rate is None:
            _out(f"throughput: no shape computed ({result['wall_seconds']:.2f} s{slowest})")
        else:
            _out(
                f"throughput: {result['n_computed']} shapes computed in {result['wall_seconds']:.2f} s{slowest}, "
                f"{rate:.3g} shapes/s"
            )
        _out(f"store: {result['store']}")
        if result.get("manifest_error"):
            _out(f"manifest: {result['manifest_error']}; written to {result['manifest'] or 'no place at all'} instead")
        else:
            _out(f"manifest: {result['manifest']}")
        if export is not None:
            where = (
                export.to.absolute()
                if export.to is not None
                else f"a '{export.feature_folder or args.descriptor}' folder beside each mesh folder"
            )
            _out(f"export ({export.format}): {where}")
        for record in [r for r in result["shapes"] if r["status"] == "failed"][:20]:
            _out(f"  failed: {record['shape']}: {record['error']}")
        for record in [r for r in result["shapes"] if "export_error" in r][:20]:
            _out(f"  export failed: {record['shape']}: {record['export_error']}")
        if result.get("export_error"):
            _out(f"export failed: {result['export_error']} (the features are in the store; run again to export)")
    incomplete = result["n_failed"] or result.get("n_export_failed") or result.get("export_error") or result.get("manifest_error")
    return 1 if incomplete else 0


#: The name ``geofeat data check`` and ``prepare`` take for a whole BeCoS generator output (every setting and split).
BECOS = "becos"


def _data_check_command(args: argparse.Namespace) -> int:
    from geofeat.apps.data import check_dataset
    from geofeat.checks import parse_key_values
    from geofeat.errors import DatasetError

    options = parse_key_values(args.option or [], "--option", error=DatasetError)
    with _quiet_if(args.no_progress):
        if args.dataset.strip().lower() == BECOS:
            report = _check_becos_output(args, options)
        else:
            split = "test" if args.split is None else args.split
            report = check_dataset(args.dataset, args.data_root, split, progress=not args.no_progress, **options)
    for line in report.lines():
        _out(line)
    return 0 if report.ok else 1


def _check_becos_output(args: argparse.Namespace, options: dict):
    """``geofeat data check becos``: a whole generator output folder, through `geofeat.apps.becos_check.check_becos`."""
    from geofeat.apps.becos_check import check_becos
    from geofeat.datasets.base import DATA_ENV
    from geofeat.errors import DatasetError

    folder = args.data_root or os.environ.get(DATA_ENV)
    if not folder:
        raise DatasetError(
            f"geofeat data check {BECOS} needs --data-root: the generator's output folder, a setting folder "
            f"(.../partial_full) or a BeCoS folder (or set ${DATA_ENV})."
        )
    unknown = sorted(set(options) - {"pairings"})
    if unknown:
        raise DatasetError(f"{BECOS} does not take option(s) {', '.join(unknown)}; it takes: pairings.")
    splits = ("train", "val", "test") if args.split is None else (args.split,)
    return check_becos(folder, pairings=options.get("pairings"), splits=splits, progress=not args.no_progress)


def _data_prepare_command(args: argparse.Namespace) -> int:
    from geofeat.apps.prepare import prepare_becos
    from geofeat.checks import parse_key_values
    from geofeat.errors import DatasetError

    overrides = parse_key_values(args.set or [], "--set", error=DatasetError)
    with _quiet_if(args.no_progress):
        report = prepare_becos(
            args.generator,
            args.out,
            args.config,
            args.python,
            setting=args.setting,
            overrides=overrides or None,
            echo=_out,
            check=not args.no_check,
            progress=not args.no_progress,
        )
    for line in report.lines():
        _out(line)
    return 0 if report.ok else 1


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``geofeat`` command (every option has a plain-text help)."""
    parser = argparse.ArgumentParser(prog="geofeat", description=DESCRIPTION, epilog=EPILOG)
    parser.add_argument("-v", "--verbose", action="store_true", help="log at INFO level")
    parser.add_argument("--version", action="version", version=f"geofeat {__version__}", help="print the version and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", title="commands")
    cache = sub.add_parser(
        "cache",
        help="inspect, verify or clear the feature cache and the geodesic store",
        description="Inspect, verify or clear the stores. Without --dir or --geodesic-dir: the feature cache "
        "<cache>/features and the geodesic store <cache>/geodesics, <cache> being $GEOFEAT_CACHE_DIR or the user "
        "cache folder. With either: only the folders named. Files that are not entries are reported and left alone.",
    )
    cache.add_argument(
        "action",
        choices=["info", "verify", "clear"],
        help="info: entries and size; verify: read every entry back and remove damaged ones; clear: remove every entry",
    )
    cache.add_argument("--dir", help="a feature cache folder (default: <cache>/features)")
    cache.add_argument("--geodesic-dir", help="a geodesic store folder (default: <cache>/geodesics)")
    cache.add_argument("--keep", action="store_true", help="verify: report damaged entries without removing them")
    cache.set_defaults(func=_cache_command)
    desc = sub.add_parser(
        "descriptors",
        help="list the descriptors, what each needs (extra, weights) and whether it is ready here",
        description="List every registered descriptor: whether it can run here as it is, the extra to install, the "
        "weights it needs and where to get them, and its parameters. Nothing is downloaded or loaded.",
    )
    desc.set_defaults(func=_descriptors_command)
    demo = sub.add_parser(
        "demo",
        help="compute and compare HKS and WKS on shapes built in code (offline)",
        description="Match a coarse synthetic blob to a finer, rotated copy by nearest neighbour in HKS and in WKS "
        "space, and print each descriptor's time, cache-hit time and mean error. Needs no data and no network.",
    )
    demo.add_argument("--seed", type=int, default=0, help="seed of the synthetic shapes and of the rotation (default 0)")
    demo.add_argument("--cache-dir", help="feature cache folder to use (default: a temporary one, removed at the end)")
    demo.add_argument("--no-progress", action="store_true", help="hide progress bars (they show only on a terminal anyway)")
    demo.set_defaults(func=_demo_command)
    train = sub.add_parser(
        "train-geolora",
        help="train a LoRA on DINOv3 for GeoLoRA features (self-supervised, on synthetic partial shapes)",
        description="Train a LoRA on a frozen DINOv3 with the GeoLoRA recipe. Settings come from --config "
        "(JSON or YAML) and the flags below (flags win). Running again with the same --out resumes from its newest checkpoint.",
    )
    train.add_argument("--config", help="Settings file (.json, .yaml); keys are the flag names with underscores")
    _add_train_flags(train)
    train.add_argument(
        "--dataset",
        dest="data",
        metavar="NAME",
        default=None,
        help="the same as --data with a dataset name: faust_r, scape_r, or an official training set (faust, becos, "
        "becos_without_shrec16, smal) under --data-root",
    )
    train.set_defaults(func=_train_command)
    ext = sub.add_parser(
        "extract",
        help="compute a descriptor for every shape of a folder or dataset into the feature store (torchrun: sharded)",
        description="Compute features for a collection into the content-keyed feature store, skipping entries already "
        "there, and write a manifest (one record per shape, absolute paths) into the store folder: --out, or the "
        "feature cache without it. Under torchrun (torchrun --nproc_per_node=N -m geofeat extract ...) every rank "
        "takes every N-th shape of the sorted collection.",
    )
    ext.add_argument("--descriptor", required=True, help="descriptor name (see 'geofeat descriptors')")
    ext.add_argument("--param", action="append", metavar="KEY=VALUE", help="descriptor parameter; repeat it (JSON values)")
    source = ext.add_mutually_exclusive_group(required=True)
    source.add_argument("--data", metavar="FOLDER", help="every .off/.obj/.ply file below FOLDER")
    source.add_argument("--dataset", metavar="NAME", help="a geofeat dataset name (faust_r, scape_r, ...)")
    ext.add_argument("--split", default="all", help="--dataset: which split (default all)")
    ext.add_argument("--data-root", help="--dataset: the data folder (default $GEOFEAT_DATA)")
    ext.add_argument("--out", metavar="DIR", help="feature store folder (default: the feature cache, <cache>/features)")
    ext.add_argument(
        "--manifest",
        metavar="FILE",
        help="manifest JSON to write (default: <descriptor>-<params digest>.manifest.json in the store folder)",
    )
    ext.add_argument("--export", choices=["npy", "h5"], help="also write per-shape .npy files or one HDF5 file")
    ext.add_argument("--layout", choices=["mirror", "beside"], default="mirror", help="npy export layout (default mirror)")
    ext.add_argument("--export-to", metavar="PATH", help="export folder (npy) or file (h5)")
    ext.add_argument("--feature-folder", metavar="NAME", help="--layout beside: folder name (default the descriptor name)")
    ext.add_argument("--device", default="auto", help="auto (the rank's local GPU, else cpu), cpu, cuda, cuda:N")
    ext.add_argument(
        "--prefetch",
        type=int,
        metavar="N",
        help="shapes read and prepared (DINO descriptors: rendered) on a background thread ahead of the one being "
        "computed; 0: none (default: 2 for dinov2, dinov3 and geolora, 0 for the others)",
    )
    ext.add_argument("--no-progress", action="store_true", help="hide progress bars (they show only on a terminal anyway)")
    ext.set_defaults(func=_extract_command)
    data = sub.add_parser(
        "data",
        help="check what geofeat reads from a copy of a benchmark",
        description="Commands about benchmark data on disk.",
    )
    data_sub = data.add_subparsers(dest="data_command", required=True, metavar="ACTION", title="actions")
    check = data_sub.add_parser(
        "check",
        help="read every pair of a dataset and report counts, ranges and anything unexpected",
        description="Open a dataset as every geofeat run does, read every pair of the split, and print what was read: "
        "the folder used, pair and shape counts, vertex counts, the range of the ground-truth indices and the share "
        "of vertices without a counterpart, which way the maps go, and anything unexpected (pairs that cannot be "
        "read, indices out of range, maps whose shapes are missing, files that no pair reads). DATASET 'becos' checks "
        "a whole BeCoS generator output instead: every setting and split against the pairs the generator drew, "
        "half-written pair folders, and the recorded areas and rotations. Exit status 0: clean; 1: something is "
        "wrong (listed under 'problems'); 2: bad input (unknown dataset, missing folder).",
    )
    check.add_argument(
        "dataset", metavar="DATASET", help="a geofeat dataset name (psmal, shrec16_cuts, pfaust_m, cp2p24, ...) or becos"
    )
    check.add_argument("--data-root", metavar="PATH", help="the data folder, as for the loaders (default $GEOFEAT_DATA)")
    check.add_argument("--split", help="which split to read (default test; for becos: train, val and test)")
    check.add_argument(
        "--option", action="append", metavar="KEY=VALUE", help="a loader option (layout=dpfm, difficulty=hard); repeat it"
    )
    check.add_argument("--no-progress", action="store_true", help="hide the progress bar (it shows only on a terminal anyway)")
    check.set_defaults(func=_data_check_command)
    prepare = data_sub.add_parser(
        "prepare",
        help="build a benchmark with its authors' generator (becos) and check what it wrote",
        description="Run your copy of a benchmark's generator in its own Python environment, move what it wrote to "
        "--out/<setting>/, and check it as 'geofeat data check becos' does. Only BeCoS is built this way (its "
        "generator: NafieAmrani/becos-code). Exit status 0: the generator succeeded and its output is complete; 1: "
        "it failed or its output is not (listed under 'problems'); 2: bad input (no generator there, its Python "
        "lacks its requirements, --out/<setting> not empty).",
    )
    prepare.add_argument("benchmark", choices=[BECOS], help="the benchmark to build (becos)")
    prepare.add_argument("--generator", required=True, metavar="PATH", help="your clone of the generator (main.py, config/)")
    prepare.add_argument("--out", required=True, metavar="PATH", help="where the output goes, as <out>/<setting>/")
    prepare.add_argument(
        "--config", default="demo_config", help="a config name under <generator>/config/, no .yaml (default demo_config)"
    )
    prepare.add_argument(
        "--python",
        metavar="PY",
        help="the generator's Python (default <generator>/.venv, venv or env, else python3 on PATH)",
    )
    prepare.add_argument(
        "--setting", choices=["full_full", "partial_full", "partial_partial"], help="override the config's setting"
    )
    prepare.add_argument(
        "--set", action="append", metavar="KEY=VALUE", help="override another config key (template_file=...); repeat it"
    )
    prepare.add_argument("--no-check", action="store_true", help="do not check the output afterwards")
    prepare.add_argument("--no-progress", action="store_true", help="hide the progress bar of the check (terminal only anyway)")
    prepare.set_defaults(func=_data_prepare_command)
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
    except KeyboardInterrupt:
        sys.stderr.write("geofeat: interrupted.\n")
        return 130


if __name__ == "__main__":
    sys.exit(main())

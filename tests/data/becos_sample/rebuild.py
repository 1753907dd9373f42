"""Rebuild becos_sample.tar.xz with the BeCoS generator (run it with the generator's Python).

    cd becos-code                      # NafieAmrani/becos-code at the commit named in README.md
    <becos venv>/bin/python <geofeat>/tests/data/becos_sample/rebuild.py --out <geofeat>/tests/data/becos_sample

It uses the generator's own functions, unchanged: the demo configuration (``demo_config.yaml``)
with ``setting`` set (and, for partial_full, the TOSCA demo's template file), the pairs drawn
as ``main.py`` draws them, and each listed test pair written as ``main.py`` writes it, into
``output/<setting>/`` of the generator (an older folder there is renamed by the generator, as
``main.py`` does). ``main.py`` would write every pair of every split, train first (hours);
this writes only the sample's pairs. No geofeat code is imported: it runs in the generator's
environment.
"""

from __future__ import annotations

import argparse
import io
import lzma
import os
import shutil
import sys
import tarfile
from pathlib import Path

#: Test pairs of the sample, by setting (folder numbers as the generator numbers them).
PAIRS = {"partial_full": [11, 21], "partial_partial": [4, 10], "full_full": [0]}
#: Keys set on top of the generator's demo_config.yaml, by setting.
SETTINGS = {
    "partial_full": {"setting": "partial_full", "template_file": "templates_tosca_demo.csv"},
    "partial_partial": {"setting": "partial_partial"},
    "full_full": {"setting": "full_full"},
}
ARCHIVE = "becos_sample.tar.xz"
MTIME = 1795564800  # 2026-11-25, fixed so that the archive depends only on the files


def generate(generator: Path, setting: str, pairs: list[int]) -> Path:
    """Write the listed test pairs of ``setting``; returns the generator's output folder of the setting."""
    import yaml  # the generator's environment

    sys.path.insert(0, str(generator))
    import main as generator_main
    from datasets.shape_dataset import build_datasets, get_splits
    from preprocessing.corres_graph import build_adjacency_graph
    from preprocessing.load_shape_pairs import save_corres_for_shape_pair

    with open(generator / "config" / "demo_config.yaml") as handle:
        config = yaml.safe_load(handle)
    config.update(SETTINGS[setting])
    path = generator / "config" / f"demo_config_sample_{setting}.yaml"
    with open(path, "w") as handle:
        yaml.safe_dump(config, handle, sort_keys=False)
    config, data_dir = generator_main.prepare_config(str(path))  # seeds, makes output/<setting>/
    train_pairs, test_pairs, val_pairs = get_splits(config, build_datasets(config))
    graph = build_adjacency_graph(plot_graph=False)
    for k in pairs:
        shape_x, shape_y = test_pairs[k]
        print(f"{setting} test {k}: {shape_x['name']} and {shape_y['name']}", flush=True)  # noqa: T201 (a script)
        save_corres_for_shape_pair(
            shape_x, shape_y, config, graph, data_dir, split="test", pair_id=k, split_folder=config["test_dir"]
        )
    return Path(config["output_dir"])


def archive(staging: Path, target: Path) -> None:
    """A tar.xz of ``staging`` whose bytes depend only on the files (sorted, fixed owner and times)."""
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w", format=tarfile.PAX_FORMAT) as tar:
        for path in sorted(staging.rglob("*")):
            info = tar.gettarinfo(str(path), arcname=path.relative_to(staging).as_posix())
            info.uid = info.gid = 0
            info.uname = info.gname = ""
            info.mtime = MTIME
            info.mode = 0o755 if path.is_dir() else 0o644
            if path.is_file():
                with open(path, "rb") as handle:
                    tar.addfile(info, handle)
            else:
                tar.addfile(info)
    target.write_bytes(lzma.compress(buffer.getvalue(), preset=9 | lzma.PRESET_EXTREME))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--generator", default=".", help="the generator's folder (default: the current folder)")
    parser.add_argument("--out", required=True, help="where becos_sample.tar.xz goes (tests/data/becos_sample)")
    parser.add_argument("--keep", help="also keep the sample's files, unpacked, in this folder")
    args = parser.parse_args()
    generator = Path(args.generator).resolve()
    os.chdir(generator)  # the configuration's data_dir is relative to it
    staging = Path(args.keep).resolve() if args.keep else Path(args.out).resolve() / "_staging"
    shutil.rmtree(staging, ignore_errors=True)
    for setting, pairs in PAIRS.items():
        output = generate(generator, setting, pairs)
        (staging / setting / "logs").mkdir(parents=True)
        shutil.copy2(output / "logs" / "config.yaml", staging / setting / "logs" / "config.yaml")
        for k in pairs:
            shutil.copytree(output / "test" / str(k), staging / setting / "test" / str(k))
    archive(staging, Path(args.out).resolve() / ARCHIVE)
    if not args.keep:
        shutil.rmtree(staging)
    print(f"wrote {Path(args.out).resolve() / ARCHIVE}")  # noqa: T201 (a script)


if __name__ == "__main__":
    main()

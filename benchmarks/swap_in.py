"""geofeat's WKS inside the ULRSSM reference code: its own network, map extraction and metric, its input swapped.

The authors' repository (``dongliangcao/Unsupervised-Learning-of-Robust-Spectral-Shape-Matching``)
is imported from ``--repo`` at run time; nothing of it is copied into geofeat and none of its
files is edited. The harness builds its FAUST_r test pipeline the way its ``test.py`` does
with ``options/test/faust.yaml`` (its ``PairFaustDataset``, its ``FMNetModel`` with the
release checkpoint, its ``validate_single`` map extraction, its ``calculate_geodesic_error``)
and runs every test pair twice:

(a) unchanged: its DiffusionNet computes the WKS input itself (``compute_wks_autoscale`` on
    its cached operators), as in the authors' runs;
(b) with geofeat's WKS: one forward pre-hook on its DiffusionNet passes the stored geofeat
    features of the shape through the network's own ``feats`` argument (the hook finds the
    shape by the content of its vertex array). Everything else is the same run.

Pairs: those the reference's ``PairFaustDataset`` forms in the test phase, every ordered pair
(x, y) of the 20 test shapes ``tr_reg_080..099``, the 20 pairs x == y included (400); the
table also gives the 190 pairs with x before y. Errors are the reference's: geodesic
distances on x from its ``dist/*.mat`` (Dijkstra on the unit-area shape), at the 5,000
template points, not multiplied by 100 by the reference (the table shows x100).

The data folder the reference reads is staged under ``--work`` from ``--data-root`` (the
shared data is never written): the 100 ``off`` files and the 100 ``corres/tr_reg_XXX.vts``
files (not ``.sym.vts`` nor ``sampleID.vts``, which the reference's FAUST_r folder does not
hold and its ``*.vts`` listing would pick up); the reference's own ``preprocess.py``
centres and scales them to unit area in place and writes the geodesic matrices of the 20
test shapes. Its ``SingleFaustDataset`` counts 100 ``dist`` files but reads those of the test
shapes only, so the 80 training shapes get empty placeholder files (no 80 x 200 MB matrices).

geofeat's features: ``--features DIR`` holds ``<shape>.npy`` (float32, (V, 128)), for example
written by ``geofeat extract --descriptor wks --param n_eig=128 --param n_descr=128
--param laplacian=cotan --param normalize=true --data WORK/FAUST_r/off --export npy --layout
mirror --export-to DIR``; without ``--features`` the harness computes them with
``geofeat.compute`` with the parameters of the ``reference`` preset of geofeat's ULRSSM head
on the staged (unit-area) meshes and saves them in that layout.

    python -m benchmarks.swap_in --repo PATH/TO/Unsupervised-Learning-of-Robust-Spectral-Shape-Matching

Needs the reference's requirements (open3d, PyYAML, scikit-learn, networkx, trimesh,
potpourri3d, robust-laplacian) next to geofeat. Its ``datasets`` package imports
``torchvision.transforms`` for image transforms that the FAUST_r dataset does not use: when
torchvision cannot be imported, the harness registers an empty stand-in module. Its
``BaseModel`` reads ``resume_state`` with a plain ``torch.load``, which cannot map the
CUDA-saved release checkpoint onto a CPU-only machine: the harness reads it with
``map_location`` and hands it to the model's own ``resume_model(..., net_only=True)`` (what its
``__init__`` does with ``resume: false``), then checks every weight.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import shutil
import subprocess
import sys
import time
import types
from pathlib import Path

import numpy as np
import torch

import geofeat
from benchmarks.common import DEFAULT_DATA, REPO, data_folder, machine
from benchmarks.parity.common import reference_import
from geofeat.adapters.ulrssm import ULRSSMHead
from geofeat.apps.extract import save_npy

TEST_SHAPES = [f"tr_reg_{i:03d}" for i in range(80, 100)]
ALL_SHAPES = [f"tr_reg_{i:03d}" for i in range(100)]
#: geofeat's parameters that match the reference's WKS (the ULRSSM head's ``reference`` preset).
WKS_PARAMS = dict(ULRSSMHead.PRESETS["reference"]["descriptor_params"])


def stage_faust_r(repo: Path, data_root: Path, work: Path) -> Path:
    """The FAUST_r folder the reference reads, staged in ``work`` by the reference's own ``preprocess.py``.

    Returns the staged folder (``work/FAUST_r`` with ``off``, ``corres``, ``dist``; the
    reference adds ``diffusion``). Done once: a finished stage is marked by ``.staged``.
    """
    target = work / "FAUST_r"
    if (target / ".staged").is_file():
        return target
    source = data_root / "FAUST_r"
    if not (source / "off").is_dir():
        raise SystemExit(f"swap_in: {source / 'off'} not found; pass --data-root, the folder that holds FAUST_r")
    if target.exists():
        shutil.rmtree(target)
    test_only = work / "FAUST_r_test_only"  # preprocess.py works on a whole folder: the test shapes get distances
    shutil.rmtree(test_only, ignore_errors=True)
    for folder, names in ((target, ALL_SHAPES[:80]), (test_only, TEST_SHAPES)):
        (folder / "off").mkdir(parents=True)
        for name in names:
            shutil.copyfile(source / "off" / f"{name}.off", folder / "off" / f"{name}.off")
    (target / "corres").mkdir()
    for name in ALL_SHAPES:
        shutil.copyfile(source / "corres" / f"{name}.vts", target / "corres" / f"{name}.vts")
    for folder, flags in ((target, ["--no_dist"]), (test_only, [])):
        command = [sys.executable, "preprocess.py", "--data_root", str(folder), "--no_eig", *flags]
        print("staging:", " ".join(command), flush=True)
        subprocess.run(command, cwd=repo, check=True, stdout=subprocess.DEVNULL)
    (target / "dist").mkdir(exist_ok=True)
    for name in TEST_SHAPES:
        shutil.move(test_only / "off" / f"{name}.off", target / "off" / f"{name}.off")
        shutil.move(test_only / "dist" / f"{name}.mat", target / "dist" / f"{name}.mat")
    for name in ALL_SHAPES[:80]:
        (target / "dist" / f"{name}.mat").touch()  # counted by SingleFaustDataset, never read in the test phase
    shutil.rmtree(test_only)
    (target / ".staged").touch()
    return target


def geofeat_features(staged: Path, features: Path | None) -> Path:
    """Folder of geofeat's WKS, ``<shape>.npy`` per test shape; computed into ``staged/wks`` when not given.

    Computed on every run (20 shapes, seconds): files left by an earlier run may come from
    another geofeat version or other settings, and nothing in them says which.
    """
    if features is not None:
        missing = [n for n in TEST_SHAPES if not (features / f"{n}.npy").is_file()]
        if missing:
            raise SystemExit(f"swap_in: {features} lacks {len(missing)} feature files, e.g. {missing[0]}.npy")
        return features
    folder = staged / "wks"
    folder.mkdir(exist_ok=True)
    for name in TEST_SHAPES:
        mesh = geofeat.load_mesh(staged / "off" / f"{name}.off")
        save_npy(folder / f"{name}.npy", geofeat.compute(mesh, "wks", cache=False, **WKS_PARAMS))  # atomic
    return folder


def vertex_key(verts: torch.Tensor) -> str:
    """Content key of one vertex array (V, 3) as the reference's network receives it."""
    return hashlib.sha1(verts.detach().cpu().float().contiguous().numpy().tobytes()).hexdigest()


class StoredFeatures:
    """Forward pre-hook that feeds DiffusionNet stored features through its own ``feats`` argument.

    ``net.register_forward_pre_hook(StoredFeatures(...), with_kwargs=True)`` is the whole
    swap: the reference's forward then skips its WKS and uses ``feats`` ((1, V, C) float32).
    Shapes are found by the content of the vertex array the network gets.
    """

    def __init__(self) -> None:
        self.by_key: dict[str, torch.Tensor] = {}
        self.calls = 0

    def add(self, verts: torch.Tensor, features: np.ndarray) -> None:
        """Register the features (V, C) of the shape whose vertices (V, 3) are ``verts``."""
        self.by_key[vertex_key(verts)] = torch.from_numpy(np.ascontiguousarray(features, dtype=np.float32))

    def __call__(self, module, args, kwargs):
        verts = args[0] if args else kwargs["verts"]
        feats = self.by_key.get(vertex_key(verts[0]))
        if feats is None:
            raise RuntimeError("swap_in: the network got a shape whose geofeat features were not registered")
        self.calls += 1
        return args, {**kwargs, "feats": feats[None].to(verts.device)}


def _torchvision_stand_in() -> None:
    """An empty ``torchvision.transforms`` when torchvision cannot be imported (the FAUST_r path never uses it)."""
    try:
        import torchvision.transforms  # noqa: F401
    except Exception:  # missing, or a build that does not match this torch
        for name in [m for m in sys.modules if m == "torchvision" or m.startswith("torchvision.")]:
            del sys.modules[name]
        package, transforms = types.ModuleType("torchvision"), types.ModuleType("torchvision.transforms")
        package.transforms = transforms
        sys.modules["torchvision"], sys.modules["torchvision.transforms"] = package, transforms
        print("note: torchvision not importable here; an empty torchvision.transforms stands in (unused by FAUST_r)")


def run(
    repo: Path,
    checkpoint: Path,
    data_root: Path,
    work: Path,
    features: Path | None,
    limit: int | None,
    pairs_kind: str = "all",
    out: Path | None = None,
) -> dict:
    """Both runs over the test pairs; a dict of per-pair and summary results (also written to ``out`` as it goes)."""
    work.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    staged = stage_faust_r(repo, data_root, work)
    feature_dir = geofeat_features(staged, features)
    staging_s = time.perf_counter() - start
    _torchvision_stand_in()
    with reference_import(repo) as load:
        options, datasets, models = load("utils.options"), load("datasets"), load("models")
        geometry, logger = load("utils.geometry_util"), load("utils.logger")
        tensor_util = load("utils.tensor_util")
        opt = options.parse(str(repo / "options" / "test" / "faust.yaml"), root_path=str(work), is_train=False)
        opt.update(dist=False, rank=0, world_size=1, visualize=False)
        opt["num_gpu"] = min(opt["num_gpu"], 1)
        opt["path"]["resume_state"] = None  # loaded below: its torch.load has no map_location
        dataset_opt = opt["datasets"]["test_dataset"]
        dataset_opt["data_root"] = str(staged)
        opt["networks"]["feature_extractor"]["cache_dir"] = str(staged / "diffusion")
        (staged / "diffusion").mkdir(exist_ok=True)
        test_set = datasets.build_dataset(dataset_opt)
        chosen = test_set
        if pairs_kind == "before":  # the pairs (i, j) of its combinations with i < j, in its order
            chosen = torch.utils.data.Subset(test_set, [k for k, (i, j) in enumerate(test_set.combinations) if i < j])
        loader = datasets.build_dataloader(chosen, dataset_opt, phase="val", num_gpu=opt["num_gpu"], dist=False)
        model = models.build_model(opt)
        # what its __init__ does with resume_state and resume: false, read onto the model's device
        model.resume_model(torch.load(checkpoint, map_location=model.device, weights_only=True), net_only=True)
        net = model.networks["feature_extractor"]
        _check_weights(net, checkpoint)
        model.eval()
        for name in ("permutation",):  # what its validation() sets before validate_single
            model.networks[name].hard = True
        geo_error = model.metrics["geo_error"]
        hook = StoredFeatures()
        timer = {"own": logger.AvgTimer(), "geofeat": logger.AvgTimer()}
        pairs, feature_rows = [], {}
        order = {Path(f).stem: i for i, f in enumerate(test_set.dataset.off_files)}
        with torch.no_grad():
            for index, data in enumerate(loader):
                if limit is not None and index >= limit:
                    break
                data_x, data_y = data["first"], data["second"]
                name_x, name_y = data_x["name"][0], data_y["name"][0]
                for item, name in ((data_x, name_x), (data_y, name_y)):
                    if name not in feature_rows:
                        feature_rows[name] = _feature_row(item, name, feature_dir, hook, geometry, net, staged)
                p2p_own = model.validate_single(data, timer["own"])[0]
                handle = net.register_forward_pre_hook(hook, with_kwargs=True)  # the swap
                try:
                    p2p_geofeat = model.validate_single(data, timer["geofeat"])[0]
                finally:
                    handle.remove()
                dist_x = tensor_util.to_numpy(data_x["dist"])
                corr_x, corr_y = tensor_util.to_numpy(data_x["corr"]), tensor_util.to_numpy(data_y["corr"])
                p2p_own, p2p_geofeat = tensor_util.to_numpy(p2p_own), tensor_util.to_numpy(p2p_geofeat)
                err_own = geo_error(dist_x, corr_x, corr_y, p2p_own, return_mean=False)
                err_geofeat = geo_error(dist_x, corr_x, corr_y, p2p_geofeat, return_mean=False)
                pairs.append(
                    {
                        "x": name_x,
                        "y": name_y,
                        "error_own": float(err_own.mean()),
                        "error_geofeat": float(err_geofeat.mean()),
                        "abs_diff": float(abs(err_own.mean() - err_geofeat.mean())),
                        "point_map_differs": float((p2p_own != p2p_geofeat).mean()),
                        "template_points_differ": float((err_own != err_geofeat).mean()),
                    }
                )
                if index % 10 == 0:
                    print(
                        f"pair {index}: {name_x} {name_y} own {err_own.mean():.6f} geofeat {err_geofeat.mean():.6f}", flush=True
                    )
                    if out is not None:  # a run stopped early still leaves what it measured
                        partial = _summary(
                            pairs,
                            feature_rows,
                            order,
                            timer,
                            staging_s,
                            time.perf_counter() - start,
                            checkpoint,
                            feature_dir,
                            work,
                            pairs_kind,
                        )
                        _write(out, partial, complete=False)
        if hook.calls != 2 * len(pairs):
            raise RuntimeError(f"swap_in: the hook fed {hook.calls} forwards, expected {2 * len(pairs)}")
    total_s = time.perf_counter() - start
    return _summary(pairs, feature_rows, order, timer, staging_s, total_s, checkpoint, feature_dir, work, pairs_kind)


def _check_weights(net: torch.nn.Module, checkpoint: Path) -> None:
    """Make sure the reference network holds the checkpoint's weights (its loader skips a missing file silently)."""
    saved = torch.load(checkpoint, map_location="cpu", weights_only=True)["networks"]["feature_extractor"]
    state = net.state_dict()
    for key, value in saved.items():
        if not torch.equal(state[key.replace("module.", "")].cpu(), value):
            raise SystemExit(f"swap_in: the reference network does not hold {checkpoint}'s weights ({key})")


def _feature_row(item: dict, name: str, feature_dir: Path, hook: StoredFeatures, geometry, net, staged: Path) -> dict:
    """Register a shape's geofeat features with the hook; compare them with the reference's own WKS of that shape."""
    ours = np.load(feature_dir / f"{name}.npy")
    verts, faces = item["verts"], item["faces"]
    hook.add(verts[0], ours)
    # the reference's WKS exactly as its DiffusionNet.forward computes it (same operators, same cache)
    _, mass, _, evals, evecs, _, _ = geometry.get_all_operators(
        verts.cpu(), faces.cpu(), k=net.k_eig, cache_dir=str(staged / "diffusion")
    )
    theirs = geometry.compute_wks_autoscale(evals, evecs, mass)[0].numpy()
    if theirs.shape != ours.shape:
        raise SystemExit(f"swap_in: {name}: geofeat features {ours.shape}, reference WKS {theirs.shape}")
    diff = np.abs(ours.astype(np.float64) - theirs)
    return {"shape": name, "max_abs": float(diff.max()), "scale": float(np.abs(theirs).max()), "mean_abs": float(diff.mean())}


def _summary(pairs, feature_rows, order, timer, staging_s, total_s, checkpoint, feature_dir, work, pairs_kind) -> dict:
    def stats(rows):
        own = np.array([r["error_own"] for r in rows])
        ours = np.array([r["error_geofeat"] for r in rows])
        return {
            "pairs": len(rows),
            "error_own_x100": 100 * float(own.mean()) if rows else None,
            "error_geofeat_x100": 100 * float(ours.mean()) if rows else None,
            "max_pair_abs_diff_x100": 100 * float(np.abs(own - ours).max()) if rows else None,
            "pairs_equal": int((own == ours).sum()),
        }

    before = [r for r in pairs if order[r["x"]] < order[r["y"]]]
    worst = max(feature_rows.values(), key=lambda r: r["max_abs"])
    return {
        "reference": "dongliangcao/Unsupervised-Learning-of-Robust-Spectral-Shape-Matching, options/test/faust.yaml",
        "checkpoint": str(checkpoint),
        "features": str(feature_dir),
        "work": str(work),
        "geofeat_params": WKS_PARAMS,
        "pairs_kind": pairs_kind,
        "all_pairs": stats(pairs),
        "x_before_y": stats(before),
        "features_max_abs_diff": worst["max_abs"],
        "features_worst_shape": worst["shape"],
        "features_relative": worst["max_abs"] / worst["scale"],
        "max_point_map_fraction_differs": max((r["point_map_differs"] for r in pairs), default=0.0),
        "seconds": {
            "total": total_s,
            "staging_and_features": staging_s,
            "map_own_avg": timer["own"].get_avg_time(),
            "map_geofeat_avg": timer["geofeat"].get_avg_time(),
        },
        "threads": torch.get_num_threads(),
        "machine": machine(),
        "date": time.strftime("%Y-%m-%d"),
        "per_pair": pairs,
        "per_shape_features": list(feature_rows.values()),
    }


def markdown(result: dict) -> str:
    """The results table."""
    lines = [
        "| pairs (reference's PairFaustDataset, test phase) | mean geodesic error x100, own WKS | geofeat's WKS | "
        "max per-pair difference x100 | pairs with equal error |",
        "|---|---|---|---|---|",
    ]
    rows = [("ordered pairs (x, y) of tr_reg_080..099, x == y included", "all_pairs"), ("of them x before y", "x_before_y")]
    if result.get("pairs_kind") == "before":
        rows = [("pairs (x, y) of tr_reg_080..099 with x before y", "x_before_y")]
    for label, key in rows:
        s = result[key]
        if s["pairs"]:
            lines.append(
                f"| {label}: {s['pairs']} | {s['error_own_x100']:.5f} | {s['error_geofeat_x100']:.5f} | "
                f"{s['max_pair_abs_diff_x100']:.2g} | {s['pairs_equal']} of {s['pairs']} |"
            )
    sec = result["seconds"]
    lines += [
        "",
        f"Features: max abs difference {result['features_max_abs_diff']:.3g} (relative {result['features_relative']:.2e}, "
        f"{result['features_worst_shape']}); point maps differ at most at "
        f"{100 * result['max_point_map_fraction_differs']:.3f}% of the vertices of a pair.",
        f"Time: {sec['total']:.0f} s in all ({sec['staging_and_features']:.0f} s staging and features), "
        f"{sec['map_own_avg']:.2f} s / {sec['map_geofeat_avg']:.2f} s per pair for the reference's map extraction "
        f"(own WKS / geofeat's WKS); {result['machine']}, {result['threads']} torch thread(s), {result['date']}.",
    ]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repo", type=Path, default=None, help="your clone of the ULRSSM reference repository")
    parser.add_argument("--checkpoint", type=Path, default=REPO.parent / "shared" / "checkpoints" / "ulrssm" / "faust_scape.pth")
    parser.add_argument(
        "--data-root", type=Path, default=DEFAULT_DATA, help="the folder holding the datasets (default $GEOFEAT_DATA)"
    )
    parser.add_argument("--features", type=Path, default=None, help="folder of <shape>.npy geofeat features (default: computed)")
    parser.add_argument(
        "--work", type=Path, default=Path("/tmp/geofeat_swap_in"), help="staging folder (the reference writes here)"
    )
    parser.add_argument(
        "--pairs",
        choices=("all", "before"),
        default="all",
        help="all: the 400 ordered pairs of its PairFaustDataset; before: its 190 pairs with x before y",
    )
    parser.add_argument("--limit", type=int, default=None, help="only the first N of those pairs")
    parser.add_argument("--out", type=Path, default=None, help="write results.md and results.json here")
    parser.add_argument(
        "--render-only", action="store_true", help="rewrite OUT/results.md from OUT/results.json, running nothing"
    )
    args = parser.parse_args(argv)
    if args.render_only:
        if args.out is None or not (args.out / "results.json").is_file():
            parser.error("--render-only needs --out, a folder holding the results.json of an earlier run")
        record = json.loads((args.out / "results.json").read_text())
        _write(args.out, record, complete=record.get("complete", False))
        return 0
    if args.repo is None:
        parser.error("--repo is required (your clone of the ULRSSM reference repository)")
    repo = args.repo.resolve()
    if not (repo / "options" / "test" / "faust.yaml").is_file():
        raise SystemExit(f"swap_in: {repo} is not a clone of the ULRSSM reference repository (no options/test/faust.yaml)")
    if not args.checkpoint.is_file():
        raise SystemExit(f"swap_in: checkpoint {args.checkpoint} not found; pass --checkpoint PATH/faust_scape.pth")
    result = run(
        repo,
        args.checkpoint.resolve(),
        data_folder(args.data_root, "--data-root").resolve(),
        args.work.resolve(),
        args.features,
        args.limit,
        args.pairs,
        args.out,
    )
    print(markdown(result))
    if args.out is not None:
        _write(args.out, result, complete=True)
    return 0


def _write(out: Path, result: dict, complete: bool) -> None:
    out.mkdir(parents=True, exist_ok=True)
    result = {**result, "complete": complete}
    head = "ULRSSM's own test pipeline, release checkpoint, its WKS vs geofeat's WKS:\n\n" + (
        "" if complete else "(partial: run in progress)\n\n"
    )
    (out / "results.md").write_text(head + markdown(result))
    (out / "results.json").write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    with contextlib.suppress(BrokenPipeError):
        sys.exit(main())

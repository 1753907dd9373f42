import argparse
import importlib.metadata
import subprocess
import sys
from pathlib import Path

import pytest

import geofeat
from geofeat.apps import cli
from geofeat.apps.cli import build_parser, main, numpydoc_parameters
from geofeat.descriptors.registry import descriptor_entry


def test_demo_runs_offline_wks_beats_hks_and_draws_no_bar_off_a_terminal(tmp_path):
    """Run as a user would with stderr redirected: the table on stdout, no progress bar (nor the eigensolver's) on stderr."""
    result = subprocess.run(
        [sys.executable, "-m", "geofeat", "demo", "--cache-dir", str(tmp_path)], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-3000:]
    rows = {line.split()[0]: line.split() for line in result.stdout.splitlines() if line.strip().startswith(("hks", "wks"))}
    assert set(rows) == {"hks", "wks"}
    assert float(rows["wks"][-1]) < float(rows["hks"][-1])  # WKS localises better than 16-channel HKS
    assert float(rows["wks"][-1]) < 10.0
    assert "\r" not in result.stderr and "it/s" not in result.stderr and "eigenpairs of" not in result.stderr


def _parsers(parser: argparse.ArgumentParser, name: str = "geofeat"):
    """The parser and every sub-command's parser, each with its command line; sub-commands must have a help."""
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {choice.dest: choice.help for choice in action._choices_actions}
            for sub_name, sub in action.choices.items():
                assert helps.get(sub_name), f"{name} {sub_name} has no help line"
                yield from _parsers(sub, f"{name} {sub_name}")


def test_every_option_of_every_command_has_a_plain_text_help():
    seen = []
    for name, parser in _parsers(build_parser()):
        seen.append(name)
        assert parser.description, f"{name} has no description"
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                continue
            assert action.help and action.help.strip(), f"{name} {'/'.join(action.option_strings) or action.dest}: no help"
        text = parser.format_help()  # also fails on a stray % in a help string
        assert "``" not in text and "`" not in text, f"{name} --help shows markup"
    assert {"geofeat", "geofeat cache", "geofeat descriptors", "geofeat demo", "geofeat extract"} <= set(seen)
    assert "geofeat train-geolora" in seen
    demo = dict(_parsers(build_parser()))["geofeat demo"].format_help()
    assert "--seed SEED" in demo and "seed of the synthetic shapes" in demo


def test_train_flags_take_their_help_from_the_settings_docstring():
    train = dict(_parsers(build_parser()))["geofeat train-geolora"]
    helps = {}
    for action in train._actions:  # --data's own help, not its --dataset alias's
        helps.setdefault(action.dest, action.help)
    assert helps["rank"].startswith("LoRA rank") and helps["rank"].endswith("(default 16)")
    assert "checkpoints/step_NNNNNNN/" in helps["out"] and "``" not in helps["out"]
    assert helps["camera_layout"] == "one of official, uniform (default official)"
    assert "required" in helps["data"]
    args = build_parser().parse_args(["train-geolora", "--dataset", "becos", "--data-root", "/data", "--recipe", "reference"])
    assert (args.data, args.data_root, args.recipe) == ("becos", "/data", "reference")
    doc = """Settings.

    Parameters
    ----------
    a, b : int
        Two ``numbers`` with `refs`.
    mode : {"x", "y"}

    Returns
    -------
    int
    """
    assert numpydoc_parameters(doc) == {"a": "Two numbers with refs.", "b": "Two numbers with refs.", "mode": "one of x, y"}


@pytest.fixture
def no_dino_weights(monkeypatch):
    for name in ("GEOFEAT_DINOV2_WEIGHTS", "GEOFEAT_DINOV3_WEIGHTS"):
        monkeypatch.delenv(name, raising=False)


def descriptor_listing(capsys) -> dict[str, str]:
    """``geofeat descriptors`` as {name: its block of lines}."""
    assert main(["descriptors"]) == 0
    blocks: dict[str, str] = {}
    name = None
    for line in capsys.readouterr().out.splitlines():
        if line and not line[0].isspace() and not line.startswith("ready:"):
            name = line.split()[0]
            blocks[name] = ""
        if name is not None and line:
            blocks[name] += line + "\n"
    return blocks


def test_descriptors_say_what_each_needs_and_call_ready_only_what_runs_here(capsys, no_dino_weights):
    blocks = descriptor_listing(capsys)
    assert set(blocks) >= {"hks", "wks", "dinov2", "dinov3", "geolora"}
    for name in ("hks", "wks"):
        assert blocks[name].startswith(f"{name:<10}ready:") and "extra:   none" in blocks[name]
    dino_installed = not descriptor_entry("dinov2").missing()
    for name, variable in (
        ("dinov2", "GEOFEAT_DINOV2_WEIGHTS"),
        ("dinov3", "GEOFEAT_DINOV3_WEIGHTS"),
        ("geolora", "GEOFEAT_DINOV3_WEIGHTS"),
    ):
        block = " ".join(blocks[name].split())  # unwrapped
        assert blocks[name].startswith(f"{name:<10}not ready:"), blocks[name]
        assert "pip install 'geofeat[dino]'" in block and ("(installed)" in block) == dino_installed
        assert f"weights: missing: ${variable} is not set" in block
    assert "hf download facebook/dinov2-base" in " ".join(blocks["dinov2"].split())
    assert "facebook/dinov3-vitb16-pretrain-lvd1689m" in blocks["dinov3"] and "licence" in blocks["dinov3"]
    assert "https://github.com/vikiehm/geo-lora" in blocks["geolora"] and "checkpoint=" in blocks["geolora"]
    assert "geofeat train-geolora" in blocks["geolora"]


def test_dino_weights_are_found_from_the_environment_without_loading_them(capsys, monkeypatch, tmp_path):
    folder = tmp_path / "dinov2-base"
    folder.mkdir()
    (folder / "config.json").write_text("{}")
    (folder / "model.safetensors").write_bytes(b"")  # only looked at, never read
    monkeypatch.setenv("GEOFEAT_DINOV2_WEIGHTS", str(folder))
    monkeypatch.setenv("GEOFEAT_DINOV3_WEIGHTS", str(tmp_path / "nothing-here.pth"))
    assert cli.weights_status("dinov2") == (True, f"$GEOFEAT_DINOV2_WEIGHTS={folder} (a model folder)")
    found, why = cli.weights_status("dinov3")
    assert not found and why.endswith("does not exist")
    blocks = descriptor_listing(capsys)
    dino_installed = not descriptor_entry("dinov2").missing()
    assert blocks["dinov2"].startswith("dinov2    ready:" if dino_installed else "dinov2    not ready:")
    assert blocks["dinov3"].startswith("dinov3    not ready:") and blocks["geolora"].startswith("geolora   not ready:")

    (folder / "model.safetensors").unlink()
    assert cli.weights_status("dinov2")[0] is False  # a folder without weights
    (tmp_path / "notes.txt").write_text("x")
    monkeypatch.setenv("GEOFEAT_DINOV2_WEIGHTS", str(tmp_path / "notes.txt"))
    assert cli.weights_status("dinov2") == (
        False,
        f"$GEOFEAT_DINOV2_WEIGHTS={tmp_path / 'notes.txt'} is a .txt file, not a .pth/.pt or a model folder",
    )


def test_a_hub_id_counts_only_when_it_is_in_the_local_hugging_face_cache(monkeypatch, tmp_path):
    constants = pytest.importorskip("huggingface_hub.constants")
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path))
    monkeypatch.setenv("GEOFEAT_DINOV2_WEIGHTS", "facebook/dinov2-base")
    found, why = cli.weights_status("dinov2")
    assert not found and "not in the local Hugging Face cache" in why
    repo = tmp_path / "models--facebook--dinov2-base"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text("0123abcd")
    (repo / "snapshots" / "0123abcd").mkdir(parents=True)
    (repo / "snapshots" / "0123abcd" / "config.json").write_text("{}")
    assert cli.weights_status("dinov2") == (
        True,
        "$GEOFEAT_DINOV2_WEIGHTS=facebook/dinov2-base (a Hub id, in the local Hugging Face cache)",
    )


def test_console_script_help():
    console_script = Path(sys.executable).parent / "geofeat"  # installed beside the interpreter, on PATH or not
    result = subprocess.run([str(console_script), "--help"], capture_output=True, text=True)
    assert result.returncode == 0 and "cache" in result.stdout and "``" not in result.stdout


def test_version_prints_the_installed_version():
    console_script = Path(sys.executable).parent / "geofeat"
    result = subprocess.run([str(console_script), "--version"], capture_output=True, text=True)
    assert result.returncode == 0
    assert result.stdout.strip() == f"geofeat {importlib.metadata.version('geofeat')}" == f"geofeat {geofeat.__version__}"


@pytest.mark.parametrize(
    ("args", "problem"),
    [
        (["--descriptor", "no_such_descriptor", "--data", "{data}"], "unknown descriptor 'no_such_descriptor'"),
        (["--descriptor", "hks", "--param", "n_eig", "--data", "{data}"], "--param expects KEY=VALUE"),
        (["--descriptor", "hks", "--data", "{missing}"], "data folder {missing} does not exist"),
    ],
    ids=["unknown-descriptor", "param-without-value", "missing-data-folder"],
)
def test_errors_are_reported_without_traceback(tmp_path, args, problem):
    """Bad input to ``geofeat extract`` (a GeofeatError) exits with status 2 and one ``geofeat: error:`` line on stderr."""
    data, missing = tmp_path / "data", tmp_path / "no-such-folder"
    data.mkdir()
    (data / "a.off").write_text("OFF\n3 1 0\n0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    argv = [a.format(data=data, missing=missing) for a in args]
    problem = problem.format(missing=missing)
    result = subprocess.run(
        [sys.executable, "-m", "geofeat", "extract", *argv, "--out", str(tmp_path / "store"), "--no-progress"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 2, (result.returncode, result.stdout[-2000:], result.stderr[-2000:])
    assert "Traceback" not in result.stdout + result.stderr, result.stderr[-3000:]
    lines = result.stderr.splitlines()
    assert len(lines) == 1, result.stderr  # the error and nothing else
    line = lines[0]
    assert line.startswith("geofeat: error: ") and problem in line, line
    assert result.stdout == "" and not (tmp_path / "store").exists()  # refused before any work


# ----------------------------------------------------------------------------- geofeat data check


def _shared_sample(folder: str, probe: str) -> Path:
    """A shared real sample (``$GEOFEAT_DATA``, else ../shared/data); fails, never skips, when it is absent."""
    from shapes import DATA_ENV, data_root

    root = data_root() / folder
    if not (root / probe).is_file():
        pytest.fail(
            f"shared sample {folder} not found at {root}; set {DATA_ENV} (see the README, section 'Test').", pytrace=False
        )
    return root


@pytest.fixture(scope="module")
def psmal_sample() -> Path:
    return _shared_sample("PSMAL_sample", "PARTIALSMAL/train/maps/cuts_0_cow_02_cuts_22_dog_05.vts")


def data_check(capsys, *args: str) -> tuple[int, list[str]]:
    """``geofeat data check ARGS`` in this process: its exit status and the lines it printed."""
    status = main(["data", "check", *args, "--no-progress"])
    return status, capsys.readouterr().out.splitlines()


def test_data_check_on_the_psmal_sample(capsys, psmal_sample):
    status, lines = data_check(capsys, "psmal", "--data-root", str(psmal_sample), "--split", "train")
    assert status == 0, lines
    assert lines[0] == "dataset: psmal (PARTIALSMAL, P2P), split train"
    assert lines[1] == f"folder: {psmal_sample / 'PARTIALSMAL' / 'train'}"
    assert "pairs: 3 (P2P), 3 read" in lines
    assert "shapes: 6 distinct, 2,676 to 2,954 vertices as y (source), 2,408 to 2,685 as x (target)" in lines
    assert any(line.startswith("direction: map_yx gives, for each vertex of y") for line in lines)
    assert "reverse pairs: 0 of 3 pairs have their reverse (x->y) in the dataset" in lines  # one direction per map
    assert "no counterpart (-1): 58.1% of the vertices of y overall, per pair 34.8% to 70.6%" in lines
    assert "files read: 9" in lines and lines[-1] == "result: clean"
    assert not any(line.startswith(("problems", "note:")) for line in lines)


def test_data_check_on_the_shrec16_dpfm_sample_reports_the_dropped_faces(capsys):
    root = _shared_sample("SHREC16_dpfm_sample", "shrec_partial_test/maps/cuts-cat1_cuts-cat.map")
    status, lines = data_check(capsys, "shrec16_cuts", "--data-root", str(root))
    assert status == 0, lines
    assert f"folder: {root / 'shrec_partial_test'}" in lines
    assert "pairs: 1 (P2F), 1 read" in lines
    assert any("vertices of x from 46 to 9,998" in line for line in lines)
    assert "warning: mesh 'cuts-cat': dropped 12 repeated face(s) (the same three vertices as an earlier face)" in lines
    assert lines[-1] == "result: clean"


def test_data_check_on_faust_r_lists_the_files_the_test_split_does_not_read(capsys, faust_dir):
    status, lines = data_check(capsys, "faust_r", "--data-root", str(faust_dir.parent))
    assert status == 0, lines
    assert "pairs: 380 (F2F), 380 read" in lines
    assert "reverse pairs: 380 of 380 pairs have their reverse (x->y) in the dataset" in lines
    assert "also given: overlap_y in 0, overlap_x in 0, map_yx_sym in 380, template points in 380 of 380 pairs" in lines
    assert any(line.startswith("note: not read: 80 file(s) in off/ (*.off): tr_reg_000.off") for line in lines)
    assert lines[-1] == "result: clean"


def test_data_check_lists_what_is_wrong_and_exits_1(capsys, psmal_sample, tmp_path):
    import shutil

    folder = tmp_path / "PARTIALSMAL" / "train"
    shutil.copytree(psmal_sample / "PARTIALSMAL" / "train", folder)
    maps = folder / "maps"
    (maps / "cuts_0_cow_02_cuts_22_dog_05.vts").write_text("0\n" * 2806)  # one line short
    (maps / "cuts_0_cow_04_cuts_14_lion_04.vts").write_text("2685\n" * 2676)  # lion_04 has 2,685 vertices
    status, lines = data_check(capsys, "psmal", "--data-root", str(tmp_path), "--split", "train")
    assert status == 1 and "pairs: 3 (P2P), 1 read" in lines and lines[-1] == "result: 2 problem(s); see above"
    problems = lines[lines.index("problems: 2") + 1 :]
    assert problems[0].startswith("  - cuts_0_cow_02->cuts_22_dog_05: cannot be read:") and "expected 2807 entries" in problems[0]
    assert problems[1].startswith("  - cuts_0_cow_04->cuts_14_lion_04: cannot be read:") and "[0, 2684]" in problems[1]
    for stem in ("cuts_0_cow_02_cuts_9_wolf_01", "cuts_3_fox_01_cuts_22_dog_05"):  # maps whose shapes are missing
        (maps / f"{stem}.vts").write_text("0\n")
    status, lines = data_check(capsys, "psmal", "--data-root", str(tmp_path), "--split", "train")
    assert status == 1 and "problems: 1" in lines
    text = "\n".join(lines)
    assert "cannot tell which two shapes 2 of 5 map files pair" in text
    assert "        cuts_0_cow_02_cuts_9_wolf_01.vts" in lines and "        cuts_3_fox_01_cuts_22_dog_05.vts" in lines


def test_data_check_notes_files_no_pair_reads(capsys, psmal_sample, tmp_path):
    import shutil

    folder = tmp_path / "train"
    shutil.copytree(psmal_sample / "PARTIALSMAL" / "train", folder)
    shutil.copy(folder / "shapes" / "cuts_0_cow_02.off", folder / "shapes" / "cuts_5_cow_01.off")  # a shape no map names
    (folder / "maps" / "notes.txt").write_text("mine\n")
    status, lines = data_check(capsys, "psmal", "--data-root", str(folder), "--split", "train")
    assert status == 0, lines  # not wrong, only worth knowing
    assert "note: not read: 1 file(s) in maps/ (*.txt): notes.txt" in lines
    assert "note: not read: 1 file(s) in shapes/ (*.off): cuts_5_cow_01.off" in lines


def test_data_check_of_a_dataset_built_in_memory(capsys):
    status, lines = data_check(capsys, "synthetic_p2p", "--split", "test")
    assert status == 0, lines
    assert "folder: none (built in memory)" in lines and "pairs: 90 (P2P), 90 read" in lines
    assert not any(line.startswith("files read") for line in lines)


@pytest.mark.parametrize(
    ("args", "problem"),
    [
        (["no_such_dataset", "--data-root", "{data}"], "unknown dataset 'no_such_dataset'"),
        (["psmal", "--data-root", "{missing}"], "the data folder {missing} does not exist"),
        (["psmal", "--data-root", "{data}", "--option", "layout=dpfm"], "does not take option(s) layout"),
        (["psmal", "--data-root", "{data}", "--option", "layout"], "--option expects KEY=VALUE"),
    ],
    ids=["unknown-dataset", "missing-folder", "unknown-option", "option-without-value"],
)
def test_data_check_bad_input_exits_2_with_one_error_line(capsys, tmp_path, args, problem):
    missing = tmp_path / "no-such-folder"
    argv = [a.format(data=tmp_path, missing=missing) for a in args]
    assert main(["data", "check", *argv]) == 2
    captured = capsys.readouterr()
    lines = captured.err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("geofeat: error: ") and problem.format(missing=missing) in lines[0], lines
    assert captured.out == ""


def test_data_check_of_a_folder_in_no_known_layout_shows_the_layout_and_exits_1(capsys, tmp_path):
    status, lines = data_check(capsys, "cp2p24", "--data-root", str(tmp_path))
    assert status == 1
    assert f"data folder given: {tmp_path}" in lines
    assert any(line.startswith("  - geofeat cannot open it: CP2P24: cannot use") for line in lines)
    assert "    Expected layout:" in lines and any("<y>_<x>.map" in line for line in lines)


def test_data_check_is_a_documented_command():
    parsers = dict(_parsers(build_parser()))
    assert {"geofeat data", "geofeat data check"} <= set(parsers)
    text = parsers["geofeat data check"].format_help()
    assert "DATASET" in text and "--data-root PATH" in text and "--split SPLIT" in text and "Exit status 0" in text


def test_data_prepare_becos_refuses_a_folder_that_is_no_generator(capsys, tmp_path):
    """Bad input to ``geofeat data prepare becos`` is refused before anything runs: one error line, exit 2."""
    status = main(["data", "prepare", "becos", "--generator", str(tmp_path / "nothing"), "--out", str(tmp_path / "out")])
    captured = capsys.readouterr()
    assert status == 2 and captured.out == ""
    lines = captured.err.splitlines()
    assert len(lines) >= 1 and lines[0].startswith("geofeat: error: ") and "nothing" in captured.err
    assert not (tmp_path / "out").exists()
    parsers = dict(_parsers(build_parser()))
    assert "--generator PATH" in parsers["geofeat data prepare"].format_help()


def test_data_check_becos_needs_a_folder(capsys, monkeypatch):
    monkeypatch.delenv("GEOFEAT_DATA", raising=False)
    assert main(["data", "check", "becos"]) == 2
    assert "needs --data-root" in capsys.readouterr().err


@pytest.fixture(scope="module")
def becos_sample(tmp_path_factory) -> Path:
    """The generator-written BeCoS sample of tests/data, unpacked (partial_full, partial_partial, full_full test pairs)."""
    import tarfile

    archive = Path(__file__).parents[1] / "data" / "becos_sample" / "becos_sample.tar.xz"
    folder = tmp_path_factory.mktemp("becos")
    with tarfile.open(archive) as tar:
        if hasattr(tarfile, "data_filter"):  # Python 3.10.12+: refuse links and paths out of the folder
            tar.extractall(folder, filter="data")
        else:
            tar.extractall(folder)
    return folder


def test_data_check_on_the_generated_becos_sample(capsys, becos_sample):
    status, lines = data_check(capsys, "becos_p2p", "--data-root", str(becos_sample))
    assert status == 0, lines
    assert f"folder: {becos_sample / 'partial_partial' / 'test'}" in lines and "pairs: 2 (P2P), 2 read" in lines
    assert "also given: overlap_y in 2, overlap_x in 2, map_yx_sym in 0, template points in 0 of 2 pairs" in lines
    assert lines[-1] == "result: clean"
    status, lines = data_check(capsys, "becos", "--data-root", str(becos_sample), "--split", "test")
    assert status == 0, lines
    assert lines[0] == f"BeCoS generator output: {becos_sample}"
    assert any(line.startswith("partial_full/test: 2 complete pair folder(s)") for line in lines)
    assert lines[-1].startswith("result: complete")

"""prepare_becos: running a generator copy in a subprocess (a small stand-in generator here), and its configuration edits."""

import sys
import textwrap

import numpy as np
import pytest

from geofeat.apps.prepare import override_config, prepare_becos, requirement_modules
from geofeat.errors import DatasetError

CONFIG = """\
SEED: 42 # Random seed
n_jobs: -1 # processes

template_file: templates_all.csv # template file

datasets:
  faust: false # whether faust is included
  tosca: true # whether tosca is included

setting: full_full # full_full/partial_full/partial_partial
"""

# A stand-in for main.py: reads config/<name>.yaml as the real one does, prints progress, writes
# output/<setting>/test/<k>/ (map files only: enough for the runner) and fails on request.
FAKE_MAIN = textwrap.dedent(
    """\
    import argparse, os, re, sys
    import numpy as np

    parser = argparse.ArgumentParser()
    parser.add_argument("--config", default="general_config")
    args = parser.parse_args()
    here = os.path.dirname(os.path.realpath(__file__))
    text = open(os.path.join(here, "config", args.config + ".yaml")).read()
    setting = re.search(r"^setting: (\\w+)", text, re.M).group(1)
    out = os.path.join(here, "output", setting)
    if os.path.exists(out):
        os.rename(out, out + "_archived_1")
    for k in range(2):
        folder = os.path.join(out, "test", str(k))
        os.makedirs(folder)
        print(f"test - {k:03}/2 - Working on: cat0 and cat{k + 1}...", flush=True)
        np.save(os.path.join(folder, "corres_10.npy"), np.zeros(3, dtype=np.int64))
    if "fail: true" in text:
        sys.exit("ValueError: Failed to compute eigen-decomposition")
    print("Dataset was generated successfully in 0.01 minutes.")
    """
)


@pytest.fixture
def generator(tmp_path):
    root = tmp_path / "becos-code"
    (root / "config").mkdir(parents=True)
    (root / "config" / "demo_config.yaml").write_text(CONFIG)
    (root / "main.py").write_text(FAKE_MAIN)
    (root / "requirements.txt").write_text("numpy\n")  # importable by the test's Python
    return root


def test_runs_the_generator_and_moves_its_output(generator, tmp_path):
    lines = []
    out = tmp_path / "data"
    report = prepare_becos(generator, out, python=sys.executable, echo=lines.append, check=False)
    assert report.returncode == 0 and report.setting == "full_full" and report.config == "demo_config"
    assert report.command == [sys.executable, "main.py", "--config", "demo_config"]
    assert report.output == out / "full_full" and not (generator / "output" / "full_full").exists()
    assert sorted(p.name for p in (out / "full_full" / "test").iterdir()) == ["0", "1"]
    assert lines[0] == "test - 000/2 - Working on: cat0 and cat1..." and lines[-1].startswith("Dataset was generated")
    assert report.log.read_text().splitlines() == lines
    text = "\n".join(report.lines())
    assert "exit status: 0" in text and str(out / "full_full") in text
    # the output folder is taken now: refused before anything runs
    with pytest.raises(DatasetError, match="already exists and is not empty"):
        prepare_becos(generator, out, python=sys.executable)


def test_setting_and_overrides_write_a_configuration_copy(generator, tmp_path):
    report = prepare_becos(
        generator,
        tmp_path / "data",
        python=sys.executable,
        setting="partial_full",
        overrides={"template_file": "templates_tosca_demo.csv", "datasets.faust": True},
        check=False,
    )
    assert report.config == "demo_config_geofeat_partial_full" and report.setting == "partial_full"
    written = (generator / "config" / "demo_config_geofeat_partial_full.yaml").read_text()
    assert "setting: partial_full\n" in written and "template_file: templates_tosca_demo.csv\n" in written
    assert "  faust: true\n" in written and "  tosca: true # whether tosca is included\n" in written
    assert (generator / "config" / "demo_config.yaml").read_text() == CONFIG  # the user's file is untouched
    assert (tmp_path / "data" / "partial_full" / "test" / "1" / "corres_10.npy").is_file()


def test_a_failing_generator_is_reported_with_what_it_wrote(generator, tmp_path):
    report = prepare_becos(generator, tmp_path / "data", python=sys.executable, overrides={"fail": True})
    assert report.returncode == 1 and not report.ok
    assert report.last_lines[-1] == "ValueError: Failed to compute eigen-decomposition"
    assert report.output == tmp_path / "data" / "full_full"
    check = report.check
    assert check is not None and not check.ok
    (split,) = check.splits
    assert split.split == "test" and split.complete == 0
    assert split.incomplete == {"0": "lacks 0_<name>.off, 1_<name>.off, corres_01.npy", "1": split.incomplete["1"]}
    text = "\n".join(report.lines())
    assert "exit status: 1" in text and "incomplete: 2 pair folder(s)" in text and "result: " in text


def test_an_older_output_of_the_generator_is_not_taken_for_the_new_one(generator, tmp_path):
    older = generator / "output" / "full_full" / "test" / "0"
    older.mkdir(parents=True)
    report = prepare_becos(generator, generator / "output", python=sys.executable, check=False)
    assert report.output == generator / "output" / "full_full"  # in place: nothing moved
    assert (generator / "output" / "full_full_archived_1" / "test" / "0").is_dir()  # the generator's own renaming


def test_what_is_refused_before_running(generator, tmp_path):
    with pytest.raises(DatasetError, match="not a copy of the BeCoS generator"):
        prepare_becos(tmp_path, tmp_path / "data")
    with pytest.raises(DatasetError, match=r"no configuration 'general_config'.*found: demo_config"):
        prepare_becos(generator, tmp_path / "data", config="general_config")
    with pytest.raises(DatasetError, match="setting must be one of"):
        prepare_becos(generator, tmp_path / "data", setting="partial")
    (generator / "requirements.txt").write_text("PyYAML==6.0.2\nnumpy\ngeofeat-no-such-module==1.0  # not installed\n")
    with pytest.raises(DatasetError, match=r"cannot import what the BeCoS generator needs.*pip install -r"):
        prepare_becos(generator, tmp_path / "data", python=sys.executable)
    assert not (generator / "output").exists()


def test_requirement_modules(tmp_path):
    path = tmp_path / "requirements.txt"
    path.write_text("PyYAML==6.0.2\nnumpy==1.24.4\nrobust-laplacian==0.2.7\nlibigl==2.5.1\n# comment\n\nfast_simplification\n")
    assert requirement_modules(path) == ["yaml", "numpy", "robust_laplacian", "igl", "fast_simplification"]
    assert requirement_modules(tmp_path / "absent.txt") == []


def test_override_config_keeps_comments_and_order():
    text = override_config(CONFIG, {"setting": "partial_partial", "n_jobs": 1, "datasets.tosca": False, "new_key": "a b"})
    lines = text.splitlines()
    assert lines[0] == "SEED: 42 # Random seed" and lines[1] == "n_jobs: 1"
    assert "  tosca: false" in lines and "  faust: false # whether faust is included" in lines
    assert "setting: partial_partial" in lines and lines[-1] == 'new_key: "a b"'
    added = override_config(CONFIG, {"datasets.kids": True, "other.key": 3})
    at = added.splitlines().index("  tosca: true # whether tosca is included")
    assert added.splitlines()[at + 1] == "  kids: true"
    assert added.splitlines()[-2:] == ["other:", "  key: 3"]
    with pytest.raises(DatasetError, match="only 'key' or 'parent.key'"):
        override_config(CONFIG, {"a.b.c": 1})
    np.testing.assert_equal(override_config(CONFIG, {}), CONFIG)

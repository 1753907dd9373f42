import subprocess
import sys
from pathlib import Path

from geofeat.cli import main


def test_demo_runs_offline_and_wks_beats_hks(capsys):
    assert main(["demo", "--no-progress"]) == 0
    out = capsys.readouterr().out
    rows = {line.split()[0]: line.split() for line in out.splitlines() if line.strip().startswith(("hks", "wks"))}
    assert set(rows) == {"hks", "wks"}
    assert float(rows["wks"][-1]) < float(rows["hks"][-1])  # WKS localises better than 16-channel HKS
    assert float(rows["wks"][-1]) < 10.0


def test_descriptors_listing_and_console_script(capsys):
    assert main(["descriptors"]) == 0
    assert "wks        available" in capsys.readouterr().out
    console_script = Path(sys.executable).parent / "geofeat"  # installed beside the interpreter, on PATH or not
    result = subprocess.run([str(console_script), "--help"], capture_output=True, text=True)
    assert result.returncode == 0 and "cache" in result.stdout


def test_errors_are_reported_without_traceback(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "geofeat.cli", "cache", "info", "--dir", str(tmp_path)], capture_output=True, text=True
    )
    assert result.returncode == 0

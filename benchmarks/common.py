"""Helpers shared by the benchmark scripts: their folders, the data folder, the machine description, the FAUST_r shapes, writing results."""

from __future__ import annotations

import json
import os
import subprocess
from collections.abc import Callable
from pathlib import Path

import geofeat
from geofeat.apps.machine import machine  # noqa: F401  (re-exported: the scripts take it from here)
from geofeat.datasets.base import DATA_ENV

#: The benchmark scripts' folder, where their results land, and the repository.
BENCHMARKS = Path(__file__).resolve().parent
RESULTS = BENCHMARKS / "results"
REPO = BENCHMARKS.parent
#: The default of the scripts' data option: ``$GEOFEAT_DATA``, the library's setting (None when it is not set).
DEFAULT_DATA = os.environ.get(DATA_ENV)
#: Environment variable of the reference scripts' ``--data-ext`` (the folder holding PSMAL/ and BeCoS/), and its value.
DATA_EXT_ENV = "GEOFEAT_DATA_EXT"
DEFAULT_DATA_EXT = os.environ.get(DATA_EXT_ENV)


def data_folder(
    given: str | os.PathLike | None,
    option: str = "--data",
    variable: str = DATA_ENV,
    holds: str = "FAUST_r/ and the other datasets",
) -> Path:
    """The folder of a script's data option ``option`` (default: ``$variable``).

    Raises
    ------
    SystemExit
        With a message that says what to pass (``option``, the folder that ``holds`` ...) or
        which variable to set, when no folder is given.
    """
    if not given:
        raise SystemExit(f"no data folder: pass {option} (the folder that holds {holds}) or set ${variable}")
    return Path(given).expanduser()


def faust_test_shapes(data: str | os.PathLike | None, n_shapes: int) -> list[geofeat.Mesh]:
    """The first ``n_shapes`` FAUST_r test shapes (tr_reg_080 on) of the ``--data`` folder; exits with a clear message when missing."""
    folder = data_folder(data) / "FAUST_r" / "off"
    paths = [folder / f"tr_reg_{i:03d}.off" for i in range(80, 80 + n_shapes)]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise SystemExit(f"FAUST_r shapes not found (first missing: {missing[0]}); pass --data or set GEOFEAT_DATA")
    return [geofeat.load_mesh(p) for p in paths]


def commit_date(path: str | os.PathLike) -> str | None:
    """The date (YYYY-MM-DD) of the last commit that changed ``path``: when a run that kept no date was recorded.

    None outside a git checkout, or for a file git does not track.
    """
    path = Path(path).resolve()
    try:
        done = subprocess.run(
            ["git", "-C", str(path.parent), "log", "-1", "--format=%ad", "--date=short", "--", path.name],
            capture_output=True,
            text=True,
            check=False,
        )
    except OSError:
        return None
    if done.returncode != 0:
        return None
    return done.stdout.strip() or None


def write_results(out: str | os.PathLike, result: dict, table: str) -> None:
    """Write ``OUT.json`` (the result record) and ``OUT.md`` (its table), creating the folder; print the table."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=2) + "\n")
    out.with_suffix(".md").write_text(table + "\n")
    print(table)


def read_results(out: str | os.PathLike) -> dict:
    """The result record ``OUT.json`` that `write_results` wrote."""
    return json.loads(Path(out).with_suffix(".json").read_text())


def rewrite_table(out: str | os.PathLike, table: Callable[[dict], str]) -> None:
    """Rewrite ``OUT.md`` from ``OUT.json`` with ``table`` (record -> Markdown), running nothing."""
    Path(out).with_suffix(".md").write_text(table(read_results(out)) + "\n")


#: CUDA runtime calls that make the host wait for the device, and those that launch a kernel.
HOST_WAITS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize")
LAUNCHES = ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernelEx")


def profile_tables(prof, wall: float, top: int = 15) -> tuple[dict, list[str]]:
    """Kernel time against wall time, and the costliest kernels and host operations, of a torch.profiler run.

    Parameters
    ----------
    prof : torch.profiler.profile
        Finished, with CPU (and CUDA) activity.
    wall : float
        Wall seconds of the profiled work.
    top : int
        Rows of each table.

    Returns
    -------
    summary : dict
        ``wall_s``, ``kernel_s`` (the device's time in kernels), ``kernel_launches``,
        ``host_waits`` (synchronisations of the host with the device) and ``host_op_s``
        (the host's time in its operations, the profiler's self CPU time).
    lines : list of str
        Two Markdown tables: kernels by device time, host operations by self CPU time.
    """
    import torch

    events = list(prof.key_averages())
    kernels = [e for e in events if e.device_type == torch.autograd.DeviceType.CUDA]
    host = [e for e in events if e.device_type == torch.autograd.DeviceType.CPU]
    kernel_us = sum(e.self_device_time_total for e in kernels)
    host_us = sum(e.self_cpu_time_total for e in host)
    summary = {
        "wall_s": wall,
        "kernel_s": kernel_us / 1e6,
        "kernel_launches": sum(e.count for e in host if e.key in LAUNCHES),
        "host_waits": sum(e.count for e in host if e.key in HOST_WAITS),
        "host_op_s": host_us / 1e6,
    }

    def short(name: str) -> str:
        return name if len(name) <= 90 else name[:87] + "..."

    lines = ["| kernel | calls | device time | share of kernel time |", "|---|---|---|---|"]
    for event in sorted(kernels, key=lambda e: -e.self_device_time_total)[:top]:
        share = event.self_device_time_total / kernel_us if kernel_us else 0.0
        lines.append(f"| `{short(event.key)}` | {event.count} | {event.self_device_time_total / 1000:.2f} ms | {share:.0%} |")
    lines += ["", "| host operation | calls | host time (self) | share of host time |", "|---|---|---|---|"]
    for event in sorted(host, key=lambda e: -e.self_cpu_time_total)[:top]:
        share = event.self_cpu_time_total / host_us if host_us else 0.0
        lines.append(f"| `{short(event.key)}` | {event.count} | {event.self_cpu_time_total / 1000:.2f} ms | {share:.0%} |")
    return summary, lines


def profile_summary_line(what: str, summary: dict) -> str:
    """One sentence: wall time, kernel time and its share, launches, host waits, host time.

    Host waits and host time are left out where ``summary`` (of an older run) lacks them.
    """
    share = summary["kernel_s"] / summary["wall_s"] if summary["wall_s"] else 0.0
    parts = [
        f"wall {summary['wall_s']:.3f} s",
        f"device kernels {summary['kernel_s']:.3f} s ({share:.0%} of the wall time)",
        f"{summary['kernel_launches']} kernel launches",
    ]
    if "host_waits" in summary:
        parts.append(f"{summary['host_waits']} host waits on the device")
    if "host_op_s" in summary:
        parts.append(f"{summary['host_op_s']:.3f} s of host time in operations")
    return f"{what}: {', '.join(parts)}. The profiler slows the host down, so the wall time here is above the unprofiled one."


def profile_markdown(what: str, result: dict, tables: list[str], where: str | None = None) -> str:
    """``OUT_profile.md``: the run's date and machine, then `profile_summary_line` and the profile's tables.

    ``result`` is the run's record, holding ``profile`` (the summary), ``date`` and ``machine``;
    ``where`` names the device the record gives beyond the machine (a GPU's name), if any.
    """
    run = ", ".join(str(result[key]) for key in ("date", "machine") if result.get(key))
    run = "; ".join(part for part in (run, f"device {where}" if where else "") if part)
    head = [f"Run of {run}.", ""] if run else []
    return "\n".join([*head, profile_summary_line(what, result["profile"]), "", *tables]) + "\n"


def stored_profile_tables(record: dict, path: str | os.PathLike) -> list[str]:
    """The profile's tables: the record's ``profile_tables``, else those of the ``OUT_profile.md`` written with it.

    Runs recorded before ``profile_tables`` kept the tables only in the Markdown; its lines from
    the first table on are returned as written.
    """
    if "profile_tables" in record:
        return list(record["profile_tables"])
    lines = Path(path).read_text().splitlines()
    first = next(i for i, line in enumerate(lines) if line.startswith("|"))
    return lines[first:]

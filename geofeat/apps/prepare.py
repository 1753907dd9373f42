"""Building BeCoS with its authors' generator.

BeCoS is not downloaded but generated: ``main.py`` of ``NafieAmrani/becos-code`` draws the
pairs of every split, then writes them one folder at a time (see `geofeat.datasets.becos`
for the layout). `prepare_becos` runs the user's copy of the generator in its own Python (a
separate environment with the generator's requirements), moves what it wrote to a folder
of the user's choice and checks it (`geofeat.apps.becos_check.check_becos`).

>>> from geofeat.apps.prepare import prepare_becos
>>> report = prepare_becos("becos-code", "data/BeCoS", setting="partial_full",
...                        overrides={"template_file": "templates_tosca_demo.csv"})  # doctest: +SKIP
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from geofeat.apps.becos_check import BecosCheck, check_becos
from geofeat.datasets.becos import (
    SETTINGS,
)
from geofeat.errors import DatasetError
from geofeat.storage.files import probe_writable

log = logging.getLogger(__name__)

__all__ = ["BecosPrepare", "override_config", "prepare_becos", "requirement_modules"]

#: Import names of the generator's requirements whose distribution name differs (requirements.txt).
IMPORT_NAMES = {"pyyaml": "yaml", "libigl": "igl", "robust-laplacian": "robust_laplacian", "opencv-python": "cv2"}


# ----------------------------------------------------------------------------- running the generator


@dataclass
class BecosPrepare:
    """What `prepare_becos` did.

    Attributes
    ----------
    command : list of str
        The command run (in ``generator``).
    generator : Path
    config : str
        The configuration the generator ran (a name under ``<generator>/config/``).
    setting : str
    returncode : int
        The generator's exit status (0: it finished).
    seconds : float
        How long it ran.
    log : Path
        Everything it printed.
    output : Path or None
        Where its output now is (``<out>/<setting>``); None when it wrote none.
    check : BecosCheck or None
        `check_becos` of the output.
    notes : list of str
    """

    command: list[str]
    generator: Path
    config: str
    setting: str
    returncode: int
    seconds: float
    log: Path
    output: Path | None = None
    check: BecosCheck | None = None
    notes: list[str] = field(default_factory=list)
    last_lines: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        """The generator finished and its output passed the check."""
        return self.returncode == 0 and self.check is not None and self.check.ok

    def lines(self) -> list[str]:
        """The report as lines of text (no trailing newlines)."""
        out = [
            f"generator: {self.generator} (config {self.config}, setting {self.setting})",
            f"command: {' '.join(self.command)}",
            f"exit status: {self.returncode} after {self.seconds / 60:.1f} min; its output is in {self.log}",
        ]
        if self.returncode != 0 and self.last_lines:
            out.append("last lines it printed:")
            out += [f"  {line}" for line in self.last_lines]
        out.append(f"output: {self.output if self.output is not None else '(none written)'}")
        out += [f"note: {note}" for note in self.notes]
        if self.check is not None:
            out += self.check.lines()
        return out


def _config_setting(text: str, path: Path) -> str:
    match = re.search(r"^setting:\s*['\"]?([A-Za-z_]+)", text, flags=re.MULTILINE)
    if match is None or match.group(1) not in SETTINGS:
        raise DatasetError(f"{path}: no 'setting: {'|'.join(SETTINGS)}' line; is it a BeCoS generator configuration?")
    return match.group(1)


def _yaml_scalar(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null"
    if isinstance(value, (int, float)):
        return repr(value)
    text = str(value)
    return (
        text
        if re.fullmatch(r"[A-Za-z0-9_./-]+", text) and text.lower() not in {"true", "false", "null", "yes", "no"}
        else json.dumps(text)
    )


def override_config(text: str, overrides: Mapping[str, Any]) -> str:
    """The text of a generator configuration with some keys set (comments and order kept).

    Parameters
    ----------
    text : str
        A YAML configuration of the generator (``config/demo_config.yaml``).
    overrides : mapping of str to scalar
        ``key: value`` of top-level keys, or ``parent.key`` for a key one level down
        (``datasets.faust``). A key not present is added.

    Returns
    -------
    str
    """
    lines = text.splitlines()
    for key, value in overrides.items():
        scalar = _yaml_scalar(value)
        parent, _, child = key.rpartition(".")
        if "." in parent:
            raise DatasetError(f"configuration key {key!r}: only 'key' or 'parent.key' can be set.")
        if not parent:
            pattern = re.compile(rf"^{re.escape(child)}:(\s.*)?$")
            at = next((i for i, line in enumerate(lines) if pattern.match(line)), None)
            if at is None:
                lines.append(f"{child}: {scalar}")
            else:
                lines[at] = f"{child}: {scalar}"
            continue
        start = next((i for i, line in enumerate(lines) if re.match(rf"^{re.escape(parent)}:\s*(#.*)?$", line)), None)
        if start is None:
            lines += [f"{parent}:", f"  {child}: {scalar}"]
            continue
        end = next(
            (i for i in range(start + 1, len(lines)) if lines[i].strip() and not lines[i].startswith((" ", "\t"))), len(lines)
        )
        pattern = re.compile(rf"^(\s+){re.escape(child)}:(\s.*)?$")
        at = next((i for i in range(start + 1, end) if pattern.match(lines[i])), None)
        if at is None:
            last = max((i for i in range(start, end) if lines[i].strip()), default=start)
            lines.insert(last + 1, f"  {child}: {scalar}")
        else:
            lines[at] = f"{pattern.match(lines[at]).group(1)}{child}: {scalar}"
    return "\n".join(lines) + "\n"


def _identity(folder: Path) -> tuple[int, int] | None:
    """Device and inode of a folder (the generator renames an older output folder and makes a new one)."""
    try:
        stat = folder.stat()
    except OSError:
        return None
    return stat.st_dev, stat.st_ino


def _default_python(generator: Path) -> str:
    for venv in (".venv", "venv", "env"):
        candidate = generator / venv / "bin" / "python"
        if candidate.is_file():
            return str(candidate)
    return shutil.which("python3") or shutil.which("python") or sys.executable


def requirement_modules(requirements: Path) -> list[str]:
    """The modules to import for each distribution of a ``requirements.txt`` (``PyYAML==6.0.2`` -> ``yaml``).

    Returns
    -------
    list of str
        Empty when the file does not exist.
    """
    if not requirements.is_file():
        return []
    modules = []
    for line in requirements.read_text().splitlines():
        line = line.split("#")[0].strip()
        if not line or line.startswith("-"):
            continue
        name = re.split(r"[\s\[<>=!~;@]", line, maxsplit=1)[0].lower()
        modules.append(IMPORT_NAMES.get(name, name.replace("-", "_")))
    return modules


def _check_output_folder(out: Path) -> None:
    """Refuse an output folder that cannot be made or written (a file there or above it, a read-only place)."""
    try:
        probe_writable(out, prefix=".geofeat-write-check-")
    except OSError as err:
        raise DatasetError(f"cannot write into {out}: {err}. Pass a folder you can write to as --out.") from None


def _check_python(python: str, generator: Path) -> None:
    """Refuse a Python that cannot import the generator's requirements (before hours of running)."""
    requirements = generator / "requirements.txt"
    modules = requirement_modules(requirements)
    if not modules:
        log.info("%s lists no requirements; checking only that %s runs.", requirements, python)
    code = "import " + ", ".join(modules) if modules else "pass"
    try:
        result = subprocess.run([python, "-c", code], capture_output=True, text=True, timeout=300, cwd=generator)
    except (OSError, subprocess.TimeoutExpired) as err:
        raise DatasetError(f"cannot run {python!r} for the BeCoS generator: {err}. Pass the Python of its environment.") from None
    if result.returncode != 0:
        reason = (result.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise DatasetError(
            f"{python} cannot import what the BeCoS generator needs ({reason}). Make an environment for it, e.g. "
            f"`python3 -m venv becos-venv && becos-venv/bin/pip install -r {requirements}`, and pass its Python "
            "(python='becos-venv/bin/python', or --python on the command line)."
        )


def prepare_becos(
    generator: str | os.PathLike,
    out: str | os.PathLike,
    config: str = "demo_config",
    python: str | None = None,
    *,
    setting: str | None = None,
    overrides: Mapping[str, Any] | None = None,
    echo: Callable[[str], None] | None = None,
    check: bool = True,
    progress: bool = False,
) -> BecosPrepare:
    """Run the user's copy of the BeCoS generator and check what it wrote.

    Runs ``<python> main.py --config <config>`` in ``generator``. The generator writes into
    ``<generator>/output/<setting>/`` (renaming an older folder of that name to
    ``<setting>_archived_<time>``); what it wrote is then moved to ``<out>/<setting>/`` and
    checked with `check_becos`.

    Parameters
    ----------
    generator : path-like
        A copy of https://github.com/NafieAmrani/becos-code (``main.py``, ``config/``, ``data/``).
    out : path-like
        Where the output goes: ``<out>/<setting>/`` must not exist yet (or be empty). May be
        ``<generator>/output``, to leave it in place.
    config : str
        A configuration name of ``<generator>/config/`` (without ``.yaml``). ``demo_config``
        builds the TOSCA subset (full_full unless ``setting`` says otherwise).
    python : str, optional
        The Python to run the generator with: one with its requirements installed (its own
        environment). Default: ``<generator>/.venv/bin/python`` (or ``venv/``, ``env/``) if it
        exists, else ``python3`` on the PATH.
    setting : {"full_full", "partial_full", "partial_partial"}, optional
        Run that setting instead of the configuration's.
    overrides : mapping, optional
        Other configuration keys to set, ``{"template_file": "templates_tosca_demo.csv"}``
        (which ``partial_full`` needs with ``demo_config``), ``{"n_jobs": 4}``,
        ``{"datasets.faust": True}``. With ``setting`` or ``overrides`` the configuration is
        written to ``<generator>/config/<config>_geofeat_<setting>.yaml`` and that is run.
    echo : callable, optional
        Called with every line the generator prints (the command line shows them).
    check : bool
        Check the output (`check_becos`) afterwards.
    progress : bool
        Progress bar while checking.

    Returns
    -------
    BecosPrepare
        ``ok`` is True when the generator finished and its output passed the check; ``lines()``
        is the report. A generator that fails is reported (exit status, last lines, what it
        wrote), not raised. Interrupted (Ctrl-C, or ``echo`` raising), the generator is
        stopped and what it wrote stays in ``<generator>/output/<setting>/``, where
        `check_becos` tells what is missing.

    Raises
    ------
    DatasetError
        Before anything runs: ``generator`` is not a generator copy, the configuration does not
        exist, ``python`` cannot import the generator's requirements, or ``<out>/<setting>``
        is taken.
    """
    generator = Path(generator).expanduser().resolve()
    out = Path(out).expanduser()
    if not (generator / "main.py").is_file() or not (generator / "config").is_dir():
        raise DatasetError(
            f"{generator} is not a copy of the BeCoS generator (no main.py and config/). Clone "
            "https://github.com/NafieAmrani/becos-code and pass its folder."
        )
    config_path = generator / "config" / f"{config}.yaml"
    if not config_path.is_file():
        available = sorted(p.stem for p in (generator / "config").glob("*.yaml"))
        raise DatasetError(f"no configuration {config!r} in {generator / 'config'}; found: {', '.join(available)}.")
    text = config_path.read_text()
    if setting is not None and setting not in SETTINGS:
        raise DatasetError(f"setting must be one of {', '.join(SETTINGS)}; found {setting!r}.")
    run_config = config
    if setting is not None or overrides:
        changes = dict(overrides or {})
        if setting is not None:
            changes["setting"] = setting
        text = override_config(text, changes)
        run_config = f"{config}_geofeat_{_config_setting(text, config_path)}"
        (generator / "config" / f"{run_config}.yaml").write_text(text)
    run_setting = _config_setting(text, config_path)
    target = out / run_setting
    produced = generator / "output" / run_setting
    in_place = target.resolve() == produced.resolve()
    if not in_place and target.exists() and any(target.iterdir()):
        raise DatasetError(f"{target} already exists and is not empty; pass another output folder or remove it.")
    _check_output_folder(out)
    python = python or _default_python(generator)
    _check_python(python, generator)

    command = [python, "main.py", "--config", run_config]
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / f"becos_{run_setting}_generator.log"
    earlier = _identity(produced)
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    log.info("running the BeCoS generator: %s (in %s)", " ".join(command), generator)
    started = time.monotonic()
    tail: list[str] = []
    with (
        open(log_path, "w") as log_file,
        subprocess.Popen(command, cwd=generator, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env) as process,
    ):
        try:
            assert process.stdout is not None
            for line in process.stdout:
                log_file.write(line)
                log_file.flush()
                line = line.rstrip("\n")
                tail = (tail + [line])[-15:]
                if echo is not None:
                    echo(line)
                log.debug("generator: %s", line)
            returncode = process.wait()
        except BaseException:
            process.terminate()
            try:
                process.wait(timeout=20)
            except subprocess.TimeoutExpired:
                process.kill()
            raise
    seconds = time.monotonic() - started
    report = BecosPrepare(
        command=command,
        generator=generator,
        config=run_config,
        setting=run_setting,
        returncode=returncode,
        seconds=seconds,
        log=log_path,
        last_lines=tail,
    )
    if produced.is_dir() and _identity(produced) != earlier:
        if in_place:
            report.output = produced
        else:
            if target.exists():
                target.rmdir()  # empty, checked above
            shutil.move(str(produced), str(target))
            report.output = target
    elif produced.is_dir() and returncode != 0:
        report.notes.append(f"the generator failed before writing a new {produced}; the folder there is an older run's.")
    if returncode != 0:
        report.notes.append("the generator failed; the check below shows what it had written.")
    if check and report.output is not None:
        report.check = check_becos(report.output, progress=progress)
    return report

"""What the device check's steps share: paths, JSON files, the context, running a command in a time box.

Standard library only: the parent process of the device check never imports JAX (a GPU stays free for the
steps' processes). A step is a function `(ctx, deadline) -> {"status", "commands", "result", ...}`;
`deadline` is a `time.monotonic()` value and `ctx.run` runs one command within its time box.
"""

from __future__ import annotations

import dataclasses
import datetime
import importlib.util
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from importlib import metadata
from pathlib import Path
from typing import Callable, Optional

from .settings import Settings

HERE = Path(__file__).resolve().parent.parent  # benchmarks/
REPO = HERE.parent
DRIVER = HERE / "device_check.py"  # the steps' children run it again with a child's name (`_train`, ...)


def now_iso() -> str:
    """The current UTC time, ISO 8601 to the second."""
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def write_json(path: Path, obj) -> None:
    """Writes JSON atomically (a temporary file beside `path`, renamed onto it)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=str, allow_nan=True) + "\n")
    os.replace(tmp, path)


def read_json(path: Path):
    """The JSON in `path`, or None when it is missing or unreadable (a command cut short)."""
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


def version(dist: str) -> Optional[str]:
    """The installed version of distribution `dist`, or None."""
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


def module_available(name: str) -> bool:
    """Whether module `name` can be imported (without importing it)."""
    return importlib.util.find_spec(name) is not None


# ---------------------------------------------------------------------------------------------
# Running a step's commands: own process group, time box, output straight into the log.


class Interrupted(Exception):
    """Ctrl-C or SIGTERM: the current command's process group is killed and what was done is written."""


def on_sigterm(signum, frame):
    """SIGTERM handler: raises Interrupted, as Ctrl-C raises KeyboardInterrupt."""
    raise Interrupted(f"signal {signum}")


@dataclasses.dataclass
class Context:
    """What the steps share: settings, folders, the log, the environment of the children, results."""

    settings: Settings
    smoke: bool
    data: Path
    work: Path
    out: Path
    log: object
    env: dict
    header: dict
    fox_run: Optional[Path] = None
    results: dict = dataclasses.field(default_factory=dict)

    def run(self, label: str, argv: list, seconds: float, env: Optional[dict] = None) -> dict:
        """Runs `argv` in the repository root within `seconds`; its output goes to the log as it comes."""
        seconds = max(1.0, seconds)
        self.log.write(f"\n===== {label} (time box {seconds:.0f} s): {shlex.join(argv)}\n".encode())
        offset = self.log.tell()
        print(f"[device_check] {label}: {shlex.join(argv[1:])} (time box {seconds:.0f} s)", flush=True)
        start = time.monotonic()
        proc = subprocess.Popen(
            argv,
            cwd=REPO,
            stdout=self.log,
            stderr=subprocess.STDOUT,
            env={**self.env, **(env or {})},
            start_new_session=True,
        )
        timed_out = interrupted = False
        try:
            proc.wait(timeout=seconds)
            kill_group(proc)  # what the command left running in its group (none, normally)
        except subprocess.TimeoutExpired:
            timed_out = True
            kill_group(proc)
        except (KeyboardInterrupt, Interrupted):
            interrupted = True
            kill_group(proc)
        took = time.monotonic() - start
        with open(self.log.name, "rb") as f:
            f.seek(offset)
            printed = f.read().decode(errors="replace")
        if timed_out:
            self.log.write(f"\n===== {label}: killed after its time box of {seconds:.0f} s\n".encode())
        entry = {
            "label": label,
            "command": shlex.join(argv),
            "returncode": proc.returncode,
            "timed_out": timed_out,
            "time_box_s": round(seconds, 1),
            "seconds": round(took, 1),
            "output_tail": printed[-3000:],
        }
        if interrupted:
            entry["interrupted"] = True
            self.results.setdefault("_interrupted_commands", []).append(entry)
            raise Interrupted(label)
        return entry

    def python(self, *args) -> list:
        """argv of a Python script run by this interpreter."""
        return [sys.executable, *map(str, args)]

    def waldo(self, *args) -> list:
        """argv of the `waldo` CLI (`python -m waldo_jax`: the project need not be installed)."""
        return [sys.executable, "-m", "waldo_jax", *map(str, args)]

    def self_child(self, *args) -> list:
        """argv of the device check run as one of its children (`_environment`, `_pytest`, `_train`)."""
        return [sys.executable, str(DRIVER), *map(str, args)]


def kill_group(proc: subprocess.Popen) -> None:
    """SIGTERM to the command's process group (its own session), SIGKILL after 5 s; nothing when it is gone."""
    for sig, wait in ((signal.SIGTERM, 5), (signal.SIGKILL, 10)):
        try:
            os.killpg(proc.pid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(timeout=wait)
            # the leader is gone; members of its group may linger (xdist workers): end them too
            os.killpg(proc.pid, signal.SIGKILL)
            return
        except subprocess.TimeoutExpired:
            continue
        except ProcessLookupError:
            return


def split_box(deadline: float, weights: list) -> Callable[[int], float]:
    """The time box of sub-command i of a step: its share of the time left among those still to run."""

    def box(i: int) -> float:
        left = deadline - time.monotonic()
        return max(1.0, left * weights[i] / sum(weights[i:]))

    return box


def command_status(commands: list) -> str:
    """A step's status from its commands: timed_out, else done when every one returned 0, else failed."""
    if any(c["timed_out"] for c in commands):
        return "timed_out"
    return "done" if all(c["returncode"] == 0 for c in commands) else "failed"


def need_fox_run(ctx: Context) -> Optional[str]:
    """Why a step that reads the training step's fox run cannot run, or None when it can."""
    if ctx.fox_run is None:
        return "needs the fox run of the training step (it did not finish; or pass --fox-run DIR)"
    return None

"""Facts every benchmark records: device, commit, date, versions."""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
from pathlib import Path

import jax

REPO = Path(__file__).resolve().parent.parent


def git_commit() -> str:
    """HEAD's hash, with '+dirty' when the working tree has uncommitted changes to tracked files."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                               capture_output=True, text=True).stdout.strip()
        return head + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def device_info() -> dict:
    devices = jax.devices()
    d = devices[0]
    info = {
        "platform": d.platform,
        "device_kind": getattr(d, "device_kind", str(d)),
        "device_count": len(devices),
        "host_cpu_count": os.cpu_count(),
        "host": platform.processor() or platform.machine(),
    }
    try:
        info["cpu_affinity"] = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not on Linux
        pass
    return info


def header(name: str) -> dict:
    return {
        "benchmark": name,
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "commit": git_commit(),
        "device": device_info(),
        "jax": jax.__version__,
        "xla_flags": os.environ.get("XLA_FLAGS", ""),
    }


def emit(result: dict, out: str | None) -> None:
    text = json.dumps(result, indent=2)
    print(text)
    if out:
        path = Path(out)
        if path.exists():
            raise SystemExit(f"{path} exists: refusing to overwrite an earlier result (choose another --out)")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + "\n")

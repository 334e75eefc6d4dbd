"""The environment step and the run's provenance: which machine, which versions, which code.

The step runs a child (`device_check.py _environment`) that imports JAX and writes the devices, their
memory statistics, the XLA flags in force, `jax_default_matmul_precision`, nvidia-smi and the project's
packages present or missing. The provenance (commit, digest of the code) is read here, in the parent,
and by `--pack`: no `.git` travels to the device machine, so the pack records them for it.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Optional

from .common import HERE, REPO, Context, command_status, module_available, now_iso, read_json, version, write_json

# Import names of the distributions pyproject.toml names, where they differ.
IMPORT_NAMES = {"pillow": "PIL", "imageio-ffmpeg": "imageio_ffmpeg", "pytest-xdist": "xdist"}
# What the child prints of its JSON, one line in the log.
PRINTED = ("device", "jax", "jaxlib", "jax_default_matmul_precision", "xla_flags_in_force", "packages_missing")


def git_commit() -> Optional[str]:
    """HEAD with '+dirty' (as bench_common.git_commit), or None without git or a .git (the device machine)."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True, timeout=20
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"],
            cwd=REPO,
            capture_output=True,
            text=True,
            timeout=20,
        ).stdout.strip()
        return head + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return None


def code_digest() -> str:
    """sha256 over the project's Python sources (waldo_jax/, benchmarks/, tests/): tells whether the code
    that runs on the device is the code that was packed, where no .git travels."""
    digest = hashlib.sha256()
    for folder in ("waldo_jax", "benchmarks", "tests"):
        for path in sorted((REPO / folder).rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            digest.update(str(path.relative_to(REPO)).encode() + b"\0" + path.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def run_header(manifest: dict) -> dict:
    """The facts every step's JSON starts with; `device` is filled in by the environment step.

    `manifest` is the pack's (empty when the data folder is not a pack): its commit stands in where no
    git is, and its code digest tells whether the code that runs is the code that was packed."""
    commit = git_commit()
    digest = code_digest()
    return {
        "benchmark": "device_check",
        "date": now_iso(),
        "commit": commit
        or (f"{manifest['commit_at_pack']} (at --pack; no git here)" if manifest.get("commit_at_pack") else "unknown"),
        "code_digest": digest,
        "code_matches_pack": (
            digest == manifest["code_digest_at_pack"] if manifest.get("code_digest_at_pack") else None
        ),
        "device": None,
        "jax": version("jax"),
        "jaxlib": version("jaxlib"),
        "python": platform.python_version(),
        "host_cpu_count": os.cpu_count(),
    }


def step(ctx: Context, deadline: float) -> dict:
    """The environment step: the child's JSON; it names the device for the header of every later step."""
    path = ctx.work / "environment.json"
    command = ctx.run("environment", ctx.self_child("_environment", path), deadline - time.monotonic())
    result = read_json(path)
    if result is not None:
        ctx.header["device"] = result.get("device")
        ctx.results["environment"] = result
    status = command_status([command])
    return {
        "status": "failed" if status == "done" and result is None else status,
        "commands": [command],
        "result": result,
    }


# ---------------------------------------------------------------------------------------------
# The child: imports JAX, in its own process.


def child(argv: list) -> int:
    """The machine as the steps' processes see it, written to argv[0] as JSON."""
    path = Path(argv[0])
    start = time.perf_counter()
    import waldo_jax  # noqa: F401  (XLA flags and matmul precision, as every step's process gets them)
    import jax
    import jax.numpy as jnp

    sys.path.insert(0, str(HERE))
    from bench_common import header

    info = header("device_check/environment")
    devices = _devices(jax)
    backend_seconds = time.perf_counter() - start
    probe = float(jnp.arange(1000, dtype=jnp.float32).sum())
    packages = _packages()
    info.update(
        {
            "devices": devices,
            "xla_flags_in_force": os.environ.get("XLA_FLAGS", ""),
            "jax_default_matmul_precision": jax.config.jax_default_matmul_precision,
            "jaxlib": version("jaxlib"),
            "jax_plugins": {
                d: version(d)
                for d in ("jax-cuda12-plugin", "jax-cuda13-plugin", "jax-cuda12-pjrt", "jax-cuda13-pjrt")
                if version(d)
            },
            "python": sys.version,
            "import_to_devices_s": round(backend_seconds, 2),
            "host_memory": host_memory(),
            "probe_sum": probe,
            "nvidia_smi": _nvidia_smi(),
            "packages": packages,
            "packages_missing": sorted(d for d, v in packages.items() if v is None),
            "env": {
                k: v
                for k, v in sorted(os.environ.items())
                if k.startswith(("WALDO_", "XLA_", "JAX_", "CUDA_", "TF_CPP")) or k in ("PYTHONPATH",)
            },
            "cpu_count": os.cpu_count(),
            "platform": platform.platform(),
        }
    )
    write_json(path, info)
    print(json.dumps({k: info[k] for k in PRINTED}))
    return 0


def _devices(jax) -> list:
    """Each device: id, platform, kind and its memory statistics (the byte counts) where it has them."""
    devices = []
    for d in jax.devices():
        entry = {"id": d.id, "platform": d.platform, "device_kind": getattr(d, "device_kind", str(d))}
        try:
            stats = d.memory_stats() or {}
            entry["memory_stats"] = {k: v for k, v in stats.items() if "bytes" in k}
        except Exception as error:  # not every backend has memory statistics
            entry["memory_stats"] = f"unavailable: {type(error).__name__}"
        devices.append(entry)
    return devices


def _nvidia_smi() -> Optional[str]:
    """nvidia-smi's CSV of the GPUs (name, memory, driver, clocks, power), or None without it."""
    if not shutil.which("nvidia-smi"):
        return None
    try:
        return subprocess.run(
            [
                "nvidia-smi",
                "--query-gpu=name,memory.total,memory.used,driver_version,clocks.max.sm,power.limit",
                "--format=csv",
            ],
            capture_output=True,
            text=True,
            timeout=20,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError) as error:
        return f"failed: {error}"


def _packages() -> dict:
    """{distribution: version} of pyproject.toml's dependencies and test extras; None when missing."""
    import tomllib

    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    wanted = project["dependencies"] + project["optional-dependencies"]["test"]
    packages = {}
    for spec in wanted:
        dist = spec.split(">")[0].split("=")[0].split("<")[0].split("[")[0].strip()
        packages[dist] = version(dist) or (
            None
            if not module_available(IMPORT_NAMES.get(dist, dist.replace("-", "_")))
            else "importable, version unknown"
        )
    return packages


def host_memory() -> Optional[str]:
    """MemTotal of /proc/meminfo (e.g. '131072000 kB'), or None where there is none."""
    try:
        return next(
            line.split(":", 1)[1].strip()
            for line in Path("/proc/meminfo").read_text().splitlines()
            if line.startswith("MemTotal")
        )
    except (OSError, StopIteration):
        return None

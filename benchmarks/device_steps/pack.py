"""`--pack`: the data and wheels the steps need, copied into an ignored folder and sized against what the
device machine carries (the working tree and the carried paths, 64 MiB in all); and `--data`'s check.

Required: the fox (whole: it loads exactly as from ../shared at any --downscale, and the tests that read it
need it at full size), every criterion's weights and the donut. Then, while they fit under the limit, the
other data the suite reads (the tests needing what is left out skip). The manifest (`device_pack.json`)
records what was packed and left out, the sizes, the commit and a digest of the code.
"""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Optional

from .common import REPO, now_iso, read_json, version, write_json
from .environment import code_digest, git_commit
from .settings import Settings

DEFAULT_LIMIT_MIB = 64.0  # what the device machine carries: the working tree and the carried paths together
PACK_REQUIRED = ("scenes/fox", "weights", "splats/donut")
PACK_OPTIONAL = ("scenes/lego_tiny", "scenes/face", "scenes/fern", "scenes/garden")
# Parts of a folder to copy (relative names); the rest of it is left out.
PACK_ONLY = {"scenes/fern": ("poses_bounds.npy", "images_8")}  # images_4 (24 MB): no test or step reads it
# Room kept under the limit for the working tree to grow between --pack and the device call, and for
# what packing the files costs on the way (file headers): 4 MiB leaves garden out as the tree stands.
PACK_RESERVE_MIB = 4.0
# Wheels the device machine lacks (pyproject dependencies), at the versions installed here.
WHEELS = ("evosax", "dotmap")
MANIFEST = "device_pack.json"
# pip download's target: the device machine's Python (CPython 3.12, x86-64).
WHEEL_PLATFORM = (
    "--python-version",
    "3.12",
    "--implementation",
    "cp",
    "--platform",
    "manylinux_2_28_x86_64",
    "--platform",
    "manylinux_2_17_x86_64",
    "--platform",
    "manylinux2014_x86_64",
)


def folder_bytes(path: Path) -> int:
    """Bytes of the files under `path` (symbolic links not followed), or of the file `path`."""
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


def mib(n: float) -> float:
    """Bytes as MiB, to two decimals."""
    return round(n / 2**20, 2)


def working_tree_bytes() -> int:
    """Bytes of what travels as the working tree: tracked files and untracked files git does not ignore."""
    try:
        listed = subprocess.run(
            ["git", "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=REPO,
            capture_output=True,
            check=True,
            timeout=60,
        ).stdout
    except (OSError, subprocess.SubprocessError):
        raise SystemExit("device_check: --pack needs git to size the working tree that travels with the data")
    total = 0
    for name in {n for n in listed.decode().split("\0") if n}:
        path = REPO / name
        if path.is_file() and not path.is_symlink():
            total += path.stat().st_size
    return total


def is_ignored(path: Path) -> bool:
    """Whether git ignores the folder `path`, made or not yet: a trailing slash tells git it is a folder, so
    that a pattern for folders (`.whl/`) matches it before it exists (as on a fresh clone)."""
    folder = str(path).rstrip("/") + "/"
    return subprocess.run(["git", "check-ignore", "-q", folder], cwd=REPO, capture_output=True).returncode == 0


def pack_sources(data: Path, name: str) -> list:
    """[(source file, relative destination)] of one pack item, or [] when `data` lacks it."""
    root = data / name
    if not root.exists():
        return []
    if root.is_file():
        return [(root, name)]
    files = []
    for part in PACK_ONLY.get(name, (None,)):
        base = root if part is None else root / part
        found = [base] if base.is_file() else sorted(p for p in base.rglob("*") if p.is_file()) if base.exists() else []
        files += [(p, str(p.relative_to(data))) for p in found if not p.is_symlink()]
    return files


def download_wheels(dest: Path) -> list:
    """The WHEELS at the versions installed here, for the device machine (CPython 3.12, x86-64)."""
    dest.mkdir(parents=True, exist_ok=True)
    wanted = []
    for dist in WHEELS:
        have = version(dist)
        if have is None:
            raise SystemExit(f"device_check: {dist} is not installed here, so its version for the device is unknown")
        wanted.append(f"{dist}=={have}")
    command = [
        sys.executable,
        "-m",
        "pip",
        "download",
        "--no-deps",
        "--only-binary=:all:",
        *WHEEL_PLATFORM,
        "-d",
        str(dest),
        *wanted,
    ]
    print("[pack] " + shlex.join(command), flush=True)
    proc = subprocess.run(command, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"device_check: pip download failed ({proc.returncode}): {proc.stderr.strip()[-500:]}")
    # Another version of one of these, from an earlier pack, would make the device's pip install refuse both.
    versions = dict(w.split("==") for w in wanted)
    for wheel in dest.glob("*.whl"):
        dist, wheel_version = wheel.name.split("-")[:2]
        if dist.lower().replace("_", "-") in versions and wheel_version != versions[dist.lower().replace("_", "-")]:
            wheel.unlink()
    return wanted


def pack(
    dest: Path, data: Path, wheels: Optional[Path], limit_mib: float, reserve_mib: float, force: bool, smoke: bool
) -> dict:
    """Copies what the steps read from `data` into `dest` (and the wheels into `wheels`), after checking it
    fits in `limit_mib` with the working tree. Returns the manifest (also written as dest/MANIFEST)."""
    dest = dest.absolute()
    _refuse_before_packing(dest, data, wheels, force)
    tree = working_tree_bytes()
    wheel_bytes = 0
    wheel_names: list = []
    if wheels is not None:
        wheel_names = download_wheels(wheels)
        wheel_bytes = folder_bytes(wheels)
    limit = limit_mib * 2**20
    items = {name: pack_sources(data, name) for name in PACK_REQUIRED}
    required = sum(src.stat().st_size for files in items.values() for src, _ in files)
    if tree + wheel_bytes + required > limit:
        raise SystemExit(
            f"device_check: too big for the device machine: the working tree ({mib(tree)} MiB), the wheels "
            f"({mib(wheel_bytes)} MiB) and the required data ({mib(required)} MiB) make "
            f"{mib(tree + wheel_bytes + required)} MiB > {limit_mib:g} MiB"
        )
    room = limit - reserve_mib * 2**20 - tree - wheel_bytes - required
    left_out = _add_optional(items, data, room, smoke)
    _copy(items, dest)
    packed = folder_bytes(dest)
    manifest = {
        "packed": now_iso(),
        "from": str(data.resolve()),
        "commit_at_pack": git_commit(),
        "code_digest_at_pack": code_digest(),
        "items": {
            name: {"files": len(files), "mib": mib(sum(s.stat().st_size for s, _ in files))}
            for name, files in items.items()
        },
        "left_out": left_out,
        "only": {k: list(v) for k, v in PACK_ONLY.items()},
        "fox": "whole (1080x1920 JPEGs): loads exactly as from $WALDO_DATA; the steps downscale it at load time",
        "wheels": wheel_names,
        "wheels_dir": None if wheels is None else str(wheels),
        "sizes_mib": {
            "working_tree": mib(tree),
            "wheels": mib(wheel_bytes),
            "data": mib(packed),
            "total": mib(tree + wheel_bytes + packed),
            "limit": limit_mib,
            "reserve": reserve_mib,
        },
        "smoke": smoke,
    }
    write_json(dest / MANIFEST, manifest)
    return manifest


def _refuse_before_packing(dest: Path, data: Path, wheels: Optional[Path], force: bool) -> None:
    """One-line refusals, before anything is copied or downloaded: no data, a folder that is not an earlier
    pack (or is one, without --force), a destination git would commit, a required item missing."""
    if not (data / "scenes").is_dir():
        raise SystemExit(f"device_check: {data} has no scenes/ folder (set WALDO_DATA or pass --data-from)")
    if dest.exists() and any(dest.iterdir()):
        if not force:
            raise SystemExit(
                f"device_check: {dest} is not empty: refusing to overwrite (pass --force to replace an earlier pack)"
            )
        if not (dest / MANIFEST).is_file():
            raise SystemExit(f"device_check: {dest} is not an earlier pack (no {MANIFEST}): refusing to replace it")
    for folder in (dest, None if wheels is None else wheels.absolute()):
        if folder is not None and (folder == REPO or REPO in folder.parents) and not is_ignored(folder):
            raise SystemExit(
                f"device_check: {folder} is inside the repository but not ignored by git: use an "
                "ignored folder (.device/data, .whl) so that it is never committed"
            )
    for name in PACK_REQUIRED:
        if not pack_sources(data, name):
            raise SystemExit(f"device_check: {data / name} is missing: the steps need it")


def _add_optional(items: dict, data: Path, room: float, smoke: bool) -> dict:
    """Adds to `items` the PACK_OPTIONAL items that fit in `room` bytes, in order; returns {left out: why}."""
    left_out = {}
    for name in () if smoke else PACK_OPTIONAL:
        files = pack_sources(data, name)
        size = sum(src.stat().st_size for src, _ in files)
        if not files:
            left_out[name] = "not in the data folder"
        elif size <= room:
            items[name] = files
            room -= size
        else:
            left_out[name] = f"{mib(size)} MiB does not fit (the tests that read it skip)"
    if smoke:
        left_out.update({name: "--smoke packs only what the steps read" for name in PACK_OPTIONAL})
    return left_out


def _copy(items: dict, dest: Path) -> None:
    """Replaces `dest` with a copy of the items' files."""
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for files in items.values():
        for src, rel in files:
            target = dest / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, target)


def check_data(data: Path, settings: Settings) -> dict:
    """What the steps need from a data folder, refused in one line when missing. Returns its manifest
    (empty when the folder is not a pack, e.g. ../shared itself)."""
    if not data.is_dir():
        raise SystemExit(f"device_check: --data {data}: no such folder (make it with --pack)")
    fox = data / settings.fox / "transforms.json"
    missing = [str(p) for p in (fox, data / "weights" / "csnet") if not p.exists()]
    if missing:
        raise SystemExit(f"device_check: --data {data} lacks {', '.join(missing)} (make it with --pack)")
    return read_json(data / MANIFEST) or {}


def default_data() -> Optional[Path]:
    """$WALDO_DATA, else ../shared beside the repository when it is there, else None."""
    env = os.environ.get("WALDO_DATA")
    if env:
        return Path(env).expanduser()
    shared = REPO.parent / "shared"
    return shared if shared.is_dir() else None

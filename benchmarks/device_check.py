"""The device check: every GPU measurement of the project as one time-boxed command.

A GPU is lent now and then for about 15 minutes (a machine start takes 1-2 of them), with the code and
at most 64 MiB of carried files, and no `../shared`. This script is the whole measurement, prepared
ahead: its steps run in order, each in its own process (its compilations and device memory its own),
each within a time box, and each writes its JSON the moment it finishes, so a run cut short still
returns what it did.

  step          what (the script or command it runs)
  environment   devices, memory, XLA flags in force, jax_default_matmul_precision, packages, nvidia-smi
  correctness   pytest: the files that failed on a GPU before (FAILED_BEFORE), then the rest of the suite
                as far as the step's time allows: passed / failed / skipped, the failures' names
  determinism   the same seed's rendered-criterion `waldo explore` twice (scores byte-identical?), and
                once with WALDO_DETERMINISTIC=0 (its time beside the default's)
  training      the fox, quality preset, a fixed number of steps into a run folder the next steps reuse:
                ms_per_step, field_fwd_bwd_ms, step_over_field (as train_step.py), held-out PSNR
  rendering     that fox through render_trained.py (rays/s, evaluations/ray, passes/view, the field
                alone, render efficiency); render_population.py batched vs loop at each size
  search        `waldo explore` on the fox: EGPS, saliency, low budget, at each resolution: seconds
  gradient      gradient_cost.py, the fox run's case included
  splats        benchmarks/render_splats.py at the GPU targets' sizes; `waldo explore` on the donut

What comes back, in --out (3 files, under the device machine's 8-file limit):
  device_check.json     every step's JSON (device, versions, commit, settings, result), the targets of
                        the issue as target / measured / met, rewritten atomically after each step;
  device_check.log      everything the steps printed, written as they print it;
  pytest_reports.jsonl  one line per test report of the correctness step, written as tests finish.
Per-step JSON files, run folders and the benchmarks' own JSONs stay in --work (default a new folder in
the temporary directory): they are not needed to read the result.

  # here, before a GPU is lent: the data the steps read, and the wheels the machine lacks
  python benchmarks/device_check.py --pack .device/data
  # on the device machine (the exact call is in benchmarks/README.md, "On a GPU: the device check")
  python3 benchmarks/device_check.py --data .device/data --out $OUT
  # every step at tiny sizes on the CPU (tests/test_device_check.py runs it)
  python benchmarks/device_check.py --smoke --data ../shared --out /tmp/device_check_smoke

The parent process never imports JAX: a GPU stays free for the steps' processes.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import hashlib
import importlib.util
import json
import os
import platform
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from importlib import metadata
from pathlib import Path
from typing import Callable, Optional

HERE = Path(__file__).resolve().parent
REPO = HERE.parent

DEFAULT_BUDGET_S = 540.0
SMOKE_BUDGET_S = 1800.0  # --smoke on a shared 2-core CPU: the boxes are the GPU's, the CPU needs ~3x
DEFAULT_LIMIT_MIB = 64.0  # what the device machine carries: the working tree and the carried paths together
OUT_FILES = ("device_check.json", "device_check.log", "pytest_reports.jsonl")

# The test files that failed on a GPU before (one H100, before the packed renderer): run first.
FAILED_BEFORE = (
    "test_csnet.py",
    "test_cnniqa.py",
    "test_nerf_field.py",
    "test_cameras.py",
    "test_sharding.py",
    "test_train.py",
    "test_occupancy.py",
    "test_scenes.py",
    "test_explore_cli.py",
)
# Never in the correctness step: this check's own test (it runs the check itself, on the CPU).
NOT_IN_SUITE = ("test_device_check.py",)
# Test files that cannot even be collected without these packages (none of them is on the device machine).
TEST_FILE_PACKAGES = {"test_notebooks.py": ("nbformat", "nbclient", "ipykernel")}
# Import names of the distributions pyproject.toml names, where they differ.
IMPORT_NAMES = {"pillow": "PIL", "imageio-ffmpeg": "imageio_ffmpeg", "pytest-xdist": "xdist"}

# What --pack copies from $WALDO_DATA. Required: the fox (whole: it loads exactly as from ../shared at
# any --downscale, and the tests that read it need it at full size) and every criterion's weights. Then,
# while they fit under the limit, the other data the suite reads (tests needing what is left out skip).
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


# ---------------------------------------------------------------------------------------------
# Settings: the real sizes, and the tiny ones of --smoke.


@dataclasses.dataclass(frozen=True)
class Settings:
    """Every size the steps use (plain Python: static, shape-setting)."""

    fox: str = "scenes/fox"
    fox_downscale: float = 4.0  # 270x480 training images: the GPU's; the CPU runs used 8
    train_preset: str = "quality"
    train_steps: int = 1000
    train_overrides: tuple = ()  # (name, value) pairs given to TrainConfig.preset
    pytest_first: tuple = tuple(f"tests/{name}" for name in FAILED_BEFORE)
    pytest_rest: Optional[tuple] = None  # None: every other test file
    pytest_workers: int = 8
    determinism_args: tuple = ("procedural:0", "--resolution", "64", "--criterion", "saliency", "--budget", "low")
    render_poses: int = 16
    render_size: str = "144x256"
    render_repeats: int = 3
    population_poses: int = 256
    population_resolutions: tuple = (64, 128, 256)
    population_samples: int = 64
    population_repeats: int = 3
    explore_resolutions: tuple = (256, 455)  # the fox is portrait: 144x256 and 256x455 (shorter side 256)
    explore_args: tuple = ("--criterion", "saliency", "--method", "egps", "--budget", "low")
    gradient_cases: tuple = ("procedural:waldo_oracle", "procedural:saliency", "RUN:saliency")
    gradient_resolution: int = 64
    gradient_poses: int = 4
    gradient_repeats: int = 5
    # The splat renderer (issue [2/5]): the GPU targets' cells, then the donut explored.
    splats_args: tuple = (
        "--counts",
        "100000,1000000",
        "--sizes",
        "128,256",
        "--populations",
        "256",
        "--repeats",
        "3",
        "--max-seconds-per-cell",
        "60",
    )
    splats_explore_args: tuple = (
        "--resolution",
        "128",
        "--criterion",
        "saliency",
        "--method",
        "egps+refine",
        "--budget",
        "low",
    )


FULL = Settings()
SMOKE = Settings(
    fox_downscale=16.0,
    train_steps=48,
    train_overrides=(
        ("samples_per_batch", 2**12),
        ("rays_per_batch", 2**10),
        ("chunk", 16),
        ("occupancy_resolution", 32),
        ("occupancy_warmup", 16),
        ("eval_samples", 128),
        ("render_step_scale", 1.0),
        ("hashgrid", {"L": 8, "T": 2**14}),
    ),
    pytest_first=("tests/test_cameras.py::test_look_at_identity_frame",),
    pytest_rest=("tests/test_device_check.py::test_time_left_by_a_step_goes_to_the_later_ones",),
    pytest_workers=0,
    determinism_args=(
        "procedural:0",
        "--resolution",
        "16",
        "--views",
        "8",
        "--epochs",
        "2",
        "--children-per-epoch",
        "6",
        "--criterion",
        "colorfulness",
    ),
    render_poses=2,
    render_size="24x32",
    render_repeats=1,
    population_poses=2,
    population_resolutions=(16,),
    population_samples=16,
    population_repeats=1,
    explore_resolutions=(32,),
    explore_args=("--criterion", "colorfulness", "--method", "egps", "--epochs", "2", "--children-per-epoch", "4"),
    gradient_cases=("RUN:colorfulness",),
    gradient_resolution=16,
    gradient_poses=2,
    gradient_repeats=1,
    splats_args=("--quick", "--populations", "2"),
    splats_explore_args=(
        "--resolution",
        "16",
        "--criterion",
        "colorfulness",
        "--method",
        "egps+refine",
        "--epochs",
        "2",
        "--children-per-epoch",
        "6",
        "--refine-poses",
        "2",
        "--refine-steps",
        "1",
    ),
)


# ---------------------------------------------------------------------------------------------
# Small helpers (the parent imports no JAX and no waldo_jax: XLA flags and the GPU stay the steps').


def now_iso() -> str:
    return datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds")


def write_json(path: Path, obj) -> None:
    """Writes JSON atomically (a temporary file beside `path`, renamed onto it)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=str, allow_nan=True) + "\n")
    os.replace(tmp, path)


def version(dist: str) -> Optional[str]:
    try:
        return metadata.version(dist)
    except metadata.PackageNotFoundError:
        return None


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


def folder_bytes(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file() and not p.is_symlink())


def mib(n: float) -> float:
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


def read_json(path: Path):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, ValueError):
        return None


# ---------------------------------------------------------------------------------------------
# --pack: the data and wheels the steps need, sized against the device machine's limit.


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
    if not (data / "scenes").is_dir():
        raise SystemExit(f"device_check: {data} has no scenes/ folder (set WALDO_DATA or pass --data-from)")
    dest = dest.absolute()
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

    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    for files in items.values():
        for src, rel in files:
            target = dest / rel
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(src, target)
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


# ---------------------------------------------------------------------------------------------
# Running a step's commands: own process group, time box, output straight into the log.


class Interrupted(Exception):
    """Ctrl-C or SIGTERM: the current command's process group is killed and what was done is written."""


def _on_sigterm(signum, frame):
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
        return [sys.executable, *map(str, args)]

    def waldo(self, *args) -> list:
        return [sys.executable, "-m", "waldo_jax", *map(str, args)]

    def self_child(self, *args) -> list:
        return [sys.executable, str(Path(__file__).resolve()), *map(str, args)]


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
    if any(c["timed_out"] for c in commands):
        return "timed_out"
    return "done" if all(c["returncode"] == 0 for c in commands) else "failed"


# ---------------------------------------------------------------------------------------------
# The steps. Each takes the context and its deadline (time.monotonic) and returns
# {"status", "commands", "result", ...}; a step whose inputs are missing returns status "skipped".


def step_environment(ctx: Context, deadline: float) -> dict:
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


def step_correctness(ctx: Context, deadline: float) -> dict:
    settings = ctx.settings
    report = ctx.out / "pytest_reports.jsonl"
    not_run_files = {}
    missing = {name: [m for m in modules if not module_available(m)] for name, modules in TEST_FILE_PACKAGES.items()}
    for name, gone in missing.items():
        if gone:
            not_run_files[f"tests/{name}"] = f"needs {', '.join(gone)}: not installed on this machine"
    first = [t for t in settings.pytest_first if t.split("::")[0] not in not_run_files]
    if settings.pytest_rest is None:
        taken = {Path(t.split("::")[0]).name for t in settings.pytest_first} | set(NOT_IN_SUITE)
        rest = [
            f"tests/{p.name}"
            for p in sorted((REPO / "tests").glob("test_*.py"))
            if p.name not in taken and f"tests/{p.name}" not in not_run_files
        ]
    else:
        rest = list(settings.pytest_rest)
    env = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}  # several pytest workers share one GPU
    workers = ["-n", str(settings.pytest_workers)]
    common = ["-p", "no:cacheprovider", "-q", "-rfE", *workers]
    commands, runs = [], []
    for label, files in (("failed before", first), ("the rest", rest)):
        left = deadline - time.monotonic()
        if not files:
            continue
        if left < 10 and not ctx.smoke:
            runs.append({"files": label, "not_run": f"no time left in the step ({left:.0f} s)", "paths": files})
            continue
        marker = len(report.read_text().splitlines()) if report.exists() else 0
        command = ctx.run(
            f"correctness: {label}", ctx.self_child("_pytest", report, "--", *common, *files), left, env=env
        )
        commands.append(command)
        runs.append(
            {
                "files": label,
                "paths": files,
                **summarise_reports(report, marker),
                "timed_out": command["timed_out"],
                "exitstatus": command["returncode"],
            }
        )
    totals = {
        k: sum(r.get(k, 0) for r in runs if isinstance(r.get(k, 0), int))
        for k in (
            "collected",
            "passed",
            "failed",
            "errors",
            "skipped",
            "xfailed",
            "xpassed",
            "not_run",
            "collection_errors",
        )
    }
    failures = [f for r in runs for f in r.get("failures", [])]
    # Complete: every selected file ran to its end (no time box hit, nothing left unrun).
    complete = all(isinstance(r.get("not_run"), int) and r["not_run"] == 0 and not r.get("timed_out") for r in runs)
    if not commands:
        return {
            "status": "skipped",
            "reason": "no time left in the step to start pytest",
            "commands": [],
            "result": {"runs": runs, "totals": None, "not_run_files": not_run_files},
        }
    status = "timed_out" if any(c["timed_out"] for c in commands) else "done"
    return {
        "status": status,
        "commands": commands,
        "result": {
            "totals": totals,
            "runs": runs,
            "failures": failures,
            "failed_names": [f["nodeid"] for f in failures],
            "suite_complete": complete and settings.pytest_rest is None,
            "not_run_files": not_run_files,
            "packages_missing": (ctx.results.get("environment") or {}).get("packages_missing"),
            "workers": settings.pytest_workers,
            "env": env,
        },
    }


def module_available(name: str) -> bool:
    return importlib.util.find_spec(name) is not None


def summarise_reports(report: Path, skip_lines: int) -> dict:
    """Counts and failures from the JSON lines the `_pytest` child wrote (from line `skip_lines` on)."""
    outcomes, failures, collection_errors, collected, skips = {}, [], [], 0, {}
    if report.exists():
        for i, line in enumerate(report.read_text().splitlines()):
            if i < skip_lines or not line.strip():
                continue
            try:
                event = json.loads(line)
            except ValueError:
                continue
            kind = event.get("event")
            if kind == "collected":
                collected = max(collected, int(event["count"]))
            elif kind == "collect_error":
                collection_errors.append({"nodeid": event["nodeid"], "message": event.get("message", "")})
            elif kind == "report":
                node, when, outcome = event["nodeid"], event["when"], event["outcome"]
                previous = outcomes.get(node)
                if outcome == "failed":
                    verdict = "failed" if when == "call" else "errors"
                    if previous != "failed":
                        outcomes[node] = verdict
                    failures.append({"nodeid": node, "when": when, "message": event.get("message", "")})
                elif outcome == "skipped" and previous is None:
                    outcomes[node] = "xfailed" if event.get("xfail") else "skipped"
                    reason = event.get("message", "")[-200:]
                    skips[reason] = skips.get(reason, 0) + 1
                elif outcome == "passed" and when == "call" and previous is None:
                    outcomes[node] = "xpassed" if event.get("xfail") else "passed"
    counts = {
        k: sum(1 for v in outcomes.values() if v == k)
        for k in ("passed", "failed", "errors", "skipped", "xfailed", "xpassed")
    }
    return {
        "collected": collected,
        **counts,
        "not_run": max(0, collected - len(outcomes)),
        "collection_errors": len(collection_errors),
        "collection_error_list": collection_errors,
        "failures": failures[:200],
        "skip_reasons": dict(sorted(skips.items(), key=lambda kv: -kv[1])[:20]),
    }


def step_determinism(ctx: Context, deadline: float) -> dict:
    runs = (
        ("default, first", {}),
        ("default, second", {}),
        ("WALDO_DETERMINISTIC=0", {"WALDO_DETERMINISTIC": "0", "XLA_FLAGS": strip_determinism(ctx.env)}),
    )
    box = split_box(deadline, [1, 1, 1])
    commands, results = [], []
    for i, (label, env) in enumerate(runs):
        out = ctx.work / f"determinism_{i}"
        argv = ctx.waldo(
            "explore", *ctx.settings.determinism_args, "--method", "egps", "--seed", "0", "--quiet", "--out", out
        )
        commands.append(ctx.run(f"determinism: {label}", argv, box(i), env=env))
        results.append(read_json(out / "results.json"))
        if results[-1] is None and i < 2:
            break
    texts = [None if r is None else scores_text(r) for r in results]
    result = {"source_args": list(ctx.settings.determinism_args), "method": "egps", "seed": 0, "runs": []}
    for (label, env), command, r, text in zip(runs, commands, results, texts):
        result["runs"].append(
            {
                "label": label,
                "env": env,
                "wall_s": command["seconds"],
                "seconds": None if r is None else r.get("seconds"),
                "scores_sha256": None if text is None else hashlib.sha256(text.encode()).hexdigest(),
                "n_generated": None if r is None else r.get("n_generated"),
            }
        )
    if len(texts) >= 2 and texts[0] is not None and texts[1] is not None:
        result["identical"] = texts[0] == texts[1]
        result["compared"] = "scores_train, scores_generated and the top-k c2w of results.json, as JSON text"
    else:
        result["identical"] = None
    if len(texts) == 3 and texts[2] is not None and texts[0] is not None:
        result["nondeterministic_run_same_as_default"] = texts[2] == texts[0]
        searches = [r["seconds"]["search"] for r in results]
        result["search_seconds"] = {"default": searches[:2], "WALDO_DETERMINISTIC=0": searches[2]}
    status = command_status(commands)
    if status == "done" and len(commands) < 3:
        status = "failed"
    return {"status": status, "commands": commands, "result": result}


def strip_determinism(env: dict) -> str:
    flags = env.get("XLA_FLAGS", "").split()
    return " ".join(
        f for f in flags if not f.startswith(("--xla_gpu_deterministic_ops", "--xla_gpu_exclude_nondeterministic_ops"))
    )


def scores_text(results: dict) -> str:
    return json.dumps(
        [results.get("scores_train"), results.get("scores_generated"), [t.get("c2w") for t in results.get("topk", [])]]
    )


def step_training(ctx: Context, deadline: float) -> dict:
    settings = ctx.settings
    run = ctx.work / "fox_run"
    path = ctx.work / "training.json"
    left = deadline - time.monotonic()
    # Stop training in time for the held-out PSNR, the render-step calibration, the field timing and the save.
    train_seconds = max(5.0, 0.6 * left) if not ctx.smoke else left
    argv = ctx.self_child(
        "_train",
        ctx.data / settings.fox,
        "--downscale",
        settings.fox_downscale,
        "--preset",
        settings.train_preset,
        "--steps",
        settings.train_steps,
        "--overrides",
        json.dumps(dict(settings.train_overrides)),
        "--train-seconds",
        round(train_seconds, 1),
        "--run",
        run,
        "--json",
        path,
    )
    command = ctx.run("training", argv, left)
    result = read_json(path)  # written once training ends, then again complete
    if result is not None and (run / "checkpoint.ckpt").is_file():
        ctx.fox_run = run
    status = command_status([command])
    if status == "done" and (result is None or not result.get("complete")):
        status = "failed"
    return {"status": status, "commands": [command], "result": result}


def need_fox_run(ctx: Context) -> Optional[str]:
    if ctx.fox_run is None:
        return "needs the fox run of the training step (it did not finish; or pass --fox-run DIR)"
    return None


def step_rendering(ctx: Context, deadline: float) -> dict:
    settings = ctx.settings
    commands, result = [], {}
    sizes = list(settings.population_resolutions)
    # render_trained first (needs the fox run), then one process per population size, so that a size cut
    # short by the time box leaves the smaller sizes measured.
    weights = ([3] if ctx.fox_run is not None else []) + [1] * len(sizes)
    box = split_box(deadline, weights)
    i = 0
    if ctx.fox_run is not None:
        path = ctx.work / "render_trained.json"
        argv = ctx.python(
            HERE / "render_trained.py",
            ctx.fox_run,
            ctx.data / settings.fox,
            "--downscale",
            settings.fox_downscale,
            "--poses",
            settings.render_poses,
            "--size",
            settings.render_size,
            "--repeats",
            settings.render_repeats,
            "--skip",
            "curve",
            "--load-threshold",
            "1000",
            "--out",
            path,
        )
        commands.append(ctx.run("rendering: render_trained", argv, box(i)))
        result["render_trained"] = read_json(path)
        i += 1
    else:
        result["render_trained"] = None
        result["render_trained_skipped"] = need_fox_run(ctx)
    population = []
    for size in sizes:
        path = ctx.work / f"render_population_{size}.json"
        argv = ctx.python(
            HERE / "render_population.py",
            "--poses",
            settings.population_poses,
            "--resolutions",
            size,
            "--samples",
            settings.population_samples,
            "--repeats",
            settings.population_repeats,
            "--load-threshold",
            "1000",
            "--out",
            path,
        )
        commands.append(ctx.run(f"rendering: render_population {size}^2", argv, box(i)))
        i += 1
        population.append(read_json(path))
    result["render_population"] = population
    result["batched_over_loop"] = {
        str(size): (None if p is None else p["speedup_batched_over_loop"][str(size)])
        for size, p in zip(sizes, population)
    }
    return {"status": command_status(commands), "commands": commands, "result": result}


def step_search(ctx: Context, deadline: float) -> dict:
    reason = need_fox_run(ctx)
    if reason:
        return {"status": "skipped", "reason": reason, "commands": [], "result": None}
    settings = ctx.settings
    resolutions = list(settings.explore_resolutions)
    box = split_box(deadline, [1] * len(resolutions))
    commands, runs = [], []
    for i, resolution in enumerate(resolutions):
        out = ctx.work / f"explore_{resolution}"
        argv = ctx.waldo(
            "explore",
            ctx.fox_run,
            *settings.explore_args,
            "--resolution",
            resolution,
            "--seed",
            "0",
            "--quiet",
            "--out",
            out,
        )
        commands.append(ctx.run(f"search: explore at {resolution}", argv, box(i)))
        r = read_json(out / "results.json")
        runs.append(
            {
                "resolution_arg": resolution,
                "wall_s": commands[-1]["seconds"],
                **(
                    {}
                    if r is None
                    else {
                        k: r.get(k)
                        for k in ("resolution", "seconds", "n_train", "n_generated", "cost", "cvir", "mcvir", "device")
                    }
                ),
            }
        )
    return {
        "status": command_status(commands),
        "commands": commands,
        "result": {"args": list(settings.explore_args), "runs": runs},
    }


def step_gradient(ctx: Context, deadline: float) -> dict:
    settings = ctx.settings
    cases, note = [], None
    for case in settings.gradient_cases:
        if case.startswith("RUN:"):
            if ctx.fox_run is None:
                note = f"{case} left out: {need_fox_run(ctx)}"
                continue
            case = f"{ctx.fox_run}:{case[4:]}"
        cases.append(case)
    if not cases:
        return {"status": "skipped", "reason": note, "commands": [], "result": None}
    path = ctx.work / "gradient_cost.json"
    argv = ctx.python(
        HERE / "gradient_cost.py",
        "--cases",
        ",".join(cases),
        "--resolution",
        settings.gradient_resolution,
        "--poses",
        settings.gradient_poses,
        "--repeats",
        settings.gradient_repeats,
        "--load-threshold",
        "1000",
        "--out",
        path,
    )
    command = ctx.run("gradient cost", argv, deadline - time.monotonic())
    return {
        "status": command_status([command]),
        "commands": [command],
        "result": read_json(path),
        **({"note": note} if note else {}),
    }


def step_splats(ctx: Context, deadline: float) -> dict:
    """benchmarks/render_splats.py's synthetic cells (the GPU targets'), then `waldo explore` on the donut."""
    settings = ctx.settings
    path = ctx.work / "render_splats.json"
    argv = ctx.python(HERE / "render_splats.py", *settings.splats_args, "--load-threshold", "1000", "--out", path)
    commands = [ctx.run("render_splats", argv, 0.7 * (deadline - time.monotonic()))]
    donut = ctx.data / "splats" / "donut" / "point_cloud.ply"
    explore = None
    if donut.is_file():
        out = ctx.work / "explore_donut"
        commands.append(
            ctx.run(
                "explore donut",
                ctx.waldo("explore", donut, *settings.splats_explore_args, "--quiet", "--out", out),
                deadline - time.monotonic(),
            )
        )
        r = read_json(out / "results.json")
        explore = (
            None
            if r is None
            else {
                k: r.get(k) for k in ("resolution", "seconds", "cost", "cvir", "mcvir", "renderer", "refine", "device")
            }
        )
    return {
        "status": command_status(commands),
        "commands": commands,
        "result": {
            "render_splats": read_json(path),
            "explore_donut": explore,
            **({} if donut.is_file() else {"note": f"{donut} not packed: the donut explore left out"}),
        },
    }


@dataclasses.dataclass(frozen=True)
class Step:
    """One step of the check: `share` is its time box in seconds of the default budget (scaled with
    --budget; time a step leaves unused goes to the steps after it, in proportion to their shares)."""

    name: str
    share: float
    run: Callable[[Context, float], dict]
    what: str


STEPS = (
    Step("environment", 20, step_environment, "devices, memory, XLA flags, matmul precision, packages"),
    Step("correctness", 130, step_correctness, "pytest: the files that failed on a GPU before, then the rest"),
    Step("determinism", 75, step_determinism, "same-seed explore twice: byte-identical; WALDO_DETERMINISTIC=0 time"),
    Step("training", 90, step_training, "fox, quality preset: ms/step, field fwd+bwd, step/field, held-out PSNR"),
    Step("rendering", 100, step_rendering, "render_trained.py on the fox run; render_population.py per size"),
    Step("search", 85, step_search, "waldo explore on the fox run (EGPS, saliency, low budget) per resolution"),
    Step("gradient", 40, step_gradient, "gradient_cost.py, the fox run's case included"),
    Step(
        "splats",
        60,
        step_splats,
        "render_splats.py: 100k and 1M splats at 128^2 / 256^2, 256 poses; the donut explored",
    ),
)
STEP_NAMES = tuple(step.name for step in STEPS)


# ---------------------------------------------------------------------------------------------
# The targets of the issue, as target / measured / met.


def targets(steps: dict, platform_name: Optional[str]) -> list:
    def result(name):
        entry = steps.get(name) or {}
        return entry.get("result") or {}

    rows = []

    def add(target, measured, met, unit="", note=""):
        rows.append({"target": target, "measured": measured, "met": met, "unit": unit, "note": note})

    trained = result("rendering").get("render_trained") or {}
    rays = trained.get("rays_per_s")
    setting = (
        f"{trained.get('timing_poses')} poses at {'x'.join(map(str, trained.get('timing_size') or []))}"
        if trained
        else "not measured"
    )
    add("trained fox >= 5 M rays/s", rays, None if rays is None else rays >= 5e6, "rays/s", setting)
    efficiency = trained.get("render_efficiency")
    add("render efficiency >= 0.3", efficiency, None if efficiency is None else efficiency >= 0.3, "x")
    if not result("search").get("runs"):
        add("fox explore (EGPS, saliency, low budget) <= 10 s of search", None, None, "s", "not measured")
    for run in result("search").get("runs", []):
        search = (run.get("seconds") or {}).get("search")
        size = (
            "x".join(map(str, run["resolution"])) if run.get("resolution") else f"--resolution {run['resolution_arg']}"
        )
        add(
            f"fox explore ({' '.join(result('search').get('args', []))}) at {size} <= 10 s of search",
            search,
            None if search is None else search <= 10.0,
            "s",
        )
    ms = result("training").get("ms_per_step")
    add("quality training <= 10 ms per step", ms, None if ms is None else ms <= 10.0, "ms")
    ratios = result("rendering").get("batched_over_loop") or {"every size": None}
    for size, ratio in ratios.items():
        add(
            f"batched >= loop at {size}" + ("^2" if size.isdigit() else ""),
            ratio,
            None if ratio is None else ratio >= 1.0,
            "x",
        )
    correctness = result("correctness")
    totals = correctness.get("totals")
    if totals:
        bad = totals["failed"] + totals["errors"] + totals["collection_errors"]
        measured = {k: totals[k] for k in ("passed", "failed", "errors", "skipped", "not_run", "collection_errors")}
        complete = correctness.get("suite_complete")
        met = False if bad else (True if complete else None)
        add(
            "every test passes",
            measured,
            met,
            "tests",
            "" if complete else "the suite did not run to its end within the step's time (met: null)",
        )
    else:
        add("every test passes", None, None, "tests", "not measured")
    identical = result("determinism").get("identical")
    add("same-seed reruns byte-identical", identical, identical, "")
    for row in (result("splats").get("render_splats") or {}).get("targets", []):
        if row.get("target", "").startswith("GPU"):
            add(row["target"], row.get("measured"), row.get("met"), row.get("unit", ""), row.get("note", ""))
    for row in rows:
        if row["measured"] is None:
            row["note"] = row["note"] or "not measured"
        if platform_name != "gpu":
            done = "measured" if row["measured"] is not None else "run"
            where = f"{done} on {platform_name or 'an unknown device'}, not a GPU"
            row["note"] = (row["note"] + "; " if row["note"] else "") + where
    return rows


# ---------------------------------------------------------------------------------------------
# Children: the parts that import JAX, each run in its own process by the steps above.


def child_environment(argv: list) -> int:
    """The machine as the steps' processes see it, written to argv[0] as JSON."""
    path = Path(argv[0])
    start = time.perf_counter()
    import waldo_jax  # noqa: F401  (XLA flags and matmul precision, as every step's process gets them)
    import jax
    import jax.numpy as jnp

    sys.path.insert(0, str(HERE))
    from bench_common import header

    info = header("device_check/environment")
    devices = []
    for d in jax.devices():
        entry = {"id": d.id, "platform": d.platform, "device_kind": getattr(d, "device_kind", str(d))}
        try:
            stats = d.memory_stats() or {}
            entry["memory_stats"] = {k: v for k, v in stats.items() if "bytes" in k}
        except Exception as error:  # not every backend has memory statistics
            entry["memory_stats"] = f"unavailable: {type(error).__name__}"
        devices.append(entry)
    backend_seconds = time.perf_counter() - start
    probe = float(jnp.arange(1000, dtype=jnp.float32).sum())
    nvidia = None
    if shutil.which("nvidia-smi"):
        try:
            nvidia = subprocess.run(
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
            nvidia = f"failed: {error}"
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
            "nvidia_smi": nvidia,
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
    print(
        json.dumps(
            {
                k: info[k]
                for k in (
                    "device",
                    "jax",
                    "jaxlib",
                    "jax_default_matmul_precision",
                    "xla_flags_in_force",
                    "packages_missing",
                )
            }
        )
    )
    return 0


def host_memory() -> Optional[str]:
    try:
        return next(
            line.split(":", 1)[1].strip()
            for line in Path("/proc/meminfo").read_text().splitlines()
            if line.startswith("MemTotal")
        )
    except (OSError, StopIteration):
        return None


def child_pytest(argv: list) -> int:
    """pytest.main on the arguments after '--', every test report appended to argv[0] as a JSON line."""
    import pytest

    class ReportLog:
        """A pytest plugin: one JSON line per test report, written as the controller receives it (so a
        run killed by its time box still tells what it did)."""

        def __init__(self, path: str):
            self.file = open(path, "a", buffering=1)

        def _write(self, event: dict) -> None:
            self.file.write(json.dumps(event) + "\n")

        def pytest_runtest_logreport(self, report):
            if report.when != "call" and report.outcome == "passed":
                return
            event = {
                "event": "report",
                "nodeid": report.nodeid,
                "when": report.when,
                "outcome": report.outcome,
                "duration": round(report.duration, 3),
                "xfail": bool(getattr(report, "wasxfail", "")),
            }
            if report.outcome == "failed":
                event["message"] = str(report.longreprtext)[-2500:]
            elif report.outcome == "skipped":
                longrepr = report.longrepr
                event["message"] = str(longrepr[2] if isinstance(longrepr, tuple) else longrepr)
            self._write(event)

        def pytest_collectreport(self, report):
            if report.failed:
                self._write(
                    {"event": "collect_error", "nodeid": report.nodeid, "message": str(report.longreprtext)[-2500:]}
                )

        def pytest_collection_finish(self, session):
            self._write({"event": "collected", "count": len(session.items)})

        @pytest.hookimpl(optionalhook=True)
        def pytest_xdist_node_collection_finished(self, node, ids):
            self._write({"event": "collected", "count": len(ids)})

        def pytest_sessionfinish(self, session, exitstatus):
            self._write({"event": "finish", "exitstatus": int(exitstatus)})

    path, args = argv[0], argv[argv.index("--") + 1 :]
    return int(pytest.main(args, plugins=[ReportLog(path)]))


def steady_timing(chunks: list) -> dict:
    """ms per step over the chunks that did not compile, as benchmarks/train_step.py: a chunk is steady when
    its (rays marched, warm-up) variant had run before; after the occupancy warm-up when there are such."""
    seen, steady, previous_seconds, previous_step = set(), [], 0.0, 0
    for entry in chunks:
        variant = (entry["rays_marched"], entry["warmup"])
        seconds, steps = entry["seconds"] - previous_seconds, entry["step"] - previous_step
        previous_seconds, previous_step = entry["seconds"], entry["step"]
        if variant in seen and steps > 0:
            steady.append({**entry, "chunk_seconds": seconds, "chunk_steps": steps})
        seen.add(variant)
    main_phase = [c for c in steady if not c["warmup"]] or steady
    if not main_phase:
        return {"ms_per_step": None, "note": "no chunk ran without compiling"}
    seconds = sum(c["chunk_seconds"] for c in main_phase)
    steps = sum(c["chunk_steps"] for c in main_phase)
    return {
        "ms_per_step": 1e3 * seconds / steps,
        "steady_steps_timed": steps,
        "timed_phase": "after the occupancy warm-up" if any(not c["warmup"] for c in steady) else "warm-up",
        "rays_per_step": sum(c["rays"] * c["chunk_steps"] for c in main_phase) / steps,
        "samples_per_step": sum(c["samples"] * c["chunk_steps"] for c in main_phase) / steps,
    }


def child_train(argv: list) -> int:
    """Trains the fox as `waldo train` does (a run folder with checkpoint.ckpt and train.json), timing the
    steady chunks as train_step.py does, then the field's forward and backward pass alone.

    The run is saved as soon as training ends (before the held-out PSNR and the render-step calibration,
    which `train` would do first), so a time box that ends during those still leaves a run for the next
    steps; the JSON is written then, and again complete at the end."""
    parser = argparse.ArgumentParser(prog="device_check.py _train")
    parser.add_argument("scene_path")
    parser.add_argument("--downscale", type=float)
    parser.add_argument("--preset")
    parser.add_argument("--steps", type=int)
    parser.add_argument("--overrides", default="{}")
    parser.add_argument("--train-seconds", type=float)
    parser.add_argument("--run", type=Path)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)

    sys.path.insert(0, str(HERE))
    import waldo_jax  # noqa: F401
    import jax

    from bench_common import header
    from train_step import occupied_points, time_field
    from waldo_jax import io
    from waldo_jax.nerf.checkpoint import CHECKPOINT_NAME, save_checkpoint
    from waldo_jax.nerf.config import TrainConfig
    from waldo_jax.nerf.runs import TRAIN_JSON, load_splits, train_stats
    from waldo_jax.nerf.train import train
    from waldo_jax.nerf.trained import calibrate_render_step, evaluate

    overrides = json.loads(args.overrides)
    hashgrid = overrides.pop("hashgrid", None)
    train_scene, test_scene = load_splits(args.scene_path, args.downscale)
    config = TrainConfig.preset(args.preset, train_scene, steps=args.steps, sampler="occupancy", **overrides)
    if hashgrid:
        field = dataclasses.replace(config.field, hashgrid=dataclasses.replace(config.field.hashgrid, **hashgrid))
        config = config.replace(field=field)
    chunks = []
    stopped_by = ["steps"]

    def on_chunk(state, entry):
        chunks.append(dict(entry))
        if entry["seconds"] >= args.train_seconds and entry["step"] < config.steps:
            stopped_by[0] = f"--train-seconds {args.train_seconds:g}"
            return True
        return False

    def save(result):
        stats = train_stats(result, train_scene, args.preset, 0, args.scene_path)
        save_checkpoint(
            args.run / CHECKPOINT_NAME,
            result.params,
            result.config,
            train_scene,
            result.occupancy,
            info={k: v for k, v in stats.items() if k != "history"},
        )
        io.write_json(args.run / TRAIN_JSON, stats)

    result = train(jax.random.key(0), train_scene, config, None, progress=False, on_chunk=on_chunk)
    args.run.mkdir(parents=True)
    save(result)
    out = header("device_check/training")
    out.update(
        {
            "complete": False,
            "scene_path": str(Path(args.scene_path).resolve()),
            "downscale": train_scene.metadata.get("downscale"),
            "image_size": [train_scene.width, train_scene.height],
            "n_train": train_scene.n_images,
            "n_test": None if test_scene is None else test_scene.n_images,
            "preset": args.preset,
            "steps_planned": config.steps,
            "steps": result.steps,
            "stopped_by": stopped_by[0],
            "train_seconds": result.seconds,
            "compile_seconds": result.compile_seconds,
            "rays_per_second": result.rays_per_second,
            "samples_per_batch": config.samples_per_batch,
            **steady_timing(chunks),
            "run": str(args.run),
            "overrides": json.loads(args.overrides),
            "definitions": {
                "ms_per_step": "wall-clock per step over the chunks that did not compile, after the "
                "occupancy warm-up (as benchmarks/train_step.py)",
                "field_fwd_bwd_ms": "train_step.time_field: value_and_grad of the field alone over "
                "samples_per_batch points in the trained occupied cells",
                "step_over_field": "ms_per_step / field_fwd_bwd_ms",
                "psnr_test": "held-out PSNR at the run's render step (calibrated as `waldo train` "
                "calibrates it), after `steps` steps",
            },
        }
    )
    write_json(args.json, out)
    print(
        f"[training] {result.steps} steps ({stopped_by[0]}) in {result.seconds:.1f} s, "
        f"{out['ms_per_step']} ms/step; saved {args.run}",
        flush=True,
    )

    # What `train` does after training when given the held-out views: calibrate the render step, measure.
    if test_scene is not None:
        start = time.perf_counter()
        scale, curve = result.config.render_step_scale, []
        if scale is None:
            scale, curve = calibrate_render_step(result.params, result.occupancy, result.config, test_scene)
        calibrated = result.config.replace(render_step_scale=scale)
        final = evaluate(result.params, result.occupancy, calibrated, test_scene)
        history = result.history + [
            {
                "step": result.steps,
                "seconds": result.seconds,
                "psnr_test": final["psnr"],
                "render_step_scale": scale,
                "evaluations_per_ray": final["evaluations_per_ray"],
            }
        ]
        result = result._replace(
            config=calibrated,
            psnr_test=final["psnr"],
            render_step_curve=curve,
            psnr_test_training_step=final["psnr"] if scale == 1.0 else None,
            n_test=test_scene.n_images,
            history=history,
        )
        save(result)
        out.update(
            {
                "psnr_test": result.psnr_test,
                "psnr_test_training_step": result.psnr_test_training_step,
                "render_step_scale": scale,
                "render_step_curve": curve,
                "evaluations_per_ray_psnr_views": final["evaluations_per_ray"],
                "psnr_seconds": round(time.perf_counter() - start, 2),
            }
        )
        write_json(args.json, out)
    points = occupied_points(jax.random.key(0), result.occupancy, config.samples_per_batch)
    field = time_field(config, result.params, points, 5)
    out.update(
        {
            **field,
            "complete": True,
            "step_over_field": (None if out["ms_per_step"] is None else out["ms_per_step"] / field["field_fwd_bwd_ms"]),
        }
    )
    write_json(args.json, out)
    print(
        f"[training] field forward+backward {field['field_fwd_bwd_ms']:.2f} ms; held-out PSNR "
        f"{out.get('psnr_test')} dB at step x{out.get('render_step_scale')}",
        flush=True,
    )
    return 0


CHILDREN = {"_environment": child_environment, "_pytest": child_pytest, "_train": child_train}


# ---------------------------------------------------------------------------------------------
# The command.


def parse_args(argv):
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], epilog="Steps: " + ", ".join(f"{s.name} ({s.what})" for s in STEPS)
    )
    parser.add_argument("--out", type=Path, help="output folder (empty or new; the device machine: $OUT)")
    parser.add_argument("--data", type=Path, help="data folder made by --pack (default: $WALDO_DATA or ../shared)")
    parser.add_argument("--work", type=Path, help="run folders and per-step JSONs (default: a new temporary folder)")
    parser.add_argument(
        "--budget",
        type=float,
        default=None,
        help=f"wall-clock seconds for all steps (default {DEFAULT_BUDGET_S:g}; --smoke {SMOKE_BUDGET_S:g})",
    )
    parser.add_argument("--steps", default=",".join(STEP_NAMES), help=f"comma list of {', '.join(STEP_NAMES)}")
    parser.add_argument(
        "--fox-run", type=Path, help="an earlier fox run for rendering/search/gradient (default: the training step's)"
    )
    parser.add_argument("--smoke", action="store_true", help="every step at tiny sizes on the CPU")
    parser.add_argument(
        "--pytest-workers",
        type=int,
        default=None,
        help=f"pytest-xdist workers of the correctness step (default {FULL.pytest_workers}; --smoke 0)",
    )
    parser.add_argument("--force", action="store_true", help="write into a non-empty --out / replace a --pack DIR")
    parser.add_argument(
        "--pack",
        type=Path,
        metavar="DIR",
        help="copy what the steps need from $WALDO_DATA (or "
        "--data-from) into DIR (an ignored folder, e.g. .device/data) and the wheels into --wheels, "
        "check the size, and exit",
    )
    parser.add_argument("--data-from", type=Path, help="--pack: the data folder to copy from (default $WALDO_DATA)")
    parser.add_argument(
        "--wheels",
        type=Path,
        default=REPO / ".whl",
        help="--pack: folder for the wheels the device machine lacks (default .whl)",
    )
    parser.add_argument("--no-wheels", action="store_true", help="--pack: download no wheels")
    parser.add_argument(
        "--limit-mib",
        type=float,
        default=DEFAULT_LIMIT_MIB,
        help=f"--pack: what may travel, code included (default {DEFAULT_LIMIT_MIB:g})",
    )
    parser.add_argument(
        "--reserve-mib",
        type=float,
        default=PACK_RESERVE_MIB,
        help=f"--pack: room kept free under the limit before optional data is added (default {PACK_RESERVE_MIB:g})",
    )
    args = parser.parse_args(argv)
    names = [s.strip() for s in args.steps.split(",") if s.strip()]
    unknown = [n for n in names if n not in STEP_NAMES]
    if unknown or not names:
        parser.error(f"--steps: unknown {', '.join(unknown) or '(none given)'}; choose from {', '.join(STEP_NAMES)}")
    args.step_names = names
    if args.budget is None:
        args.budget = SMOKE_BUDGET_S if args.smoke else DEFAULT_BUDGET_S
    if not args.budget > 0:
        parser.error(f"--budget must be a positive number of seconds, got {args.budget:g}")
    if args.pytest_workers is not None and args.pytest_workers < 0:
        parser.error(f"--pytest-workers must be >= 0, got {args.pytest_workers}")
    if args.pack is None and args.out is None:
        parser.error("give --out DIR (or --pack DIR)")
    if args.fox_run is not None and not (args.fox_run / "checkpoint.ckpt").is_file():
        parser.error(f"--fox-run {args.fox_run}: no checkpoint.ckpt there")
    return args


def default_data() -> Optional[Path]:
    env = os.environ.get("WALDO_DATA")
    if env:
        return Path(env).expanduser()
    shared = REPO.parent / "shared"
    return shared if shared.is_dir() else None


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in CHILDREN:
        return CHILDREN[argv[0]](argv[1:])
    args = parse_args(argv)
    settings = SMOKE if args.smoke else FULL
    if args.pytest_workers is not None:
        settings = dataclasses.replace(settings, pytest_workers=args.pytest_workers)

    if args.pack is not None:
        source = args.data_from or default_data()
        if source is None:
            raise SystemExit("device_check: --pack needs the data: set WALDO_DATA or pass --data-from DIR")
        manifest = pack(
            args.pack,
            source,
            None if args.no_wheels else args.wheels,
            args.limit_mib,
            args.reserve_mib,
            args.force,
            args.smoke,
        )
        sizes = manifest["sizes_mib"]
        print(
            f"[pack] {args.pack}: {sizes['data']} MiB of data, {sizes['wheels']} MiB of wheels, working tree "
            f"{sizes['working_tree']} MiB: {sizes['total']} MiB of {sizes['limit']:g} MiB"
            + (f"; left out: {', '.join(manifest['left_out'])}" if manifest["left_out"] else ""),
            flush=True,
        )
        return 0

    data = args.data or default_data()
    if data is None:
        raise SystemExit("device_check: no data: pass --data DIR (made by --pack) or set WALDO_DATA")
    manifest = check_data(data, settings)
    # Absolute paths: the steps' processes run in the repository root.
    data, out = data.resolve(), args.out.resolve()
    if args.fox_run is not None:
        args.fox_run = args.fox_run.resolve()
    if args.work is not None:
        args.work = args.work.resolve()
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        if not out.is_dir() or not args.force:
            raise SystemExit(
                f"device_check: --out {out} exists and is not empty: refusing to overwrite an earlier "
                "run (choose another --out or pass --force)"
            )
    if args.work is not None and args.work.exists() and (not args.work.is_dir() or any(args.work.iterdir())):
        raise SystemExit(f"device_check: --work {args.work} is not an empty folder (choose a new one)")
    if out.exists():
        for name in OUT_FILES:
            (out / name).unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    work = args.work or Path(tempfile.mkdtemp(prefix="waldo_device_check_"))
    work.mkdir(parents=True, exist_ok=True)
    (work / "steps").mkdir()

    env = dict(os.environ)
    env.update(
        {
            "WALDO_DATA": str(data.resolve()),
            "WALDO_WEIGHTS": str((data / "weights").resolve()),
            "PYTHONUNBUFFERED": "1",
            "PYTHONPATH": os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])]),
        }
    )
    if args.smoke:
        env.update({"JAX_PLATFORMS": "cpu"})
        env.setdefault("WALDO_FAST_COMPILE", "1")

    commit = git_commit()
    digest = code_digest()
    header = {
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
    log = open(out / "device_check.log", "ab", buffering=0)
    ctx = Context(
        settings=settings,
        smoke=args.smoke,
        data=data,
        work=work,
        out=out,
        log=log,
        env=env,
        header=header,
        fox_run=args.fox_run,
    )
    selected = [s for s in STEPS if s.name in args.step_names]
    scale = args.budget / DEFAULT_BUDGET_S
    report = {
        **header,
        "settings": {
            "budget_s": args.budget,
            "smoke": args.smoke,
            "steps": args.step_names,
            **dataclasses.asdict(settings),
            "data": str(data),
            "work": str(work),
        },
        "pack": manifest,
        "outputs": list(OUT_FILES),
        "steps": {},
        "finished": False,
    }
    combined = out / "device_check.json"
    write_json(combined, report)

    previous = signal.signal(signal.SIGTERM, _on_sigterm)
    start = time.monotonic()
    deadline_all = start + args.budget
    interrupted = None
    try:
        for index, step in enumerate(selected):
            left = deadline_all - time.monotonic()
            shares = sum(s.share for s in selected[index:])
            box = left * step.share / shares
            began = time.monotonic()
            if box < 3.0 * scale and not args.smoke:
                entry = {"status": "skipped", "reason": f"no time left in the budget ({left:.0f} s)", "commands": []}
            else:
                print(f"[device_check] step {step.name}: time box {box:.0f} s ({left:.0f} s left)", flush=True)
                try:
                    entry = step.run(ctx, began + box)
                except (KeyboardInterrupt, Interrupted) as error:
                    interrupted = str(error) or "Ctrl-C"
                    entry = {
                        "status": "interrupted",
                        "reason": interrupted,
                        "commands": ctx.results.get("_interrupted_commands", []),
                    }
            entry = {
                **ctx.header,
                "date": now_iso(),
                "benchmark": f"device_check/{step.name}",
                "step": step.name,
                "what": step.what,
                "settings": report["settings"],
                "time_box_s": round(box, 1),
                "seconds": round(time.monotonic() - began, 1),
                "result": None,
                **entry,
            }
            write_json(work / "steps" / f"{index + 1:02d}_{step.name}.json", entry)
            report["steps"][step.name] = entry
            report["device"] = ctx.header["device"]
            report["summary"] = summary(report)
            write_json(combined, report)
            print(
                f"[device_check] step {step.name}: {entry['status']} in {entry['seconds']:.0f} s"
                + (f" ({entry['reason']})" if entry.get("reason") else ""),
                flush=True,
            )
            if interrupted:
                break
    except (KeyboardInterrupt, Interrupted) as error:  # between steps
        interrupted = str(error) or "Ctrl-C"
    finally:
        signal.signal(signal.SIGTERM, previous)
    report.update(
        {
            "finished": interrupted is None,
            "interrupted": interrupted,
            "seconds": round(time.monotonic() - start, 1),
            "summary": summary(report),
        }
    )
    write_json(combined, report)
    log.close()
    print_summary(report)
    if interrupted:
        print(f"[device_check] interrupted ({interrupted}): wrote what was done to {combined}", flush=True)
        return 130
    return 0


def summary(report: dict) -> dict:
    device = report.get("device") or {}
    return {
        "steps": {name: entry["status"] for name, entry in report["steps"].items()},
        "targets": targets(report["steps"], device.get("platform")),
    }


def print_summary(report: dict) -> None:
    device = report.get("device") or {}
    print(
        f"[device_check] {device.get('platform', '?')}:{device.get('device_kind', '?')}, commit "
        f"{report['commit']}, {report.get('seconds', 0):.0f} s; steps: "
        + ", ".join(f"{k} {v}" for k, v in report["summary"]["steps"].items()),
        flush=True,
    )
    for row in report["summary"]["targets"]:
        measured = row["measured"]
        if isinstance(measured, float):
            measured = f"{measured:,.4g}"
        print(
            f"  {'met' if row['met'] else 'NOT met' if row['met'] is False else 'unknown':8} {row['target']}: "
            f"{measured} {row['unit']}".rstrip(),
            flush=True,
        )


if __name__ == "__main__":
    sys.exit(main())

"""Facts every benchmark records: device, commit, date, versions."""

from __future__ import annotations

import datetime
import json
import os
import platform
import statistics
import subprocess
import sys
import time
from pathlib import Path

import jax

REPO = Path(__file__).resolve().parent.parent


def git_commit() -> str:
    """HEAD's hash, with '+dirty' when the working tree has uncommitted changes to tracked files."""
    try:
        head = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True, check=True
        ).stdout.strip()
        dirty = subprocess.run(
            ["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True, text=True
        ).stdout.strip()
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


def refuse_existing_out(out: str | None) -> None:
    """Stops before any measurement when `--out` (or its `_loaded` name, which a shared machine gets)
    already holds an earlier result: results are never overwritten."""
    for path in (out, out and loaded_name(out)):
        if path and Path(path).exists():
            raise SystemExit(f"{path} exists: refusing to overwrite an earlier result (choose another --out)")


def emit(result: dict, out: str | None) -> None:
    text = json.dumps(result, indent=2)
    print(text)
    if out:
        path = Path(out)
        if path.exists():
            raise SystemExit(f"{path} exists: refusing to overwrite an earlier result (choose another --out)")
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text + "\n")


def timed(fn, repeats: int):
    """(best, median, all) seconds of `fn()` over `repeats` runs, after one untimed call (compile, warm-up)."""
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return min(times), statistics.median(times), times


def timed_alternately(fns: dict, repeats: int) -> dict:
    """{name: (best, median, all)} seconds of each `fns[name]()` over `repeats` rounds, after one untimed
    call of each (compile, warm-up). Each round runs every function once, in turn, so a drift in the
    machine's speed (another job, thermal state) falls on all of them alike: use it to compare."""
    for fn in fns.values():
        jax.block_until_ready(fn())
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            jax.block_until_ready(fn())
            times[name].append(time.perf_counter() - start)
    return {name: (min(t), statistics.median(t), t) for name, t in times.items()}


def cold_compile_env() -> dict:
    """The environment for a timed `waldo` child process: the command's persistent compilation cache
    off (`WALDO_COMPILE_CACHE`, unless set), so that a wall time includes its compiles as a first run's
    does, whatever ran before."""
    return {**os.environ, "WALDO_COMPILE_CACHE": os.environ.get("WALDO_COMPILE_CACHE", "off")}


def steady_chunks(chunks: list) -> tuple:
    """The training chunks that ran without compiling, from `train.train`'s `on_chunk` entries (cumulative
    "seconds" and "step", "rays_marched", "warmup"): a chunk is steady when its (rays marched, warm-up)
    variant had run before. Returns (steady, timed): every steady chunk with its own "chunk_seconds" and
    "chunk_steps", and those of them to time, the ones after the occupancy warm-up when there are such."""
    seen, steady, previous_seconds, previous_step = set(), [], 0.0, 0
    for entry in chunks:
        variant = (entry["rays_marched"], entry["warmup"])
        seconds, steps = entry["seconds"] - previous_seconds, entry["step"] - previous_step
        previous_seconds, previous_step = entry["seconds"], entry["step"]
        if variant in seen and steps > 0:
            steady.append({**entry, "chunk_seconds": seconds, "chunk_steps": steps})
        seen.add(variant)
    return steady, [c for c in steady if not c["warmup"]] or steady


# Other processes' mean CPU use over a run (cores) above which it counts as shared, per unit of the
# start's load threshold (so 0.25 cores at the usual 1.0; a test's huge threshold turns both off).
OTHERS_CORES_PER_LOAD = 0.25


def cpu_snapshot() -> dict | None:
    """The machine's busy CPU seconds (/proc/stat: user, nice, system, irq, softirq; steal left out)
    and this process's own and its waited-for children's, with the wall clock; None where /proc/stat
    cannot be read (not Linux)."""
    try:
        fields = Path("/proc/stat").read_text().splitlines()[0].split()
    except OSError:
        return None
    user, nice, system, _idle, _iowait, irq, softirq = (int(x) for x in fields[1:8])
    mine = os.times()
    return {
        "machine_s": (user + nice + system + irq + softirq) / os.sysconf("SC_CLK_TCK"),
        "own_s": mine.user + mine.system + mine.children_user + mine.children_system,
        "wall_s": time.perf_counter(),
    }


def others_cores(start: dict | None) -> float | None:
    """Other processes' mean CPU use (cores) since `start` (`cpu_snapshot`): the machine's busy time
    less this process's and its children's (a child still running when this is called is not counted
    as ours, so call it after waiting for them). None without a snapshot."""
    end = cpu_snapshot()
    if start is None or end is None:
        return None
    wall = max(end["wall_s"] - start["wall_s"], 1e-9)
    others = (end["machine_s"] - start["machine_s"]) - (end["own_s"] - start["own_s"])
    return max(others, 0.0) / wall


def wait_for_quiet(threshold: float, poll_s: float = 30.0, max_wait_s: float = 300.0) -> dict:
    """Polls the 1-minute load average until it is <= threshold or max_wait_s has passed; starts the
    count of other processes' CPU time that `emit_with_load` reads at the end."""
    start = time.perf_counter()
    load = os.getloadavg()
    while load[0] > threshold and time.perf_counter() - start < max_wait_s:
        print(f"load average {load[0]:.2f} > {threshold}: waiting {poll_s:.0f} s", file=sys.stderr, flush=True)
        time.sleep(poll_s)
        load = os.getloadavg()
    return {
        "loadavg_start": list(load),
        "waited_s": round(time.perf_counter() - start, 1),
        "loaded": load[0] > threshold,
        "cpu_start": cpu_snapshot(),
    }


def loaded_name(out: str) -> str:
    """`out` with `_loaded` before its suffix (results measured while other jobs shared the machine)."""
    path = Path(out)
    return str(path.with_name(path.stem + "_loaded" + path.suffix))


def emit_with_load(result: dict, out: str | None, quiet: dict, load_threshold: float) -> None:
    """Adds the load record of `wait_for_quiet` (start, end, other processes' CPU use over the run,
    verdict) to `result` and emits it, under `loaded_name(out)` when the machine was shared: loaded
    at the start, or other processes used more than `OTHERS_CORES_PER_LOAD * load_threshold` cores on
    average during it."""
    others = others_cores(quiet.get("cpu_start"))
    limit = OTHERS_CORES_PER_LOAD * load_threshold
    loaded = bool(quiet["loaded"]) or (others is not None and others > limit)
    result.update(
        {
            "loadavg_start": quiet["loadavg_start"],
            "loadavg_end": list(os.getloadavg()),
            "waited_for_load_s": quiet["waited_s"],
            "others_cores": None if others is None else round(others, 3),
            "loaded": loaded,
            "loaded_rule": (
                f"loaded = 1-min load average still > {load_threshold} after waiting up to 5 min, or other "
                f"processes used > {limit:g} cores on average during the run (/proc/stat busy time less this "
                "process's and its children's)"
            ),
        }
    )
    if out and loaded:
        out = loaded_name(out)
        print(f"the machine was shared during this run: writing {out}", file=sys.stderr)
    emit(result, out)

"""What a compilation-cache folder that holds many programs costs each program written to it.

JAX bounds its persistent cache itself when `jax_compilation_cache_max_size` is set: before every
program it writes, it lists the whole folder and reads each program's last-read time. The `waldo`
command bounds the folder instead once per process (`environment.prune_compile_cache`) and sets no
bound of JAX's. This times, in a child process per mode, `--programs` distinct small programs compiled
and written to a folder already holding `--entries` programs of `--entry-kib` KiB each (made up here:
the listing's cost is per file, not per byte):

  jax_bound      JAX's own bound (1 GiB), as the command did before
  pruned_once    `enable_compile_cache`'s: pruned at the start, no bound of JAX's

  python benchmarks/compile_cache_writes.py --out benchmarks/results/compile_cache_writes_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_common import emit_with_load, header, refuse_existing_out, wait_for_quiet  # noqa: E402

CHILD = r"""
import json, sys, time
from pathlib import Path
import os
os.environ["WALDO_COMPILE_CACHE"] = sys.argv[1]
if sys.argv[2] == "jax_bound":
    os.environ["JAX_COMPILATION_CACHE_MAX_SIZE"] = str(2**30)
import waldo_jax
from waldo_jax.environment import enable_compile_cache
import jax, jax.numpy as jnp
start = time.perf_counter()
enable_compile_cache()
enabled = time.perf_counter() - start
n = int(sys.argv[3])
x = jnp.ones(8)
times = []
for i in range(n):
    f = jax.jit(lambda v, i=i: jnp.sin(v * (i + 1)).sum())
    t = time.perf_counter()
    jax.block_until_ready(f(x))
    times.append(time.perf_counter() - t)
written = len(list(Path(sys.argv[1]).glob("*-cache")))
print(json.dumps({"enable_s": enabled, "compile_and_write_s": times, "programs_in_folder": written}))
"""


def fill(folder: Path, entries: int, entry_kib: int) -> None:
    """`entries` made-up programs with JAX's last-read records, as a folder JAX bounded itself holds."""
    folder.mkdir(parents=True)
    payload = os.urandom(entry_kib * 1024)
    now = time.time_ns()
    for i in range(entries):
        (folder / f"made-up-{i:06d}-cache").write_bytes(payload)
        (folder / f"made-up-{i:06d}-atime").write_bytes((now - i).to_bytes(8, "little"))


def run(mode: str, entries: int, entry_kib: int, programs: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="waldo-cache-bench-") as tmp:
        folder = Path(tmp) / "cache"
        fill(folder, entries, entry_kib)
        env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
        env.pop("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", None)
        start = time.perf_counter()
        result = subprocess.run(
            [sys.executable, "-c", CHILD, str(folder), mode, str(programs)],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        )
        wall = time.perf_counter() - start
        shutil.rmtree(folder, ignore_errors=True)
    child = json.loads(result.stdout.strip().splitlines()[-1])
    times = child["compile_and_write_s"]
    return {
        "mode": mode,
        "process_wall_s": round(wall, 3),
        "enable_s": round(child["enable_s"], 4),
        "programs_s": round(sum(times), 3),
        "per_program_ms_median": round(1000 * sorted(times)[len(times) // 2], 2),
        "programs_in_folder_after": child["programs_in_folder"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--entries", type=int, default=1200, help="programs in the folder before (default 1200)")
    parser.add_argument("--entry-kib", type=int, default=20, help="size of each (default 20 KiB)")
    parser.add_argument("--programs", type=int, default=40, help="programs compiled in each child (default 40)")
    parser.add_argument("--rounds", type=int, default=2, help="each mode this many times, alternately")
    parser.add_argument("--load-threshold", type=float, default=1.0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    refuse_existing_out(args.out)
    quiet = wait_for_quiet(args.load_threshold)
    runs = [
        run(mode, args.entries, args.entry_kib, args.programs)
        for _ in range(args.rounds)
        for mode in ("jax_bound", "pruned_once")
    ]
    by_mode = {m: [r for r in runs if r["mode"] == m] for m in ("jax_bound", "pruned_once")}
    result = {
        **header("compile_cache_writes"),
        "settings": {"entries": args.entries, "entry_kib": args.entry_kib, "programs": args.programs},
        "runs": runs,
        "per_program_ms_median": {m: sorted(r["per_program_ms_median"] for r in rs) for m, rs in by_mode.items()},
        "programs_s_best": {m: min(r["programs_s"] for r in rs) for m, rs in by_mode.items()},
    }
    emit_with_load(result, args.out, quiet, args.load_threshold)


if __name__ == "__main__":
    main()

"""Millions of splats on a CPU: a whole `waldo explore` of synthetic SH-3 splat files, its speed and peak memory.

For each count (`--counts`, default 100k and 1M): `render_splats.synthetic_splats(count, sh_degree=3)`
(uniform in a box, the harder case for a renderer: every view sees every splat, nothing stops early)
written as a reference-layout PLY into a scratch folder, then, in a child process,

  waldo explore PLY --resolution 128 --criterion colorfulness --method egps --budget low --seed 0

(colorfulness: the renderer's cost, not a network's). Per count: the child's wall time, its
results.json phases (`seconds`: load, which renders the 24 ring views exactly and calibrates
`max_pairs` and `tile_chunks`; search), views rendered in the search and views/s, the renderer's
settings (`source_info.renderer`), and the child's peak resident memory (`os.wait4`'s ru_maxrss).

  python benchmarks/splat_scale.py --out benchmarks/results/splat_scale_cpu.json
  python benchmarks/splat_scale.py --counts 3000000 --out benchmarks/results/splat_scale_3m_cpu.json

The JSON names the device, commit and versions; a shared machine's result goes under its `_loaded` name.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)

from bench_common import cold_compile_env, emit_with_load, header, refuse_existing_out, wait_for_quiet  # noqa: E402
from render_splats import synthetic_splats  # noqa: E402
from waldo_jax.splats.io import write_splat_ply  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def measure(count: int, scratch: Path, args) -> dict:
    ply = scratch / f"splats_{count}.ply"
    write_splat_ply(ply, synthetic_splats(count, sh_degree=3), normals=False)
    out = scratch / f"explore_{count}"
    argv = [sys.executable, "-m", "waldo_jax", "explore", str(ply), "--resolution", str(args.resolution)]
    argv += ["--criterion", "colorfulness", "--method", "egps", "--budget", "low", "--seed", "0"]
    argv += ["--quiet", "--out", str(out)]
    start = time.perf_counter()
    env = cold_compile_env()
    child = subprocess.Popen(argv, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - start
    stdout, stderr = child.stdout.read(), child.stderr.read()
    row = {
        "count": count,
        "sh_degree": 3,
        "ply_bytes": ply.stat().st_size,
        "command": " ".join(["waldo", *argv[3:]]),
        "returncode": os.waitstatus_to_exitcode(status),
        "wall_s": round(wall, 1),
        "peak_rss_gib": round(usage.ru_maxrss / 2**20, 3),
    }
    if row["returncode"] != 0:
        row["stderr_tail"] = stderr[-2000:]
        return row
    results = json.loads((out / "results.json").read_text())
    search = results["seconds"]["search"]
    rendered = int(results["n_generated"])
    row.update(
        {
            "seconds": results["seconds"],
            "views_in_search": rendered,
            "views_per_s": round(rendered / search, 3),
            "renderer": results["source_info"]["renderer"],
            "renderer_report": results.get("renderer"),
            "stdout_tail": stdout[-500:],
        }
    )
    ply.unlink()
    return row


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--counts", default="100000,1000000", help="comma-separated splat counts")
    parser.add_argument("--resolution", type=int, default=128)
    parser.add_argument("--load-threshold", type=float, default=1.0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    counts = [int(c) for c in args.counts.split(",") if c]
    refuse_existing_out(args.out)
    quiet = wait_for_quiet(args.load_threshold)
    result = header("splat_scale")
    result["settings"] = {"counts": counts, "resolution": args.resolution}
    rows = []
    with tempfile.TemporaryDirectory() as scratch:
        for count in counts:
            rows.append(measure(count, Path(scratch), args))
            print(
                json.dumps({k: rows[-1].get(k) for k in ("count", "wall_s", "peak_rss_gib", "views_per_s")}),
                file=sys.stderr,
                flush=True,
            )
            if args.out:
                Path(args.out + ".partial").write_text(json.dumps(rows))
    result["rows"] = rows
    emit_with_load(result, args.out, quiet, args.load_threshold)
    if args.out:
        Path(args.out + ".partial").unlink(missing_ok=True)


if __name__ == "__main__":
    main()

"""Whole low-budget explore of the procedural Waldo room at 64x64 on the CPU (target: < 30 s).

For each method (GRS, PIBS, EGPS) and criterion:
  * `cli`: wall clock of `waldo explore procedural --criterion C --method M --budget low --out TMP
    --quiet` as a subprocess: Python start-up, imports, rendering the training views, compiling,
    searching, rendering the top-k and writing every file; the `seconds` split the command itself
    records in results.json is kept too;
  * `in_process`: `load_source` + `run_explore` + `write_outputs` in this process, split into setup
    (building the room and rendering its training views), search (initial scores + the compiled
    search), render of the top-k and writing the files; `cold` is the first call (it compiles),
    `warm` a second identical call (compilation cached).

Criteria: `waldo_oracle` scores poses exactly without rendering (the search itself is what costs);
`colorfulness` is an image criterion, so every generated pose (about 250 of the 275) is rendered by
the room's analytic field at 64x64, 128 samples per ray: render-dominated cost.

The 2 cores may be shared: the 1-minute load average is recorded at start and end; above
`--load-threshold` the script polls every 30 s for up to 5 minutes, then measures anyway and
writes `--out` with a `_loaded` suffix.

  python benchmarks/explore_room.py --out benchmarks/results/explore_room_cpu.json
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

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)

from bench_common import cold_compile_env, emit_with_load, header, wait_for_quiet  # noqa: E402
from waldo_jax.criteria import CriterionContext, make_criterion  # noqa: E402
from waldo_jax.pipeline import load_source, run_explore, write_outputs  # noqa: E402
from waldo_jax.search import ExploreConfig  # noqa: E402
from waldo_jax.search.registry import PAPER_METHODS  # noqa: E402

SOURCE = "procedural"
TARGET_S = 30.0


def waldo_command() -> list:
    found = shutil.which("waldo")
    return [found] if found else [sys.executable, "-m", "waldo_jax"]


def run_cli(criterion: str, method: str, resolution: int, seed: int, scratch: Path) -> dict:
    """Wall clock of one `waldo explore` subprocess and the seconds split it records."""
    out = scratch / f"cli_{criterion}_{method}"
    command = waldo_command() + [
        "explore",
        SOURCE,
        "--criterion",
        criterion,
        "--method",
        method,
        "--budget",
        "low",
        "--seed",
        str(seed),
        "--resolution",
        str(resolution),
        "--out",
        str(out),
        "--quiet",
    ]
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, env=cold_compile_env())
    wall = time.perf_counter() - start
    if done.returncode != 0:
        return {"command": " ".join(command[1:]), "error": done.stderr.strip()[-2000:], "wall_s": round(wall, 3)}
    results = json.loads((out / "results.json").read_text())
    return {
        "command": "waldo " + " ".join(command[-15:]),
        "wall_s": round(wall, 3),
        "recorded_seconds": results["seconds"],
        "n_train": results["n_train"],
        "n_generated": results["n_generated"],
        "cvir": results["cvir"],
        "mcvir": results["mcvir"],
        "stdout": done.stdout.strip().splitlines()[-1] if done.stdout.strip() else "",
    }


def run_in_process(criterion_name: str, method: str, resolution: int, seed: int, out: Path) -> dict:
    """load_source + run_explore + write_outputs, timed by part."""
    start = time.perf_counter()
    source = load_source(SOURCE, resolution)
    criterion = make_criterion(criterion_name, CriterionContext(room=source.room, source=source.spec))
    setup = time.perf_counter() - start
    run = run_explore(source, criterion, ExploreConfig(method=method, budget="low"), seed=seed, setup_seconds=setup)
    written = time.perf_counter()
    out.mkdir()
    results = write_outputs(run, out)
    write = time.perf_counter() - written
    seconds = dict(run.seconds, write_outputs=round(write, 3), total=round(run.seconds["total"] + write, 3))
    return {
        "seconds": seconds,
        "n_train": results["n_train"],
        "n_generated": results["n_generated"],
        "cvir": results["cvir"],
        "mcvir": results["mcvir"],
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--methods", default=",".join(PAPER_METHODS))
    parser.add_argument("--criteria", default="waldo_oracle,colorfulness")
    parser.add_argument("--load-threshold", type=float, default=1.5)
    parser.add_argument("--out", default=None, help="also write the JSON here (never overwrites)")
    args = parser.parse_args(argv)

    quiet = wait_for_quiet(args.load_threshold)
    runs = {}
    with tempfile.TemporaryDirectory(prefix="explore_room_") as tmp:
        scratch = Path(tmp)
        for criterion in args.criteria.split(","):
            runs[criterion] = {}
            for method in args.methods.split(","):
                entry = {"cli": run_cli(criterion, method, args.resolution, args.seed, scratch)}
                for phase in ("cold", "warm"):
                    entry[f"in_process_{phase}"] = run_in_process(
                        criterion, method, args.resolution, args.seed, scratch / f"{phase}_{criterion}_{method}"
                    )
                entry["load_1min_after"] = os.getloadavg()[0]
                runs[criterion][method] = entry
                print(
                    f"{criterion} {method}: cli {entry['cli']['wall_s']:.1f} s, in-process cold "
                    f"{entry['in_process_cold']['seconds']['total']:.1f} s, warm "
                    f"{entry['in_process_warm']['seconds']['total']:.1f} s",
                    file=sys.stderr,
                    flush=True,
                )

    cli_walls = [e["cli"]["wall_s"] for c in runs.values() for e in c.values()]
    result = header("explore_room")
    result.update(
        {
            "source": SOURCE,
            "resolution": args.resolution,
            "budget": "low",
            "seed": args.seed,
            "target_s": TARGET_S,
            "runs": runs,
            "cli_wall_s_max": {c: max(e["cli"]["wall_s"] for e in m.values()) for c, m in runs.items()},
            "all_cli_under_target": all(w < TARGET_S for w in cli_walls),
            "notes": (
                "cli: subprocess wall clock incl. Python start-up, imports, compile and file writing; "
                "in_process seconds: setup = load_source (room + training renders), search = initial scores + "
                "compiled search, render_topk = top-k renders, write_outputs = PNGs, pose cloud, JSON; "
                "cold = first call in this process (compiles), warm = repeated call"
            ),
        }
    )
    emit_with_load(result, args.out, quiet, args.load_threshold)


if __name__ == "__main__":
    main()

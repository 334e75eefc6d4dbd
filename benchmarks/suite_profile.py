"""Where the test suite's time goes: tests, compiles, and programs compiled more than once.

Reads the per-test log that `WALDO_TEST_COMPILE_LOG=FILE python -m pytest -n 2 tests` writes
(tests/conftest.py: one JSON line per test with its wall seconds, JAX's trace / lower / compile
seconds in that process, and every program XLA was asked for with its persistent-cache key), and
reports, per test file and for the run:

- the test-seconds (setup, call and teardown of every test, summed over the workers) and the part
  spent tracing, lowering and compiling in the test process (subprocesses are not seen);
- the programs: asked for, loaded from the run's persistent cache, compiled; distinct cache keys;
  and the *compiled again* ones, a key compiled before in the same run (two workers at once, or a
  program under `JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS`, which is not stored), with their seconds:
  the part of the compile time that sharing could still remove;
- the program names with the most compile seconds, and how many distinct programs each has.

  WALDO_TEST_COMPILE_LOG=/tmp/suite.jsonl python -m pytest -n 2 tests
  python benchmarks/suite_profile.py /tmp/suite.jsonl --wall 1721.2 --out benchmarks/results/suite_profile_cpu.json

`--wall` is the run's wall time as pytest printed it (the log holds test times only); `--tier fast`
marks a run of the fast tier (`-m "not slow"`, target 60 s) instead of the whole suite (480 s).
"""

from __future__ import annotations

import argparse
import collections
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_common import emit, header, refuse_existing_out  # noqa: E402

PHASES = ("jaxpr_trace_duration", "jaxpr_to_mlir_module_duration", "backend_compile_duration")
# The targets on the 2-core CPU: the whole suite, and the fast tier (`-m "not slow"`).
TARGETS_S = {"suite": 480.0, "fast": 60.0}


def read_log(path: Path) -> list:
    """The log's records, one per test (a test run twice, e.g. rerun, keeps both)."""
    if not path.is_file():
        raise SystemExit(f"suite_profile: {path}: no such file (run the suite with WALDO_TEST_COMPILE_LOG={path})")
    records = []
    with path.open() as lines:
        for number, line in enumerate(lines, 1):
            if not line.strip():
                continue
            try:
                record = json.loads(line)
            except json.JSONDecodeError as e:
                raise SystemExit(f"suite_profile: {path}, line {number}: not JSON ({e.msg})") from None
            if not _is_record(record):
                raise SystemExit(f"suite_profile: {path}, line {number}: not a test record")
            records.append(record)
    if not records:
        raise SystemExit(f"suite_profile: {path} holds no test records")
    return records


def _is_record(record) -> bool:
    """A test's line as tests/conftest.py writes it: its node id, and each program as [name, key, hit, seconds]."""
    if not isinstance(record, dict) or not isinstance(record.get("test"), str):
        return False
    programs = record.get("programs", [])
    return isinstance(programs, list) and all(
        isinstance(p, list)
        and len(p) == 4
        and isinstance(p[0], str)
        and isinstance(p[1], str)
        and isinstance(p[2], bool)
        and (p[3] is None or isinstance(p[3], (int, float)))
        for p in programs
    )


def profile(records: list) -> dict:
    """The run's and each file's seconds and program counts (see the module docstring)."""
    files: dict = collections.defaultdict(collections.Counter)
    compiled_keys: dict = collections.Counter()
    by_name: dict = collections.defaultdict(lambda: {"compiled": 0, "seconds": 0.0, "keys": set()})
    totals = collections.Counter()
    for record in records:
        name = record["test"].split("::", 1)[0]
        f = files[name]
        f["tests"] += 1
        f["seconds"] += float(record.get("seconds", 0.0))
        for phase in PHASES:
            f[phase] += float(record.get(phase, 0.0))
        for module, key, hit, seconds in record.get("programs", []):
            f["asked"] += 1
            if hit:
                f["loaded"] += 1
                continue
            seconds = float(seconds or 0.0)
            f["compiled"] += 1
            f["compile_s"] += seconds
            if compiled_keys[key]:
                f["compiled_again"] += 1
                f["compiled_again_s"] += seconds
            compiled_keys[key] += 1
            entry = by_name[module]
            entry["compiled"] += 1
            entry["seconds"] += seconds
            entry["keys"].add(key)
    for f in files.values():
        totals.update(f)
    rows = []
    for name, f in sorted(files.items(), key=lambda item: -item[1]["seconds"]):
        rows.append(
            {
                "file": name,
                "tests": f["tests"],
                "seconds": round(f["seconds"], 1),
                "trace_lower_compile_s": round(sum(f[p] for p in PHASES), 1),
                "programs_compiled": f["compiled"],
                "programs_loaded": f["loaded"],
                "xla_compile_s": round(f["compile_s"], 1),
                "compiled_again": f["compiled_again"],
                "compiled_again_s": round(f["compiled_again_s"], 1),
            }
        )
    names = sorted(by_name.items(), key=lambda item: -item[1]["seconds"])
    return {
        "tests": totals["tests"],
        "test_seconds": round(totals["seconds"], 1),
        "trace_s": round(totals["jaxpr_trace_duration"], 1),
        "lower_s": round(totals["jaxpr_to_mlir_module_duration"], 1),
        "backend_compile_s": round(totals["backend_compile_duration"], 1),
        "programs": {
            "asked": totals["asked"],
            "loaded_from_cache": totals["loaded"],
            "compiled": totals["compiled"],
            "distinct_keys_compiled": len(compiled_keys),
            "compiled_again": totals["compiled_again"],
            "compiled_again_s": round(totals["compiled_again_s"], 1),
            "xla_compile_s": round(totals["compile_s"], 1),
        },
        "files": rows,
        "top_programs": [
            {"name": n, "compiled": e["compiled"], "distinct": len(e["keys"]), "seconds": round(e["seconds"], 1)}
            for n, e in names[:25]
        ],
    }


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("log", type=Path, help="the WALDO_TEST_COMPILE_LOG file of one suite run")
    parser.add_argument("--wall", type=float, default=None, help="the run's wall seconds, as pytest printed them")
    parser.add_argument("--workers", type=int, default=2, help="the run's pytest-xdist workers (-n)")
    parser.add_argument(
        "--tier", choices=sorted(TARGETS_S), default="suite", help='the run: the whole suite, or -m "not slow"'
    )
    parser.add_argument("--commit", default=None, help="the commit the suite ran at (default: this checkout's)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    if args.wall is not None and not args.wall > 0:
        raise SystemExit(f"suite_profile: --wall must be a positive number of seconds, not {args.wall}")
    if args.workers < 1:
        raise SystemExit(f"suite_profile: --workers must be at least 1, not {args.workers}")
    refuse_existing_out(args.out)
    result = header("suite_profile")
    if args.commit:
        result["commit"] = args.commit
    target_s = TARGETS_S[args.tier]
    result["settings"] = {
        "log": str(args.log),
        "tier": args.tier,
        "workers": args.workers,
        "wall_s": args.wall,
        "target_s": target_s,
    }
    result.update(profile(read_log(args.log)))
    # The target's arithmetic: the wall time allows `workers` x target test-seconds at best.
    result["target_test_seconds"] = args.workers * target_s
    emit(result, args.out)
    return result


if __name__ == "__main__":
    main()

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

This file is the driver: the command line, --pack, the time box, the steps in order, the JSON. Each step
is a module of benchmarks/device_steps/ (its `step(ctx, deadline)`, and its `child(argv)` where it runs
JAX or pytest in a process of its own: `device_check.py _environment | _pytest | _train`); the sizes are
in device_steps/settings.py, --pack in device_steps/pack.py, the targets in device_steps/targets.py.
The parent process never imports JAX: a GPU stays free for the steps' processes.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import signal
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

from device_steps import correctness, determinism, environment, gradient, rendering, search, splats, training
from device_steps.common import REPO, Context, Interrupted, now_iso, on_sigterm, write_json
from device_steps.pack import DEFAULT_LIMIT_MIB, PACK_RESERVE_MIB, check_data, default_data, pack
from device_steps.settings import FULL, SMOKE, Settings
from device_steps.targets import targets

DEFAULT_BUDGET_S = 540.0
SMOKE_BUDGET_S = 1800.0  # --smoke on a shared 2-core CPU: the boxes are the GPU's, the CPU needs ~3x
OUT_FILES = ("device_check.json", "device_check.log", "pytest_reports.jsonl")


@dataclasses.dataclass(frozen=True)
class Step:
    """One step of the check: `share` is its time box in seconds of the default budget (scaled with
    --budget; time a step leaves unused goes to the steps after it, in proportion to their shares)."""

    name: str
    share: float
    run: Callable[[Context, float], dict]
    what: str


STEPS = (
    Step("environment", 20, environment.step, "devices, memory, XLA flags, matmul precision, packages"),
    Step("correctness", 130, correctness.step, "pytest: the files that failed on a GPU before, then the rest"),
    Step("determinism", 75, determinism.step, "same-seed explore twice: byte-identical; WALDO_DETERMINISTIC=0 time"),
    Step("training", 90, training.step, "fox, quality preset: ms/step, field fwd+bwd, step/field, held-out PSNR"),
    Step("rendering", 100, rendering.step, "render_trained.py on the fox run; render_population.py per size"),
    Step("search", 85, search.step, "waldo explore on the fox run (EGPS, saliency, low budget) per resolution"),
    Step("gradient", 40, gradient.step, "gradient_cost.py, the fox run's case included"),
    Step(
        "splats",
        60,
        splats.step,
        "render_splats.py: 100k and 1M splats at 128^2 / 256^2, 256 poses; the donut explored",
    ),
)
STEP_NAMES = tuple(step.name for step in STEPS)
# The parts that import JAX (or pytest), each run in its own process by a step: `device_check.py _train ...`.
CHILDREN = {"_environment": environment.child, "_pytest": correctness.child, "_train": training.child}


# ---------------------------------------------------------------------------------------------
# The command line.


def parse_args(argv):
    """The command line, checked: one-line errors for unknown steps, a bad budget, a missing --out."""
    parser = _parser()
    args = parser.parse_args(argv)
    names = [s.strip() for s in args.steps.split(",") if s.strip()]
    unknown = [n for n in names if n not in STEP_NAMES]
    error = parser.error
    if unknown or not names:
        error(f"--steps: unknown {', '.join(unknown) or '(none given)'}; choose from {', '.join(STEP_NAMES)}")
    args.step_names = names
    if args.budget is None:
        args.budget = SMOKE_BUDGET_S if args.smoke else DEFAULT_BUDGET_S
    if not args.budget > 0:
        error(f"--budget must be a positive number of seconds, got {args.budget:g}")
    if args.pytest_workers is not None and args.pytest_workers < 0:
        error(f"--pytest-workers must be >= 0, got {args.pytest_workers}")
    if args.pack is None and args.out is None:
        error("give --out DIR (or --pack DIR)")
    if args.fox_run is not None and not (args.fox_run / "checkpoint.ckpt").is_file():
        error(f"--fox-run {args.fox_run}: no checkpoint.ckpt there")
    return args


def _parser() -> argparse.ArgumentParser:
    """The flags of the check and of --pack."""
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
    return parser


# ---------------------------------------------------------------------------------------------
# The command: --pack, or the steps in order within the budget.


def main(argv=None) -> int:
    """The device check (or one of its children, by name); returns the exit status (130 when interrupted)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv and argv[0] in CHILDREN:
        return CHILDREN[argv[0]](argv[1:])
    args = parse_args(argv)
    settings = SMOKE if args.smoke else FULL
    if args.pytest_workers is not None:
        settings = dataclasses.replace(settings, pytest_workers=args.pytest_workers)
    if args.pack is not None:
        return run_pack(args)
    return run_check(args, settings)


def run_pack(args: argparse.Namespace) -> int:
    """--pack: copies the data (and downloads the wheels) and prints the sizes against the limit."""
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


def run_check(args: argparse.Namespace, settings: Settings) -> int:
    """The selected steps in order, each in its time box; device_check.json rewritten after each."""
    data, out, work, manifest = _folders(args, settings)
    header = environment.run_header(manifest)
    log = open(out / "device_check.log", "ab", buffering=0)
    ctx = Context(
        settings=settings,
        smoke=args.smoke,
        data=data,
        work=work,
        out=out,
        log=log,
        env=_child_env(data, args.smoke),
        header=header,
        fox_run=args.fox_run,
    )
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
    start = time.monotonic()
    interrupted = _run_steps(ctx, [s for s in STEPS if s.name in args.step_names], report, args.budget)
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


def _folders(args: argparse.Namespace, settings: Settings) -> tuple:
    """(data, out, work, the pack's manifest): checked, absolute (the steps' processes run in the repository
    root), --out emptied of an earlier run's files under --force, --work new."""
    data = args.data or default_data()
    if data is None:
        raise SystemExit("device_check: no data: pass --data DIR (made by --pack) or set WALDO_DATA")
    manifest = check_data(data, settings)
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
    return data, out, work, manifest


def _child_env(data: Path, smoke: bool) -> dict:
    """The environment of the steps' processes: the data and weights, the repository on PYTHONPATH, the
    `waldo` command's compilation cache off (each step's compiles timed cold, and the determinism step's
    second run compiled again, not loaded; unless WALDO_COMPILE_CACHE is set)."""
    env = dict(os.environ)
    env.setdefault("WALDO_COMPILE_CACHE", "off")
    env.update(
        {
            "WALDO_DATA": str(data.resolve()),
            "WALDO_WEIGHTS": str((data / "weights").resolve()),
            "PYTHONUNBUFFERED": "1",
            "PYTHONPATH": os.pathsep.join([str(REPO), *filter(None, [env.get("PYTHONPATH")])]),
        }
    )
    if smoke:
        env.update({"JAX_PLATFORMS": "cpu"})
        env.setdefault("WALDO_FAST_COMPILE", "1")
    return env


def _run_steps(ctx: Context, selected: list, report: dict, budget: float):
    """Runs `selected` in order within `budget` seconds, each step's box its share of the time left;
    writes each step's JSON (work/steps/NN_name.json and the report) as it ends. Returns why it was
    interrupted (Ctrl-C, SIGTERM), or None."""
    scale = budget / DEFAULT_BUDGET_S
    previous = signal.signal(signal.SIGTERM, on_sigterm)
    deadline_all = time.monotonic() + budget
    interrupted = None
    try:
        for index, step in enumerate(selected):
            left = deadline_all - time.monotonic()
            box = left * step.share / sum(s.share for s in selected[index:])
            began = time.monotonic()
            if box < 3.0 * scale and not ctx.smoke:
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
            _record(ctx, report, index, step, box, began, entry)
            if interrupted:
                break
    except (KeyboardInterrupt, Interrupted) as error:  # between steps
        interrupted = str(error) or "Ctrl-C"
    finally:
        signal.signal(signal.SIGTERM, previous)
    return interrupted


def _record(ctx: Context, report: dict, index: int, step: Step, box: float, began: float, entry: dict) -> None:
    """A step's JSON: the run's header, the step's name, box and seconds, then what the step returned;
    written into work/steps and into the report (rewritten with its summary)."""
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
    write_json(ctx.work / "steps" / f"{index + 1:02d}_{step.name}.json", entry)
    report["steps"][step.name] = entry
    report["device"] = ctx.header["device"]
    report["summary"] = summary(report)
    write_json(ctx.out / "device_check.json", report)
    print(
        f"[device_check] step {step.name}: {entry['status']} in {entry['seconds']:.0f} s"
        + (f" ({entry['reason']})" if entry.get("reason") else ""),
        flush=True,
    )


def summary(report: dict) -> dict:
    """Each step's status and the issue's targets as target / measured / met."""
    device = report.get("device") or {}
    return {
        "steps": {name: entry["status"] for name, entry in report["steps"].items()},
        "targets": targets(report["steps"], device.get("platform")),
    }


def print_summary(report: dict) -> None:
    """The device, the commit, each step's status and each target, as lines on stdout."""
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

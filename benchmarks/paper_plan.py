"""`paper_tables.py --plan`: the work a protocol asks for and its expected time on THIS device.

Nothing of the protocol is run and nothing is written: the plan counts the work (NeRFs to train, and
per cell the renders its budget costs, `ExploreConfig.cost`, times the seeds), then times a small
sample of it on the device it runs on and multiplies:

  * training: a probe NeRF of each kind the protocol would train (the real scenes' preset; the room's
    fast recipe) is trained for `--plan-steps` steps in a scratch folder; a NeRF costs its steps times
    the probe's steady seconds per step (the rays trained per step over its steady rays per second),
    plus the probe's compile time;
  * cells: with the probe NeRF of the first scene, one EGPS cell per criterion at the first budget
    (the real resolution, seeds and children per epoch, but one epoch) runs once: JAX's compile
    events during it (tracing, lowering, XLA) are the cell's compilation, the rest over its renders
    the cell's rate. A cell
    costs that compilation plus its renders at that rate, scaled by its scene's pixels per render.

The probe NeRF is briefly trained, so its occupancy grid is still nearly full: its renders march more
samples than a trained NeRF's, and the render part of the plan is an upper bound. Other methods are
assumed to cost what EGPS costs per render (their cost in renders already counts refinement). Not
counted: the Waldo-room table's cells (pose oracles, no render: seconds) and the figures.
The plan then cuts the protocol into parts of at most `--plan-part-minutes` (default 10: the device's
limit per command), one `--scenes S --criteria C [--budgets B]` run each, and prints their commands.
"""

from __future__ import annotations

import copy
import math
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Dict, List, Sequence

import jax


def _n_train(scene: str, args, room: str, train_split: Callable) -> int:
    return int(args.room_views) if scene == room else int(train_split(scene).n_images)


def _cells(scene: str, n_train: int, criteria, methods, budgets, args, children) -> List[Dict[str, Any]]:
    """Every (criterion, budget, method) cell of one scene with the renders it costs over all seeds."""
    from waldo_jax.search import ExploreConfig

    out = []
    for criterion in criteria:
        for budget in budgets:
            for method in methods:
                config = ExploreConfig(
                    method=method,
                    budget=budget,
                    epochs=args.epochs,
                    top_k=args.top_k,
                    children_per_epoch=int(children[budget]) if budget in children else None,
                )
                cost = config.cost(n_train)
                renders = (cost["renders"] - cost["training_views"]) * args.seeds
                if args.initial == "renders":
                    renders += n_train
                out.append(
                    {
                        "scene": scene,
                        "criterion": criterion,
                        "budget": budget,
                        "method": method,
                        "renders": int(renders),
                    }
                )
    return out


_COMPILE_EVENTS = (
    "/jax/core/compile/backend_compile_duration",
    "/jax/core/compile/jaxpr_to_mlir_module_duration",
    "/jax/core/compile/jaxpr_trace_duration",
)


def _probe_cells(source, criteria, budget: str, args, children) -> Dict[str, Dict[str, float]]:
    """Per criterion: the compile seconds and the seconds per render of one EGPS cell on this device.

    One call per criterion; JAX's compile events (tracing, lowering, XLA compilation) during it are its
    compile time, the rest is its run time.
    """
    from jax import monitoring

    from paper_cells import explore_cell
    from waldo_jax.criteria import CriterionContext, build_criterion
    from waldo_jax.search import ExploreConfig

    compiling: List[float] = []

    def listen(event: str, seconds: float, **_) -> None:
        if event in _COMPILE_EVENTS:
            compiling.append(seconds)

    context = CriterionContext(room=source.room, weights_dir=args.weights, source=source.spec)
    # The budget's children per epoch (the batch each epoch renders), but one epoch: the scan compiles
    # its body once whatever the epochs, and a render costs the same in any epoch.
    config = ExploreConfig(
        method="egps",
        budget=budget,
        epochs=args.epochs,
        top_k=args.top_k,
        children_per_epoch=int(children[budget]) if budget in children else None,
    )
    probe_args = copy.copy(args)
    probe_args.epochs = 1
    probe_children = dict(children, **{budget: config.resolve(source.n_train).children_per_epoch})
    rates = {}
    monitoring.register_event_duration_secs_listener(listen)
    try:
        for name in criteria:
            criterion = build_criterion(name, context)
            compiling.clear()
            start = time.perf_counter()
            run = explore_cell(source, criterion, "egps", budget, probe_args, probe_children)
            total = time.perf_counter() - start
            compile_s = min(sum(compiling), total)
            renders = run.config.epochs * run.config.children_per_epoch * len(run.seeds)
            if args.initial == "renders":
                renders += source.n_train  # the training poses were rendered too
            rates[name] = {
                "compile_s": compile_s,
                "seconds_per_render": (total - compile_s) / max(renders, 1),
                "probe_renders": renders,
                "probe_seconds": round(total, 3),
            }
    finally:
        monitoring.unregister_event_duration_listener(listen)
    return rates


def _train_probe(kind: str, train: Callable[[Path], Dict[str, Any]], scratch: List[Path]) -> Dict[str, Any]:
    """Trains a probe NeRF with `train(run_dir)` in a scratch folder (listed in `scratch` at once, so it is
    removed whatever happens). Its seconds per step: the fastest chunk's (a chunk that compiled is
    slower by its compilation); its compile time: what the chunks took beyond that rate."""
    folder = Path(tempfile.mkdtemp(prefix=f"waldo-plan-{kind}-"))
    scratch.append(folder)
    stats = train(folder / "run")
    chunks, done, elapsed = [], 0, 0.0
    for entry in stats["history"]:
        if "loss" not in entry:  # a held-out evaluation, not a chunk
            continue
        chunks.append((entry["step"] - done, entry["seconds"] - elapsed))
        done, elapsed = entry["step"], entry["seconds"]
    per_step = min((t / n for n, t in chunks if n > 0), default=float("nan"))
    compile_s = sum(max(t - n * per_step, 0.0) for n, t in chunks)
    return {
        "run_dir": folder / "run",
        "seconds_per_step": per_step,
        "compile_s": compile_s,
        "steps": stats.get("steps"),
        "seconds": stats.get("seconds"),
        "chunks": len(chunks),
    }


def _parts(cells: Sequence[Dict[str, Any]], limit_s: float) -> List[Dict[str, Any]]:
    """Cells grouped into runs of one scene and criterion (split by budget when that is too long)."""
    groups: Dict[tuple, List[Dict[str, Any]]] = {}
    for cell in cells:
        groups.setdefault((cell["scene"], cell["criterion"]), []).append(cell)
    parts = []
    for (scene, criterion), members in groups.items():
        seconds = sum(c["seconds"] for c in members)
        if seconds <= limit_s:
            parts.append({"scene": scene, "criterion": criterion, "budgets": None, "seconds": seconds})
            continue
        for budget in dict.fromkeys(c["budget"] for c in members):
            share = sum(c["seconds"] for c in members if c["budget"] == budget)
            parts.append(
                {
                    "scene": scene,
                    "criterion": criterion,
                    "budgets": budget,
                    "seconds": share,
                    "over_limit": share > limit_s,
                }
            )
    return parts


def plan(
    args,
    scenes,
    criteria,
    methods,
    budgets,
    children,
    downscale,
    *,
    room: str,
    run_dir_of: Callable[[str], Path],
    train_real: Callable,
    train_room: Callable,
    say: Callable[[str], None],
) -> Dict[str, Any]:
    """The plan (see the module docstring): printed, and returned as a dict."""
    from waldo_jax.nerf.checkpoint import CHECKPOINT_NAME
    from waldo_jax.nerf.config import TrainConfig
    from waldo_jax.nerf.runs import TRAIN_JSON, load_splits
    from waldo_jax.paths import scene_path
    from waldo_jax.pipeline import run_source

    t0 = time.perf_counter()
    device = str(jax.devices()[0].device_kind)
    scratch: List[Path] = []
    splits: Dict[str, Any] = {}

    def train_split(scene: str):
        """A real scene's training split, read once per plan (its count, step preset and aspect use it)."""
        if scene not in splits:
            splits[scene] = load_splits(str(scene_path(scene)), downscale.get(scene), stacklevel=3)[0]
        return splits[scene]

    try:
        work = {}
        for scene in scenes:
            n_train = _n_train(scene, args, room, train_split)
            reused = (run_dir_of(scene) / CHECKPOINT_NAME).exists()
            steps = None
            if not reused:
                if scene == room:
                    steps = int(args.room_steps)
                elif args.train_steps is not None:
                    steps = int(args.train_steps)
                else:
                    steps = TrainConfig.preset(args.preset, train_split(scene)).steps
            work[scene] = {
                "n_train": n_train,
                "reused": reused,
                "train_steps": steps,
                "cells": _cells(scene, n_train, criteria, methods, budgets, args, children),
            }

        # Probes: one short training per kind of NeRF that is trained; the cells' rates on the first scene.
        probes: Dict[str, Dict[str, Any]] = {}
        first = scenes[0]
        probe_args = copy.copy(args)
        probe_args.train_steps = probe_args.room_steps = int(args.plan_steps)
        probe_args.progress = False
        for scene in scenes:
            kind = "room" if scene == room else "real"
            if kind in probes or work[scene]["reused"]:  # a reused first scene's cells are timed on its own NeRF
                continue
            say(f"plan: training a {kind} probe NeRF ({args.plan_steps} steps) ...")
            if kind == "room":
                probes[kind] = _train_probe(kind, lambda d: _stats(train_room(d, probe_args), d, TRAIN_JSON), scratch)
            else:
                probes[kind] = _train_probe(
                    kind,
                    lambda d, s=scene: _stats(train_real(s, d, probe_args, downscale.get(s)), d, TRAIN_JSON),
                    scratch,
                )
        first_kind = "room" if first == room else "real"
        probe_dir = run_dir_of(first) if work[first]["reused"] else probes[first_kind]["run_dir"]
        source = run_source(str(probe_dir), args.resolution)
        pixels_first = source.intrinsics.width * source.intrinsics.height
        say(f"plan: timing one EGPS cell per criterion on {first} ({args.seeds} seeds, {budgets[0]} budget) ...")
        rates = _probe_cells(source, criteria, budgets[0], args, children) if criteria else {}

        # Pixels per render of the other scenes (their aspect at --resolution).
        pixels = {first: pixels_first}
        for scene in scenes[1:]:
            if work[scene]["reused"]:
                other = run_source(str(run_dir_of(scene)), args.resolution).intrinsics
            elif scene == room:
                other = None  # the room renders square
            else:
                other = train_split(scene).intrinsics
            if other is None:
                pixels[scene] = args.resolution**2
            else:
                w, h = int(other.width), int(other.height)
                s = args.resolution / max(w, h)
                pixels[scene] = max(1, round(w * s)) * max(1, round(h * s))

        rows, all_cells = [], []
        for scene in scenes:
            entry = work[scene]
            kind = "room" if scene == room else "real"
            train_s = 0.0
            if not entry["reused"]:
                probe = probes.get(kind)
                train_s = entry["train_steps"] * probe["seconds_per_step"] + probe["compile_s"]
            compiles = sum(rates[c["criterion"]]["compile_s"] for c in entry["cells"]) if rates else 0.0
            for cell in entry["cells"]:
                rate = rates[cell["criterion"]]
                cell["seconds"] = rate["compile_s"] + rate["seconds_per_render"] * cell["renders"] * (
                    pixels[scene] / pixels_first
                )
                all_cells.append(cell)
            cells_s = sum(c["seconds"] for c in entry["cells"])
            rows.append(
                {
                    "scene": scene,
                    "n_train": entry["n_train"],
                    "nerf": "reused" if entry["reused"] else f"train {entry['train_steps']} steps",
                    "train_s": train_s,
                    "cells": len(entry["cells"]),
                    "renders": sum(c["renders"] for c in entry["cells"]),
                    "compile_s": compiles,
                    "cells_s": cells_s,
                    "pixels_per_render": pixels[scene],
                }
            )
        total = sum(r["train_s"] + r["cells_s"] for r in rows)
        limit = 60.0 * float(args.plan_part_minutes)
        parts = _parts(all_cells, limit)
        text = _text(rows, rates, probes, parts, total, device, args, limit)
        print(text)
        return {
            "device": device,
            "rows": rows,
            "rates": rates,
            "parts": parts,
            "total_s": total,
            "probes": {k: {n: v for n, v in p.items() if n != "run_dir"} for k, p in probes.items()},
            "plan_seconds": time.perf_counter() - t0,
            "text": text,
        }
    finally:
        for folder in scratch:
            shutil.rmtree(folder, ignore_errors=True)


def _stats(_, run_dir: Path, train_json: str) -> Dict[str, Any]:
    import json

    return json.loads((run_dir / train_json).read_text())


def _minutes(seconds: float) -> str:
    return "n/a" if not math.isfinite(seconds) else f"{seconds / 60:.1f} min"


def _text(rows, rates, probes, parts, total, device, args, limit) -> str:
    lines = [
        f"Plan on {device} ({jax.default_backend()}): {args.seeds} seeds, {args.resolution} px, "
        f"preset {args.preset}; probes of {args.plan_steps} training steps.",
        "",
        "| scene | training views | NeRF | training | cells | renders | of which compiling | cells time |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:
        lines.append(
            f"| {r['scene']} | {r['n_train']} | {r['nerf']} | {_minutes(r['train_s'])} | {r['cells']} | "
            f"{r['renders']:,} | {_minutes(r['compile_s'])} | {_minutes(r['cells_s'])} |"
        )
    lines.append(
        f"\nExpected total on this device: {_minutes(total)} (an upper bound for the renders: the probe "
        "NeRF's grid is still nearly full)."
    )
    for kind, p in probes.items():
        lines.append(
            f"  {kind} NeRF probe: {p['seconds_per_step'] * 1e3:.1f} ms per steady step, "
            f"{p['compile_s']:.1f} s compiling"
        )
    for name, r in rates.items():
        lines.append(
            f"  {name}: {r['compile_s']:.1f} s compiling per cell, {r['seconds_per_render'] * 1e3:.1f} ms per render"
        )
    lines.append(
        f"\nParts of at most {limit / 60:.0f} minutes: the NeRFs first (`--criteria none --no-waldo` trains a "
        "scene's NeRF into --runs), then one run per part; `--tables-from` joins the JSONs:"
    )
    for r in rows:
        if r["train_s"] > 0:
            warn = (
                "  # longer than a part: fewer --train-steps, or a machine with a longer limit"
                if (r["train_s"] > limit)
                else ""
            )
            lines.append(
                f"  python benchmarks/paper_tables.py --scenes {r['scene']} --criteria none --no-waldo "
                f"--out runs/paper_{r['scene']}_nerf.json ...  # {_minutes(r['train_s'])}{warn}"
            )
    for part in parts:
        budgets = f" --budgets {part['budgets']}" if part["budgets"] else ""
        warn = "  # longer than a part: fewer seeds or a smaller --resolution" if part.get("over_limit") else ""
        lines.append(
            f"  python benchmarks/paper_tables.py --scenes {part['scene']} --criteria {part['criterion']}"
            f"{budgets} --no-waldo --out runs/paper_{part['scene']}_{part['criterion']}"
            f"{'_' + part['budgets'] if part['budgets'] else ''}.json ...  # {_minutes(part['seconds'])}{warn}"
        )
    return "\n".join(lines)

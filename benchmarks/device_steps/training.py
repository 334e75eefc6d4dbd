"""The training step: the fox, quality preset, a fixed number of steps into a run folder the later steps
reuse (rendering, search, gradient): ms_per_step, field_fwd_bwd_ms and step_over_field (as
benchmarks/train_step.py), held-out PSNR at the calibrated render step.

The `_train` child trains as `waldo train` does and saves the run as soon as training ends, so a time box
that ends during the held-out PSNR still leaves a run for the next steps.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

from .common import HERE, Context, command_status, read_json, write_json

DEFINITIONS = {
    "ms_per_step": "wall-clock per step over the chunks that did not compile, after the "
    "occupancy warm-up (as benchmarks/train_step.py)",
    "field_fwd_bwd_ms": "train_step.time_field: value_and_grad of the field alone over "
    "samples_per_batch points in the trained occupied cells",
    "step_over_field": "ms_per_step / field_fwd_bwd_ms",
    "psnr_test": "held-out PSNR at the run's render step (calibrated as `waldo train` "
    "calibrates it), after `steps` steps",
}


def step(ctx: Context, deadline: float) -> dict:
    """The fox trained by the `_train` child within the step's box; its run folder is the later steps'."""
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


def steady_timing(chunks: list) -> dict:
    """ms per step over the chunks that did not compile (`bench_common.steady_chunks`, as
    benchmarks/train_step.py): after the occupancy warm-up when there are such."""
    from bench_common import steady_chunks  # benchmarks/ is on the child's path (`child`)

    steady, main_phase = steady_chunks(chunks)
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


# ---------------------------------------------------------------------------------------------
# The child: trains in its own process.


def child(argv: list) -> int:
    """Trains the fox as `waldo train` does (a run folder with checkpoint.ckpt and train.json), timing the
    steady chunks as train_step.py does, then the field's forward and backward pass alone.

    The run is saved as soon as training ends (before the held-out PSNR and the render-step calibration,
    which `train` would do first), so a time box that ends during those still leaves a run for the next
    steps; the JSON is written then, and again complete at the end."""
    args = _parse_child(argv)
    sys.path.insert(0, str(HERE))
    import waldo_jax  # noqa: F401
    import jax

    from waldo_jax.nerf.runs import load_splits
    from waldo_jax.nerf.train import train

    train_scene, test_scene = load_splits(args.scene_path, args.downscale)
    config = _config(args, train_scene)
    chunks = []
    stopped_by = ["steps"]

    def on_chunk(state, entry):
        chunks.append(dict(entry))
        if entry["seconds"] >= args.train_seconds and entry["step"] < config.steps:
            stopped_by[0] = f"--train-seconds {args.train_seconds:g}"
            return True
        return False

    result = train(jax.random.key(0), train_scene, config, None, progress=False, on_chunk=on_chunk)
    args.run.mkdir(parents=True)
    _save(args, result, train_scene)
    out = _trained_json(args, result, (train_scene, test_scene), config, chunks, stopped_by[0])
    write_json(args.json, out)
    print(
        f"[training] {result.steps} steps ({stopped_by[0]}) in {result.seconds:.1f} s, "
        f"{out['ms_per_step']} ms/step; saved {args.run}",
        flush=True,
    )
    if test_scene is not None:
        result = _held_out(args, result, train_scene, test_scene, out)
    _time_field(args, result, config, out)
    return 0


def _parse_child(argv: list) -> argparse.Namespace:
    """The `_train` child's arguments (the step passes them all)."""
    parser = argparse.ArgumentParser(prog="device_check.py _train")
    parser.add_argument("scene_path")
    parser.add_argument("--downscale", type=float)
    parser.add_argument("--preset")
    parser.add_argument("--steps", type=int)
    parser.add_argument("--overrides", default="{}")
    parser.add_argument("--train-seconds", type=float)
    parser.add_argument("--run", type=Path)
    parser.add_argument("--json", type=Path)
    return parser.parse_args(argv)


def _config(args: argparse.Namespace, train_scene):
    """The preset's TrainConfig with the settings' overrides (a `hashgrid` override replaces its fields)."""
    from waldo_jax.nerf.config import TrainConfig

    overrides = json.loads(args.overrides)
    hashgrid = overrides.pop("hashgrid", None)
    config = TrainConfig.preset(args.preset, train_scene, steps=args.steps, sampler="occupancy", **overrides)
    if hashgrid:
        field = dataclasses.replace(config.field, hashgrid=dataclasses.replace(config.field.hashgrid, **hashgrid))
        config = config.replace(field=field)
    return config


def _save(args: argparse.Namespace, result, train_scene) -> None:
    """The run folder as `waldo train` writes it: checkpoint.ckpt and train.json."""
    from waldo_jax import io
    from waldo_jax.nerf.checkpoint import CHECKPOINT_NAME, save_checkpoint
    from waldo_jax.nerf.runs import TRAIN_JSON, train_stats

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


def _trained_json(args: argparse.Namespace, result, scenes: tuple, config, chunks: list, stopped_by: str) -> dict:
    """The step's JSON as training ends (`complete` False until the field is timed)."""
    from bench_common import header

    train_scene, test_scene = scenes
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
            "stopped_by": stopped_by,
            "train_seconds": result.seconds,
            "compile_seconds": result.compile_seconds,
            "rays_per_second": result.rays_per_second,
            "samples_per_batch": config.samples_per_batch,
            **steady_timing(chunks),
            "run": str(args.run),
            "overrides": json.loads(args.overrides),
            "definitions": DEFINITIONS,
        }
    )
    return out


def _held_out(args: argparse.Namespace, result, train_scene, test_scene, out: dict):
    """What `train` does after training when given the held-out views: calibrate the render step, measure
    the PSNR; saves the run again and adds both to `out`. Returns the result with them."""
    from waldo_jax.nerf.trained import calibrate_render_step, evaluate

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
    _save(args, result, train_scene)
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
    return result


def _time_field(args: argparse.Namespace, result, config, out: dict) -> None:
    """The field's forward and backward pass alone (train_step.time_field) on points in the occupied cells;
    writes `out` complete."""
    import jax

    from train_step import occupied_points, time_field

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

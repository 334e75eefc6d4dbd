"""Training quality against wall clock: held-out PSNR at a few training-time checkpoints.

Trains an Instant-NGP field on a scene exactly as `waldo train` does (`train.train`, the preset's
config; the same key gives the same parameters), and after each chunk whose training time crosses
one of `--eval-at` seconds, renders the held-out split and records its PSNR (`train`'s `on_chunk`).
Evaluations pause the clock: the seconds reported are training seconds (compilation included, as in
`waldo train`). Training stops at `--steps` (default: the preset's) or once `--seconds` of training
have passed, whichever comes first; the learning-rate decay follows `--steps`, so choose a step
count that fits the budget. The final PSNR is rendered as the run renders (its calibrated
`render_step_scale`), as `waldo train` reports it.

The held-out split is the one `waldo train` uses: Blender's test split, every 8th image otherwise.

The 2 cores of the development machine may be shared (another process running tests). The JSON
records the 1-minute load average before and after the run and, measured from /proc during the
training loop, the CPU time that OTHER processes used (in cores; our own process is excluded, so a
busy 2-core training run alone reads ~0). A run is called `loaded` when the load average before it
was above `--load-threshold` or other processes used more than `--others-threshold` cores on
average; `--out` then gets a `_loaded` suffix before its extension, and the JSON says so.

  python benchmarks/train_quality.py ../shared/scenes/lego_tiny --seconds 300 \
      --out benchmarks/results/train_quality_lego_tiny_cpu.json
  python benchmarks/train_quality.py ../shared/scenes/fox --downscale 8 --seconds 600 --steps 1500 \
      --checkpoint-out /tmp/bench_runs/fox --out benchmarks/results/train_quality_fox_cpu.json
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax  # noqa: E402

from bench_common import emit, header, loaded_name, refuse_existing_out  # noqa: E402
from waldo_jax.errors import SceneFormatError  # noqa: E402
from waldo_jax.nerf.config import PRESETS, TrainConfig  # noqa: E402
from waldo_jax.nerf.trained import evaluate  # noqa: E402
from waldo_jax.nerf.train import HeldOut, train  # noqa: E402
from waldo_jax.scenes import load_scene  # noqa: E402


def load_splits(scene_path: str, downscale):
    """(train scene, held-out scene): Blender's test (or val) split, else every 8th image."""
    train_scene = load_scene(scene_path, downscale=downscale, split="train")
    splits = ("test", "val") if train_scene.format == "blender" else ("test",)
    for split in splits:
        try:
            with warnings.catch_warnings():  # the train split already warned about skipped frames
                warnings.simplefilter("ignore", UserWarning)
                return train_scene, load_scene(scene_path, downscale=downscale, split=split)
        except SceneFormatError:
            continue
    raise SystemExit(f"{scene_path}: no held-out split to measure PSNR on")


class CpuShare:
    """CPU time used by other processes (in cores) between `start()` and `stop()`, from /proc."""

    def __init__(self):
        self.tick = os.sysconf("SC_CLK_TCK")

    @staticmethod
    def _busy_total() -> float:
        fields = [float(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
        idle = fields[3] + (fields[4] if len(fields) > 4 else 0.0)  # idle + iowait
        return sum(fields[:8]) - idle

    @staticmethod
    def _own() -> float:
        stat = Path("/proc/self/stat").read_text()
        fields = stat[stat.rindex(")") + 2 :].split()
        return float(fields[11]) + float(fields[12])  # utime + stime (all threads), in ticks

    def start(self):
        self.t0, self.busy0, self.own0 = time.perf_counter(), self._busy_total(), self._own()

    def stop(self) -> dict:
        seconds = time.perf_counter() - self.t0
        busy = (self._busy_total() - self.busy0) / self.tick
        own = (self._own() - self.own0) / self.tick
        return {"own_cores": own / seconds, "others_cores": max(0.0, busy - own) / seconds, "seconds": seconds}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene_path")
    parser.add_argument("--downscale", type=float, default=None)
    parser.add_argument("--preset", default="fast", choices=PRESETS)
    parser.add_argument("--steps", type=int, default=None, help="default: the preset's")
    parser.add_argument("--seconds", type=float, default=None, help="training wall-clock budget (default: none)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--eval-at",
        default="60,120,300,600",
        help="comma-separated training seconds after which to measure held-out PSNR",
    )
    parser.add_argument("--load-threshold", type=float, default=1.5)
    parser.add_argument("--others-threshold", type=float, default=0.5)
    parser.add_argument(
        "--checkpoint-out",
        default=None,
        help="also save the trained run (checkpoint.ckpt) into this new folder (keep it out of the repo)",
    )
    parser.add_argument("--out", default=None, help="also write the JSON here (never overwrites)")
    args = parser.parse_args(argv)

    load_before = os.getloadavg()
    if args.checkpoint_out and Path(args.checkpoint_out).exists():
        raise SystemExit(f"{args.checkpoint_out} exists: refusing to overwrite a run")
    refuse_existing_out(args.out)

    train_scene, test_scene = load_splits(args.scene_path, args.downscale)
    overrides = {} if args.steps is None else {"steps": args.steps}
    config = TrainConfig.preset(args.preset, train_scene, **overrides)
    eval_at = sorted(float(s) for s in args.eval_at.split(",") if s.strip())

    checkpoints = []
    stopped_by = ["steps"]

    def on_chunk(state, entry):
        done, seconds = entry["step"], entry["seconds"]
        over_budget = args.seconds is not None and seconds >= args.seconds
        crossed = [t for t in eval_at if t <= seconds]
        if crossed and done < config.steps and not over_budget:
            eval_at[:] = [t for t in eval_at if t > seconds]
            psnr = evaluate(state.params, state.sampler_state, config, test_scene)["psnr"]
            checkpoints.append(
                {
                    "step": done,
                    "train_seconds": round(seconds, 2),
                    "psnr_test": psnr,
                    "train_psnr_batch": entry["psnr"],
                    "loadavg_1min": os.getloadavg()[0],
                }
            )
            print(f"step {done}: {seconds:.0f} s, held-out PSNR {psnr:.2f} dB", file=sys.stderr)
        if over_budget and done < config.steps:
            stopped_by[0] = "seconds"
            return True
        return False

    share = CpuShare()
    share.start()
    start = time.perf_counter()
    run = train(  # the final PSNR at the test images' loaded size, as the evaluations above
        jax.random.key(args.seed),
        train_scene,
        config,
        test_scene,
        progress=False,
        on_chunk=on_chunk,
        held_out=HeldOut(None),
    )
    cpu = share.stop()
    # Everything in `train` but the training chunks (the evaluations above, the calibration of the render
    # step, the final evaluation) is evaluation time.
    eval_seconds = time.perf_counter() - start - run.seconds
    last = next(h for h in reversed(run.history) if "loss" in h)
    checkpoints.append(
        {
            "step": run.steps,
            "train_seconds": round(run.seconds, 2),
            "psnr_test": run.psnr_test,
            "train_psnr_batch": last["psnr"],
            "loadavg_1min": os.getloadavg()[0],
        }
    )
    load_after = os.getloadavg()
    loaded = load_before[0] > args.load_threshold or cpu["others_cores"] > args.others_threshold

    result = header("train_quality")
    result.update(
        {
            "scene_path": str(Path(args.scene_path).resolve()),
            "scene": train_scene.name,
            "scene_format": train_scene.format,
            "downscale": train_scene.metadata.get("downscale"),
            "image_size": [train_scene.width, train_scene.height],
            "n_train": train_scene.n_images,
            "n_test": test_scene.n_images,
            "preset": args.preset,
            "seed": args.seed,
            "budget_seconds": args.seconds,
            "steps_planned": config.steps,
            "steps": run.steps,
            "stopped_by": stopped_by[0],
            "seconds": round(run.seconds, 2),
            "compile_seconds": round(run.compile_seconds, 2),
            "eval_seconds_excluded": round(eval_seconds, 2),
            "rays_per_second": run.rays_per_second,
            "steps_per_second": run.steps / max(run.seconds, 1e-9),
            "psnr_test": run.psnr_test,
            "psnr_test_training_step": run.psnr_test_training_step,
            "render_step_scale": run.config.render_step_scale,
            "render_step_curve": run.render_step_curve,
            "checkpoints": checkpoints,
            "loadavg_start": list(load_before),
            "loadavg_end": list(load_after),
            "cpu_during_training": {k: round(v, 3) for k, v in cpu.items()},
            "loaded": loaded,
            "loaded_rule": (
                f"loaded = 1-min load average before the run > {args.load_threshold} or other processes "
                f"used > {args.others_threshold} cores on average during training (from /proc; this "
                "process's own threads excluded, since a 2-core training run alone reads ~2 in loadavg)"
            ),
            "config": run.config.to_dict(),
        }
    )
    out = args.out
    if out and loaded:
        out = loaded_name(out)
        print(f"the machine was shared during this run: writing {out}", file=sys.stderr)
    if args.checkpoint_out:
        from waldo_jax.io import prepare_output_dir
        from waldo_jax.nerf.checkpoint import CHECKPOINT_NAME, save_checkpoint

        folder = prepare_output_dir(args.checkpoint_out, force=False)
        save_checkpoint(
            folder / CHECKPOINT_NAME,
            run.params,
            run.config,
            train_scene,
            run.occupancy,
            info={
                "psnr_test": run.psnr_test,
                "steps": run.steps,
                "seconds": run.seconds,
                "n_train": train_scene.n_images,
                "n_test": test_scene.n_images,
            },
        )
        result["checkpoint_out"] = str(folder)
    emit(result, out)


if __name__ == "__main__":
    main()

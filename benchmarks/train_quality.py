"""Training quality against wall clock: held-out PSNR at a few training-time checkpoints.

Trains an Instant-NGP field on a scene exactly as `waldo train` does (`training_inputs` + the jitted
`run_chunk` scan, the preset's config; the same key gives the same parameters), and after each chunk
whose training time crosses one of `--eval-at` seconds, renders the held-out split and records its
PSNR. Evaluations pause the clock: the seconds reported are training seconds (compilation of the
first chunk included, as in `waldo train`). Training stops at `--steps` (default: the preset's) or
once `--seconds` of training have passed, whichever comes first; the learning-rate decay follows
`--steps`, so choose a step count that fits the budget.

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
import numpy as np  # noqa: E402

from _common import emit, header, loaded_name  # noqa: E402
from waldo_jax.errors import SceneFormatError  # noqa: E402
from waldo_jax.nerf.train import (PRESETS, TrainConfig, TrainHParams, evaluate, run_chunk,  # noqa: E402
                                  training_inputs)
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
        fields = stat[stat.rindex(")") + 2:].split()
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
    parser.add_argument("--eval-at", default="60,120,300,600",
                        help="comma-separated training seconds after which to measure held-out PSNR")
    parser.add_argument("--load-threshold", type=float, default=1.5)
    parser.add_argument("--others-threshold", type=float, default=0.5)
    parser.add_argument("--checkpoint-out", default=None,
                        help="also save the trained run (checkpoint.ckpt) into this new folder (keep it out of the repo)")
    parser.add_argument("--out", default=None, help="also write the JSON here (never overwrites)")
    args = parser.parse_args(argv)

    load_before = os.getloadavg()
    if args.checkpoint_out and Path(args.checkpoint_out).exists():
        raise SystemExit(f"{args.checkpoint_out} exists: refusing to overwrite a run")
    for out in (args.out, args.out and loaded_name(args.out)):
        if out and Path(out).exists():
            raise SystemExit(f"{out} exists: refusing to overwrite an earlier result (choose another --out)")

    train_scene, test_scene = load_splits(args.scene_path, args.downscale)
    overrides = {} if args.steps is None else {"steps": args.steps}
    config = TrainConfig.preset(args.preset, train_scene, **overrides)
    hparams = TrainHParams.for_config(config)
    state, train_key, data, _, render_config = training_inputs(jax.random.key(args.seed), train_scene, config,
                                                               hparams)
    eval_at = sorted(float(s) for s in args.eval_at.split(",") if s.strip())

    checkpoints = []
    chunk_seconds, chunk_rays, chunk_steps = [], [], []
    train_seconds, eval_seconds = 0.0, 0.0
    share = CpuShare()
    share.start()
    stopped_by = "steps"
    while int(state.step) < config.steps:
        start = time.perf_counter()
        state, metrics = run_chunk(state, train_key, data, hparams, render_config, config, config.steps)
        metrics = jax.device_get(metrics)  # the host sync of this chunk
        elapsed = time.perf_counter() - start
        train_seconds += elapsed
        chunk_seconds.append(elapsed)
        chunk_rays.append(int(np.sum(metrics["rays"])))
        chunk_steps.append(int(np.sum(np.isfinite(metrics["loss"]))))
        done = int(state.step)
        over_budget = args.seconds is not None and train_seconds >= args.seconds
        crossed = [t for t in eval_at if t <= train_seconds]
        if crossed and done < config.steps and not over_budget:
            eval_at = [t for t in eval_at if t > train_seconds]
            start = time.perf_counter()
            psnr = evaluate(state.params, state.sampler_state, config, test_scene)["psnr"]
            eval_seconds += time.perf_counter() - start
            checkpoints.append({"step": done, "train_seconds": round(train_seconds, 2), "psnr_test": psnr,
                                "train_psnr_batch": float(np.nanmean(metrics["psnr"])),
                                "loadavg_1min": os.getloadavg()[0]})
            print(f"step {done}: {train_seconds:.0f} s, held-out PSNR {psnr:.2f} dB", file=sys.stderr)
        if over_budget and done < config.steps:
            stopped_by = "seconds"
            break
    cpu = share.stop()
    start = time.perf_counter()
    final = evaluate(state.params, state.sampler_state, config, test_scene)
    eval_seconds += time.perf_counter() - start
    checkpoints.append({"step": int(state.step), "train_seconds": round(train_seconds, 2), "psnr_test": final["psnr"],
                        "train_psnr_batch": float(np.nanmean(metrics["psnr"])), "loadavg_1min": os.getloadavg()[0]})
    load_after = os.getloadavg()

    # As `train`: the first chunk compiles; the rate is that of the others.
    steady_rays = sum(chunk_rays[1:]) if len(chunk_seconds) > 1 else sum(chunk_rays)
    steady_seconds = sum(chunk_seconds[1:]) if len(chunk_seconds) > 1 else sum(chunk_seconds)
    steady_steps = sum(chunk_steps[1:]) if len(chunk_seconds) > 1 else sum(chunk_steps)
    compile_seconds = max(0.0, chunk_seconds[0] - float(np.mean(chunk_seconds[1:]))) if len(chunk_seconds) > 1 else 0.0
    loaded = load_before[0] > args.load_threshold or cpu["others_cores"] > args.others_threshold

    result = header("train_quality")
    result.update({
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
        "steps": int(state.step),
        "stopped_by": stopped_by,
        "seconds": round(train_seconds, 2),
        "compile_seconds": round(compile_seconds, 2),
        "eval_seconds_excluded": round(eval_seconds, 2),
        "rays_per_second": steady_rays / max(steady_seconds, 1e-9),
        "steps_per_second": steady_steps / max(steady_seconds, 1e-9),
        "psnr_test": final["psnr"],
        "psnr_test_per_image": final["psnr_per_image"],
        "checkpoints": checkpoints,
        "loadavg_start": list(load_before),
        "loadavg_end": list(load_after),
        "cpu_during_training": {k: round(v, 3) for k, v in cpu.items()},
        "loaded": loaded,
        "loaded_rule": (f"loaded = 1-min load average before the run > {args.load_threshold} or other processes "
                        f"used > {args.others_threshold} cores on average during training (from /proc; this "
                        "process's own threads excluded, since a 2-core training run alone reads ~2 in loadavg)"),
        "config": config.to_dict(),
    })
    out = args.out
    if out and loaded:
        out = loaded_name(out)
        print(f"the machine was shared during this run: writing {out}", file=sys.stderr)
    if args.checkpoint_out:
        from waldo_jax.io import prepare_output_dir
        from waldo_jax.nerf.checkpoint import CHECKPOINT_NAME, save_checkpoint

        folder = prepare_output_dir(args.checkpoint_out, force=False)
        save_checkpoint(folder / CHECKPOINT_NAME, state.params, config, train_scene, state.sampler_state,
                        info={"psnr_test": final["psnr"], "steps": int(state.step), "seconds": train_seconds,
                              "n_train": train_scene.n_images, "n_test": test_scene.n_images})
        result["checkpoint_out"] = str(folder)
    emit(result, out)


if __name__ == "__main__":
    main()

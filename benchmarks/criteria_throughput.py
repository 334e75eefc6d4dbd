"""Criterion throughput: images per second for a batch of P images at S x S, inside one jit.

For every image criterion of the registry (or `--criteria`), times `jax.jit(criterion.score_images)`
on a batch of `--batch` (default 64) natural images at `--size` (default 256): fox training views
cropped and resized when `$WALDO_DATA` has them, else smooth synthetic images. Compilation is
excluded (one untimed call first); best and median of `--repeats` are reported, with the compile
time. The `waldo` finder uses a 40x40 crop of the first image as its target.

  python benchmarks/criteria_throughput.py --out benchmarks/results/criteria_throughput_cpu.json

The network criteria run inside the same jit as a search's scoring step (`pipeline.score_function`
composes render and criterion in one function), so these figures are what a search pays per view.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np  # noqa: E402

import waldo_jax  # noqa: E402,F401  (before jax: XLA flags)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from bench_common import emit, header, loaded_name, timed, wait_for_quiet  # noqa: E402
from waldo_jax.criteria import CRITERIA, CriterionContext, make_criterion  # noqa: E402


def natural_images(count: int, size: int) -> tuple[np.ndarray, str]:
    """[count, size, size, 3] float32 images: fox views (square crops) if available, else synthetic."""
    from waldo_jax import paths
    from waldo_jax.pipeline.sources import resize_images

    data = paths.data_dir()
    fox = None if data is None else data / "scenes" / "fox" / "images"
    if fox is not None and fox.is_dir():
        import imageio.v3 as iio

        files = sorted(fox.glob("*.jpg"))
        images = []
        for i in range(count):
            image = np.asarray(iio.imread(files[i % len(files)]), np.float32)[..., :3] / 255.0
            h, w = image.shape[:2]
            side = min(h, w)
            top = (h - side) // 2
            images.append(resize_images(image[None, top : top + side, :side], size, size)[0])
        return np.stack(images), "fox training views, centre square crops"
    key = jax.random.key(0)
    ys, xs = np.mgrid[0:size, 0:size] / size
    base = np.stack([xs, ys, 0.5 + 0.5 * np.sin(6 * xs)], -1).astype(np.float32)
    noise = np.asarray(jax.random.uniform(key, (count, size, size, 3)), np.float32) * 0.1
    return np.clip(base[None] + noise, 0, 1), "synthetic gradients with noise"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--criteria", default=None, help="comma-separated names (default: every image criterion)")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--size", type=int, default=256)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quiet-load", type=float, default=2.5, help="wait for this 1-min load average first")
    parser.add_argument("--out", default=None, help="JSON file (never overwritten; '_loaded' added if loaded)")
    args = parser.parse_args(argv)

    names = (
        args.criteria.split(",")
        if args.criteria
        else sorted(n for n, spec in CRITERIA.items() if spec.inputs != "poses")
    )
    load = (
        wait_for_quiet(args.quiet_load)
        if os.getloadavg()[0] > args.quiet_load
        else {"loadavg_start": list(os.getloadavg()), "waited_s": 0.0, "loaded": False}
    )
    images, what = natural_images(args.batch, args.size)
    target = images[0, 100:140, 100:140] if args.size >= 140 else images[0, : args.size // 4, : args.size // 4]
    batch = jnp.asarray(images)
    results = {}
    for name in names:
        criterion = make_criterion(name, CriterionContext(target=target))
        score = jax.jit(criterion.score_images)
        start = time.perf_counter()
        jax.block_until_ready(score(batch))
        compile_s = time.perf_counter() - start
        best, median, _ = timed(lambda: score(batch), args.repeats)
        results[name] = {
            "direction": criterion.direction,
            "images_per_s": args.batch / best,
            "images_per_s_median": args.batch / median,
            "seconds_best": best,
            "first_call_s": compile_s,
            "mean_score": float(np.mean(np.asarray(score(batch)))),
        }
        print(f"{name:13s} {args.batch / best:9.1f} images/s  (first call {compile_s:.1f} s)", file=sys.stderr)
    load_end = list(os.getloadavg())
    loaded = load["loaded"] or load_end[0] > args.quiet_load
    result = dict(
        header("criteria_throughput"),
        batch=args.batch,
        size=args.size,
        images=what,
        repeats=args.repeats,
        load=dict(load, loadavg_end=load_end, loaded=loaded),
        criteria=results,
    )
    emit(result, loaded_name(args.out) if args.out and loaded else args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())

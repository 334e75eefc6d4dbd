"""The demo's training trade: how good the room's NeRF is at the views the searches return, per training setting.

`waldo demo` trains the hash-grid NeRF on views of the procedural room that see Waldo at most half, then
shows the views the searches find (Waldo whole, close up) as the NeRF renders them. Those views lie away
from the training cameras, so the held-out PSNR (views like the training views) overstates how well the
found views render. This benchmark measures what the demo shows:

  1. the evaluation views: each method's best view per seed (GRS, PIBS, EGPS; low budget; `waldo_found`,
     exact, so the views do not depend on the NeRF) plus a few more of seed 0's top 10, and their truth
     rendered analytically;
  2. for each setting (training views, steps, resolution, hash-grid finest resolution N_max, marching
     steps per diagonal), a NeRF trained as the demo trains it, and the PSNR of its renders at those views
     against the truth (`psnr_found`: all, `psnr_best`: the per-seed best views only, `psnr_closeup`:
     Waldo's close-ups from the best views as `waldo demo` draws them), beside its held-out PSNR and
     its training seconds (`--figures DIR`: each setting's close-ups, NeRF over truth).

  python benchmarks/demo_training.py --out benchmarks/results/demo_training_cpu.json
  python benchmarks/demo_training.py --settings nmax05,nmax05_steps1500,res128_steps1500 \\
      --out benchmarks/results/demo_training_closeups_cpu.json --figures /tmp/closeups

The settings are named in SETTINGS below. A 2-core CPU needs about 2 minutes for `base` and 10 for the
largest; the JSON says when other jobs shared the machine (`_loaded` name).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path
from typing import NamedTuple, Optional

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, wait_for_quiet  # noqa: E402
from waldo_jax import io  # noqa: E402
from waldo_jax.criteria import CriterionContext, make_criterion  # noqa: E402
from waldo_jax.nerf import train as training  # noqa: E402
from waldo_jax.nerf.trained import TrainedField  # noqa: E402
from waldo_jax.pipeline import procedural_source, run_explore  # noqa: E402
from waldo_jax.metrics import image_psnr  # noqa: E402
from waldo_jax.pipeline.demo import DEMO_ROOM_SEED, SETTINGS as DEMO_SETTINGS  # noqa: E402
from waldo_jax.pipeline.demo import closeup_cameras, room_train_config  # noqa: E402
from waldo_jax.pipeline.sources import field_renderer  # noqa: E402
from waldo_jax.procedural import held_out_scene, room_scene, waldo_surface_seen  # noqa: E402
from waldo_jax.search import ExploreConfig  # noqa: E402

# name -> overrides of the demo's full settings: views, steps, resolution, N_max scale, steps-per-diagonal scale.
SETTINGS = {
    "base": {},
    "nmax05": {"nmax_scale": 0.5},
    "spd05": {"spd_scale": 0.5},
    "steps800": {"steps": 800},
    "views64": {"views": 64},
    "views64_nmax05_steps800": {"views": 64, "nmax_scale": 0.5, "steps": 800},
    "nmax05_steps1500": {"nmax_scale": 0.5, "steps": 1500},
    "res128": {"resolution": 128},
    "res128_steps1500": {"resolution": 128, "steps": 1500},
}


class Views(NamedTuple):
    """The evaluation views and their truth (all at the demo's resolution)."""

    c2w: np.ndarray  # [V, 4, 4]
    truth: np.ndarray  # [V, H, W, 3]
    best: np.ndarray  # bool [V], a seed's best view
    intrinsics: object
    closeup_c2w: np.ndarray  # [B, 4, 4], Waldo's close-ups from the best views (`demo.closeup_cameras`)
    closeup_intrinsics: object
    closeup_truth: np.ndarray  # [B, H, W, 3]


def evaluation_views(seeds: int, resolution: int) -> Views:
    """Each method's best view of each seed, and seed 0's 2nd, 5th and 8th best of GRS and EGPS (the exact
    criterion finds them, the room renders them), and Waldo's close-ups from the best views."""
    source = procedural_source(DEMO_ROOM_SEED, resolution, views=DEMO_SETTINGS["full"].views)
    criterion = make_criterion("waldo_found", CriterionContext(room=source.room))
    views, best = [], []
    for method in ("grs", "pibs", "egps"):
        run = run_explore(
            source, criterion, ExploreConfig(method=method, budget="low"), seed=DEMO_ROOM_SEED, seeds=seeds
        )
        tops = np.stack([np.asarray(r.top_c2w[0]) for r in run.results])
        views.append(tops)
        best += [True] * len(tops)
        if method != "pibs":
            first = run.results[0]
            more = np.asarray(first.top_c2w)[np.asarray(first.top_valid)][1:10:3]
            views.append(more)
            best += [False] * len(more)
    c2w = np.concatenate(views).astype(np.float32)
    best = np.asarray(best)
    closeup_c2w, zoomed, _ = closeup_cameras(source.room, c2w[best], source.intrinsics)
    closeup_truth = np.asarray(source.render(closeup_c2w, zoomed))
    truth = np.asarray(source.render(jnp.asarray(c2w)))
    return Views(c2w, truth, best, source.intrinsics, closeup_c2w, zoomed, closeup_truth)


def measure(name: str, overrides: dict, views: Views, figures: Optional[Path]) -> dict:
    base = DEMO_SETTINGS["full"]
    count, steps = overrides.get("views", base.views), overrides.get("steps", base.train_steps)
    resolution = overrides.get("resolution", base.resolution)
    t0 = time.perf_counter()
    scene, room = room_scene(DEMO_ROOM_SEED, num_views=count, resolution=resolution, camera_config=base.camera)
    test = held_out_scene(room, DEMO_ROOM_SEED, base.test_views, scene, base.camera)
    settings = dataclasses.replace(
        base, train_steps=steps, render_step_scale=None, finest_resolution_scale=overrides.get("nmax_scale", 1.0)
    )
    config = room_train_config(scene, settings)
    if "spd_scale" in overrides:
        config = config.replace(steps_per_diagonal=config.steps_per_diagonal * overrides["spd_scale"])
    t1 = time.perf_counter()
    result = training.train(jax.random.key(DEMO_ROOM_SEED), scene, config, test, progress=False)
    t2 = time.perf_counter()
    render = field_renderer(TrainedField.from_result(result, scene))
    psnr = image_psnr(np.asarray(render(jnp.asarray(views.c2w), views.intrinsics).rgba[..., :3]), views.truth)
    closeups = np.asarray(render(jnp.asarray(views.closeup_c2w), views.closeup_intrinsics).rgba[..., :3])
    closeup_psnr = image_psnr(closeups, views.closeup_truth)
    if figures is not None:
        io.save_png(
            figures / f"{name}_closeups.png",
            io.contact_sheet(list(closeups) + list(views.closeup_truth), columns=len(closeups)),
        )
    return {
        "name": name,
        "views": count,
        "steps": steps,
        "resolution": resolution,
        "n_max": int(config.field.hashgrid.N_max),
        "steps_per_diagonal": float(config.steps_per_diagonal),
        "render_step_scale": result.config.render_step_scale,
        "seconds": {"scene": round(t1 - t0, 1), "train": round(t2 - t1, 1)},
        "waldo_surface_seen": round(float(waldo_surface_seen(room, jnp.asarray(scene.c2w), scene.intrinsics)), 3),
        "psnr_test": round(float(result.psnr_test), 2),
        "psnr_found": round(float(np.mean(psnr)), 2),
        "psnr_best": round(float(np.mean(psnr[views.best])), 2),
        "psnr_closeup": round(float(np.mean(closeup_psnr)), 2),
        "psnr_closeup_per_view": np.round(closeup_psnr, 2).tolist(),
        "psnr_per_view": np.round(psnr, 2).tolist(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--settings", default=",".join(SETTINGS), help="comma-separated names of SETTINGS")
    parser.add_argument("--seeds", type=int, default=8, help="search seeds for the evaluation views (default 8)")
    parser.add_argument("--load-threshold", type=float, default=1.0)
    parser.add_argument("--out", default=None)
    parser.add_argument("--figures", default=None, help="a new folder for the close-up sheets (NeRF over truth)")
    args = parser.parse_args()
    names = [n for n in args.settings.split(",") if n]
    unknown = sorted(set(names) - set(SETTINGS))
    if unknown:
        raise SystemExit(f"unknown --settings {', '.join(unknown)}: expected some of {', '.join(SETTINGS)}")
    refuse_existing_out(args.out)
    figures = None if args.figures is None else io.prepare_output_dir(args.figures, force=False, can_force=False)
    quiet = wait_for_quiet(args.load_threshold)
    result = header("demo_training")
    views = evaluation_views(args.seeds, DEMO_SETTINGS["full"].resolution)
    result["evaluation_views"] = {
        "count": int(len(views.c2w)),
        "best_views": int(views.best.sum()),
        "closeup_zoom": float(views.closeup_intrinsics.fx / views.intrinsics.fx),
        "seeds": args.seeds,
        "criterion": "waldo_found",
        "room_seed": DEMO_ROOM_SEED,
    }
    result["settings"] = []
    for name in names:
        row = measure(name, SETTINGS[name], views, figures)
        print(
            f"{name}: held-out {row['psnr_test']:.2f} dB, found views {row['psnr_found']:.2f} dB, "
            f"Waldo's close-ups {row['psnr_closeup']:.2f} dB, "
            f"train {row['seconds']['train']:.0f} s",
            file=sys.stderr,
            flush=True,
        )
        result["settings"].append(row)
    emit_with_load(result, args.out, quiet, args.load_threshold)


if __name__ == "__main__":
    main()

"""`waldo demo`: the whole pipeline on the procedural Waldo room, in a few minutes on a CPU.

  1. build the room and render its training views (cameras that see Waldo at most half);
  2. train the hash-grid NeRF (`waldo_jax.nerf`) on them and save it as a run directory `nerf/`
     (so `waldo explore DEMO_DIR/nerf ...` explores it again);
  3. run GRS, PIBS and EGPS at the paper's low budget, several seeds each in one vmapped call,
     scored by `waldo_found` (Waldo at least 90 % visible, then as large as possible; exact, from the
     room's geometry); the views found are rendered by the NeRF (what a user of a real scene would
     see) and by the analytic room (the truth); with `search_renders`, a method (GRS by default) also
     searches the NeRF's renders with the `waldo` finder (the paper's setting), its best views checked
     by the oracle, and the full demo's NeRF trains `RENDERS_TRAIN_STEPS` steps;
  4. write `report.md` (CVIR / mCVIR per method, mean +/- std over seeds; Waldo's visible share and
     the NeRF render's PSNR against the truth at each seed's best view), one folder per method
     (results.json, top-k PNGs, contact sheet, poses.json, pose cloud), a combined contact sheet,
     `waldo_closeups.png` (Waldo up close from each seed's best view, NeRF above truth, with the
     close-up PSNR) and `summary.json`, into a new directory (default `runs/demo-<timestamp>`; never
     overwritten).

The room is `procedural:6` by default (`DEMO_ROOM_SEED`): in room 0 (and 2, 3) the crates hide part of
Waldo from every camera the searches may place, so no view shows him whole (docs/results.md, "The Waldo
room"), and of the others room 6's NeRF renders him best where the searches find him.
"""

from __future__ import annotations

import concurrent.futures
import dataclasses
import datetime
import functools
import time
from pathlib import Path
from typing import Any, Dict, Optional

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax import io
from waldo_jax.cameras import look_at
from waldo_jax.criteria import CriterionContext, make_criterion
from waldo_jax.errors import WaldoError
from waldo_jax.metrics import image_psnr, masked_psnr
from waldo_jax.nerf.config import TrainConfig
from waldo_jax.nerf.runs import evaluate_run, train_run
from waldo_jax.nerf.trained import TrainedField
from waldo_jax.pipeline.experiment import prepare_explore, run_prepared
from waldo_jax.pipeline.figures import criterion_caption, methods_sheet
from waldo_jax.pipeline.outputs import write_outputs
from waldo_jax.pipeline.sources import NERF_GRADIENT, Source, field_renderer, render_in, room_renderer
from waldo_jax.procedural import (
    FOUND_VISIBILITY,
    RoomCameraConfig,
    held_out_scene,
    make_room,
    room_scene,
    waldo_mask,
    waldo_reference,
    waldo_surface_seen,
    waldo_visibility_batch,
)
from waldo_jax.search import ExploreConfig
from waldo_jax.search.views import DEFAULT_MIN_SEPARATION
from waldo_jax.types import Intrinsics, Scene

__all__ = [
    "DEMO_ROOM_SEED",
    "DemoSettings",
    "RENDERS_TRAIN_STEPS",
    "SETTINGS",
    "demo_settings",
    "run_demo",
    "default_demo_dir",
    "closeup_cameras",
    "closeup_sheet",
    "render_in",
    "room_scenes",
    "nerf_source",
    "train_room_nerf",
    "room_train_config",
]

METHOD_ORDER = ("grs", "pibs", "egps")
# The row that searches the NeRF's renders (the paper's setting): a method scored by the `waldo` finder
# with a reference image of Waldo; its best views are checked by the exact oracle like the others'. GRS by
# default: scored by the finder on the room's own (analytic) views, GRS found him in 7 of 8 seeds of room 6,
# MAP-Elites in 5, EGPS in 2 (it narrows onto one view early; benchmarks/finder_methods.py,
# benchmarks/results/finder_methods_room6_cpu_loaded.json).
RENDERS_METHOD, RENDERS_SUFFIX, RENDERS_CRITERION = "grs", "_on_renders", "waldo"
RENDERS_METHODS = ("grs", "pibs", "egps", "map-elites")
# The demo's room: of the rooms whose search space holds views of Waldo whole (not 0, 2, 3), the one where
# the NeRF renders him best at EGPS's best views (the demo's training: 7 of 8 seeds >= 20 dB over his pixels
# in room 6; 5 in room 4; 4 in rooms 1, 5 and 7; docs/results.md, "Waldo's own pixels").
DEMO_ROOM_SEED = 6


@dataclasses.dataclass(frozen=True)
class DemoSettings:
    """Sizes of a demo run.

    Attributes:
      views: training views of the room.
      resolution: image side of the training views and of every render.
      train_steps: NeRF training steps (fast preset).
      seeds: search seeds per method (one vmapped call each).
      test_views: held-out views for the NeRF's PSNR (10, the top-k's size: the held-out views and every
        later render of the NeRF and of the room then run the programs compiled once for 10 poses).
      render_step_scale: the NeRF's marching step over its training step; None calibrates it after
        training (`waldo_jax.nerf.train`), a number fixes it (quick: x3, the usual choice, saving
        the calibration's renders and compiles).
      finest_resolution_scale: the hash grid's finest resolution (N_max) over the fast preset's: 0.5
        fits the room's 64 px views better in the same steps (`benchmarks/demo_training.py`).
      criterion: what the searches maximise (a pose criterion of the room).
      camera: where the training (and held-out) cameras go.
      min_separation: degrees between the top-k views shown (different shots; 0: the paper's top-k).
      waldo_scale: Waldo's size, with his pen's, in the room (`procedural.make_room`).
      stripe_width: his stripes' width in metres (None: 5 cm times `waldo_scale`).
      hash_table_log2: the hash grid's table size T = 2**hash_table_log2 per level (None: the fast preset's).
      hash_levels: the hash grid's levels L between its coarsest and finest resolution (None: the fast
        preset's 16); fewer levels, fewer table lookups a sample.
      samples_per_batch: field samples per training step (None: the fast preset's 2**15).
      first_rays: the rays the training's steps march through its warm-up (`TrainConfig.first_rays`;
        None: the fast preset's choice, those that fill the budget with the grid all occupied).
      search_renders: a method (one of `RENDERS_METHODS`) to run also scored by the `waldo` finder on the
        NeRF's renders (key `<method>_on_renders`), or None; it renders every view it scores (settings.seeds
        x the low budget), the others render only their top-k.
      pixel_sampling: how the NeRF's training draws its pixels (`TrainConfig.pixel_sampling`): "error"
        trains the pixels it still gets wrong more often (Waldo's stripes, the crates' edges).
      train_step_scale: the NeRF's training marching step over the fast preset's (2: steps twice as long,
        so a step's fixed budget of samples holds twice the rays).
    """

    views: int
    resolution: int
    train_steps: int
    seeds: int
    test_views: int = 10
    render_step_scale: Optional[float] = None
    finest_resolution_scale: float = 1.0
    criterion: str = "waldo_found"
    camera: RoomCameraConfig = RoomCameraConfig()
    min_separation: float = DEFAULT_MIN_SEPARATION
    waldo_scale: float = 1.0
    stripe_width: Optional[float] = None
    hash_table_log2: Optional[int] = None
    hash_levels: Optional[int] = None
    samples_per_batch: Optional[int] = None
    first_rays: Optional[int] = None
    search_renders: Optional[str] = None
    pixel_sampling: str = "error"
    train_step_scale: float = 1.0


# Waldo 1.5 x his size with 15 cm stripes, 16 of the 48 training cameras placed to see his surface from
# 1.2-2.2 m (none sees more than half of him); 1,200 steps with pixels drawn by their error, marching twice
# the fast preset's step (twice the rays in a step's samples): the NeRF then renders his stripes where the
# searches find him. Room 6, EGPS, Waldo-pixel PSNR at the best views (benchmarks/demo_settings.py,
# docs/results.md "Waldo's own pixels"): these settings 7 of 8 seeds >= 20 dB, mean 20.9 dB, the whole demo
# 146-179 s in first runs on the 2-core CPU (benchmarks/results/demo_programs_ab_cpu.json); rendered at the
# training step (render_step_scale 1) 8 of 8, 22.1 dB, 180 s;
# the preset's step with error sampling 7 of 8, 22.0 dB, 186 s; 1,200 uniform steps 5 of 8; 2,500 uniform
# steps 8 of 8, 23.3 dB, 225 s.
DEMO_ROOM = dict(waldo_scale=1.5, stripe_width=0.15)
SETTINGS = {
    # render_step_scale 2: renders march twice the training step, half the NeRF's render time (the
    # search-renders row renders every view it scores) for about 1 dB over Waldo's pixels.
    # first_rays 1024: the rung the training marches after its warm-up; the warm-up's own rung (512)
    # overflows the budget too, so the same rays train and one program compiles, not two (the same
    # NeRF and figures, 2026-12-06).
    "full": DemoSettings(
        views=48,
        resolution=64,
        train_steps=1200,
        seeds=8,
        finest_resolution_scale=0.5,
        render_step_scale=2.0,
        train_step_scale=2.0,
        camera=RoomCameraConfig(cover_views=16, cover_band=(1.2, 2.2)),
        first_rays=1024,
        **DEMO_ROOM,
    ),
    "quick": DemoSettings(
        views=20,
        resolution=48,
        train_steps=120,
        seeds=4,
        render_step_scale=3.0,
        train_step_scale=2.0,
        camera=RoomCameraConfig(cover_views=6, cover_band=(1.2, 2.2)),
        **DEMO_ROOM,
    ),
}


# The full demo's training steps when it also searches the NeRF's renders: the finder then judges Waldo by
# the NeRF's pictures of his whole views, which 1,200 steps render worse than his part-hidden ones (the row
# found him in 4 of 8 seeds; at 2,400 steps in 6 of 8, EGPS's Waldo-pixel PSNR >= 20 dB in 8 of 8, and the
# demo took 671 s on the 2-core CPU: docs/results.md, "Waldo up close", "At 2,400 steps ...").
RENDERS_TRAIN_STEPS = 2400


def demo_settings(quick: bool = False, search_renders: Optional[str] = None) -> DemoSettings:
    """The demo's settings (`SETTINGS["quick"]` or `["full"]`) with `search_renders`; the full demo with a
    row on renders trains `RENDERS_TRAIN_STEPS` steps (the quick one its own)."""
    settings = dataclasses.replace(SETTINGS["quick" if quick else "full"], search_renders=search_renders)
    if search_renders is not None and not quick:
        settings = dataclasses.replace(settings, train_steps=RENDERS_TRAIN_STEPS)
    return settings


def default_demo_dir(root: str | Path = "runs") -> Path:
    """`runs/demo-<UTC timestamp>`, with a suffix when that name is taken."""
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y%m%d-%H%M%S")
    path = Path(root) / f"demo-{stamp}"
    n = 1
    while path.exists():
        n += 1
        path = Path(root) / f"demo-{stamp}-{n}"
    return path


def room_train_config(scene: Scene, settings: DemoSettings) -> TrainConfig:
    """The room NeRF's training config: the fast preset with `settings.train_steps`, its pixel sampling,
    render step and training step (`train_step_scale`), the hash grid's finest resolution scaled by
    `settings.finest_resolution_scale` (at least 32), its table size and levels where the settings give them."""
    overrides = {} if settings.render_step_scale is None else {"render_step_scale": settings.render_step_scale}
    for name in ("samples_per_batch", "first_rays"):
        if getattr(settings, name) is not None:
            overrides[name] = getattr(settings, name)
    config = TrainConfig.preset(
        "fast", scene, steps=settings.train_steps, pixel_sampling=settings.pixel_sampling, **overrides
    )
    if settings.train_step_scale != 1.0:
        config = config.replace(steps_per_diagonal=config.steps_per_diagonal / settings.train_step_scale)
    hashgrid = config.field.hashgrid
    n_max = max(32, int(hashgrid.N_max * settings.finest_resolution_scale))
    table = hashgrid.T if settings.hash_table_log2 is None else 2**settings.hash_table_log2
    levels = hashgrid.L if settings.hash_levels is None else settings.hash_levels
    if (n_max, table, levels) == (hashgrid.N_max, hashgrid.T, hashgrid.L):
        return config
    hashgrid = dataclasses.replace(hashgrid, N_max=n_max, T=table, L=levels)
    return config.replace(field=dataclasses.replace(config.field, hashgrid=hashgrid))


def train_room_nerf(
    scene: Scene, test_scene: Optional[Scene], settings: DemoSettings, seed: int, run_dir: Path, progress: bool
):
    """The room's NeRF (`room_train_config`) trained into the existing folder `run_dir` (evaluated on
    `test_scene`; None: not evaluated, see `waldo_jax.nerf.runs.evaluate_run`).

    Returns:
      (the `TrainResult`, its train.json contents), as `waldo_jax.nerf.runs.train_run`.
    """
    return train_run(seed, scene, room_train_config(scene, settings), test_scene, run_dir, progress)


def _report(out: Path, summary: Dict[str, Any]) -> str:
    rows, seed_rows = [], []
    for method in summary["methods"]:  # the exact criterion's rows, then the one on renders
        m = summary["methods"][method]
        rows.append(
            f"| {_label(method)} | {m['cvir_mean']:.0f} ± {m['cvir_std']:.0f} | "
            f"{m['mcvir_mean']:.0f} ± {m['mcvir_std']:.0f} | {m['dcvir_mean']:.0f} ± {m['dcvir_std']:.0f} | "
            f"{np.mean(m['shots_beating_train_per_seed']):.1f} | {np.mean(m['paper_topk_shots_per_seed']):.1f} | "
            f"{m['best_mean']:.4f} | "
            f"{m['best_visible_mean']:.0%} ({m['found_seeds']}/{len(m['best_visible_per_seed'])}) | "
            f"{m['best_psnr_mean']:.1f} | {m['top_psnr_mean']:.1f} | {m['seconds']:.1f} |"
        )
        per_seed = (m["best_visible_per_seed"], m["best_psnr_per_seed"], m["waldo_psnr_per_seed"])
        cells = [
            f"{v:.0%}, {p:.1f} dB, Waldo {_db(w)}, {c:.1f} dB"
            for (v, p, w), c in zip(zip(*per_seed), m["closeup_psnr_per_seed"])
        ]
        seed_rows.append(f"| {_label(method)} | " + " | ".join(cells) + " |")
    nerf = summary["nerf"]
    winner = max(METHOD_ORDER, key=lambda k: summary["methods"][k]["mcvir_mean"])  # on the exact criterion
    renders = [k for k in summary["methods"] if k.endswith(RENDERS_SUFFIX)]
    s = summary["settings"]
    seeds = summary["seeds"]
    return "\n".join(
        [
            "# waldo demo: finding Waldo in the procedural room",
            "",
            f"Room `procedural:{summary['room_seed']}`, {s['views']} training views at "
            f"{s['resolution']}x{s['resolution']} "
            f"(each sees at most half of Waldo). Criterion `{summary['criterion']}`: Waldo found (at least "
            f"{FOUND_VISIBILITY:.0%} of him in frame and unoccluded) and as large as possible: 1 + his share of the "
            "image when found, else his visible fraction (exact, from the room's geometry; direction max). Budget "
            "`low`: "
            f"{summary['n_train']} training + 5 x {summary['children_per_epoch']} generated views; top-k = 10. "
            f"{s['seeds']} seeds per method (seeds {seeds[0]}..{seeds[-1]}), one vmapped call each.",
            "",
            f"Scores in every table and figure: {summary['criterion_caption']}.",
            "",
            "| method | CVIR % (mean ± std) | mCVIR % (mean ± std) | dCVIR % (mean ± std) | different shots "
            "beating the best training view (of 10, mean) | different shots in the paper's top 10 (mean) | best score "
            "(mean) | Waldo visible in best view (mean; seeds >= 90 %) | NeRF render PSNR at best view (dB, mean) | "
            f"PSNR over seed {seeds[0]}'s top 10 (dB) | search s |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
            *rows,
            "",
            (
                f"The last row, **{_label(renders[0])}**, is the paper's own setting: "
                f"{renders[0][: -len(RENDERS_SUFFIX)].upper()} scores the NeRF's "
                f"renders with the `{RENDERS_CRITERION}` finder and a reference image of Waldo "
                "(`waldo_reference.png`, a close render of the room); its CVIR, mCVIR, dCVIR and scores are the "
                "finder's, and its best views are checked by the exact oracle like the others' (Waldo visible)."
                if renders
                else f"`waldo demo --search-renders` adds {RENDERS_METHOD.upper()} scored by the `waldo` finder on "
                "the NeRF's renders (the paper's own setting), its best views checked by the exact oracle."
            ),
            "",
            f"CVIR and mCVIR are the paper's (mCVIR: the mean of the 10 best views, however alike). The views shown "
            f"are each method's 10 best *different shots*, pairwise at least {s['min_separation']:g} degrees apart "
            "(camera centres seen from the room's focus, viewing directions, distance ratio); dCVIR is their mean "
            "gain over the best training view.",
            "",
            "Each seed's best view: Waldo's visible share (exact), the PSNR of the NeRF's render against the "
            "analytic truth at the demo's resolution, over the whole view and over Waldo's own pixels (his mask from "
            "the room's geometry), and on the close-up of Waldo from there (below):",
            "",
            "| method | " + " | ".join(f"seed {k}" for k in seeds) + " |",
            "|---|" + "---|" * len(seeds),
            *seed_rows,
            "",
            f"Best training view: score {summary['best_train_score']:.4f}, Waldo {summary['best_train_visible']:.0%} "
            f"visible. The training views together see {summary['waldo_surface_seen_in_training']:.0%} of Waldo's "
            "surface (the NeRF can only render what they saw). "
            f"Highest mCVIR: **{winner.upper()}**.",
            "",
            f"NeRF (hash grid, fast preset, {nerf['steps']} steps, {nerf['seconds']:.0f} s on {nerf['device']}): "
            f"held-out PSNR {nerf['psnr_test']:.2f} dB on {nerf['n_test']} unseen views like the training views. It "
            "renders the views shown below; the exact criterion does not look at the renders (the finder's row does).",
            "",
            "![best views](contact_sheet.png)",
            "",
            "Rows: the best training views, then for each method the best views it found (seed "
            f"{seeds[0]}) as the NeRF renders them and as the analytic room renders them (the truth).",
            "",
            "![Waldo close-ups](waldo_closeups.png)",
            "",
            "Close-ups: from each seed's best camera centre, turned onto Waldo and zoomed until he fills about "
            f"{CLOSEUP_FILL:.0%} of the height (one zoom per method, the median of its seeds'; the same image size), "
            "by the NeRF and by the truth.",
            "",
            "![EGPS pose cloud](egps/pose_cloud.png)",
            "",
            f"Per method: `{'/`, `'.join(summary['methods'])}/` hold results.json, topk/*.png, "
            "contact_sheet.png, poses.json and pose_cloud.png; `nerf/` is the trained run "
            f"(`waldo explore nerf --criterion {summary['criterion']} ...`).",
            "",
            f"Total {summary['seconds']['total']:.0f} s on {summary['device']}. Command: `{summary['command']}`.",
            "",
        ]
    )


def room_scenes(seed: int, settings: DemoSettings):
    """The room of `seed`, its training scene and its held-out views: (scene, room, test_scene)."""
    try:
        room = make_room(seed, waldo_scale=settings.waldo_scale, stripe_width=settings.stripe_width)
        scene, room = room_scene(
            seed, num_views=settings.views, resolution=settings.resolution, camera_config=settings.camera, room=room
        )
        test_scene = held_out_scene(room, seed, settings.test_views, scene, settings.camera)
    except ValueError as e:
        raise WaldoError(str(e)) from None
    return scene, room, test_scene


def nerf_source(run_dir: Path, seed: int, scene: Scene, room, field: TrainedField, psnr_test) -> Source:
    """The trained NeRF of the room as the searches' source, with the analytic room as its truth."""
    return Source(
        spec=str(run_dir),
        kind="run",
        name=f"NeRF of procedural:{seed}",
        train_c2w=scene.c2w,
        intrinsics=scene.intrinsics,
        renderer=field_renderer(field, gradient=NERF_GRADIENT),
        train_images=scene.images,
        train_names=scene.file_names,
        room=room,
        truth=room_renderer(room),
        info={"procedural_seed": seed, "run_dir": str(run_dir), "psnr_test": psnr_test},
        gradient=NERF_GRADIENT,
    )


# Close-ups: each seed's best view seen from the same camera centre, turned onto Waldo and zoomed so that
# he fills about `CLOSEUP_FILL` of the image's height (one zoom for all, the median of the views').
CLOSEUP_FILL = 0.6
CLOSEUP_MAX_ZOOM = 6.0


def closeup_cameras(room, c2w: np.ndarray, intrinsics: Intrinsics):
    """Close-up cameras of Waldo from the given views: the same centres, turned onto him, zoomed.

    Args:
      room: the `WaldoRoom`.
      c2w: float [P, 4, 4], the views (e.g. each seed's best).
      intrinsics: their camera.

    Returns:
      (c2w [P, 4, 4]: the same camera centres looking at the centroid of Waldo's surface samples, each
      with its own up vector; the intrinsics with fx, fy times `zoom`, the same image size; zoom: the
      median over the views of the zoom at which Waldo's bounding sphere spans `CLOSEUP_FILL` of the
      image height, in [1, `CLOSEUP_MAX_ZOOM`], 1 where no view gives a finite one).
    """
    c2w = np.asarray(c2w, np.float32)
    points = np.asarray(room.waldo_points)
    center = points.mean(axis=0)
    radius = float(np.max(np.linalg.norm(points - center, axis=-1)))
    distance = np.linalg.norm(c2w[:, :3, 3] - center, axis=-1)  # [P], NaN for a NaN pose
    height_px = 2.0 * radius * float(intrinsics.fy) / np.maximum(distance, 1e-3)  # Waldo's extent, unzoomed
    zooms = CLOSEUP_FILL * intrinsics.height / height_px
    zooms = zooms[np.isfinite(zooms)]
    zoom = float(np.clip(np.median(zooms), 1.0, CLOSEUP_MAX_ZOOM)) if zooms.size else 1.0
    cameras = jax.vmap(look_at, in_axes=(0, None, 0))(
        jnp.asarray(c2w[:, :3, 3]), jnp.asarray(center), jnp.asarray(c2w[:, :3, 1])
    )
    zoomed = intrinsics.replace(fx=intrinsics.fx * zoom, fy=intrinsics.fy * zoom)
    return np.asarray(cameras), zoomed, zoom


def _closeups(source: Source, best_c2w: np.ndarray, views: int):
    """Close-ups of Waldo from each best view [P, 4, 4] by the NeRF and by the truth, and Waldo's pixels in
    them: (nerf, truth, mask [P, H, W], zoom)."""
    cameras, zoomed, zoom = closeup_cameras(source.room, best_c2w, source.intrinsics)
    nerf = render_in(functools.partial(source.render, intrinsics=zoomed), cameras, views)
    truth = render_in(functools.partial(source.render_truth, intrinsics=zoomed), cameras, views)
    return nerf, truth, waldo_mask(source.room, cameras, zoomed), zoom


def _method_stats(run, results: Dict[str, Any], source: Source):
    """One method's line of the report: CVIR / mCVIR over seeds, Waldo's visible share at each seed's best
    view, the NeRF render's PSNR against the truth there, on a close-up of Waldo from there, and over the
    first seed's top-k. Returns (stats, (close-ups by the NeRF [P, H, W, 3], by the truth))."""
    best_c2w = jnp.asarray(np.stack([np.asarray(r.top_c2w[0]) for r in run.results]))
    visible = np.asarray(waldo_visibility_batch(source.room, best_c2w, source.intrinsics))
    views = max(len(run.top_images), 1)  # render in calls of the top-k's size: no new compilation
    best_nerf = render_in(source.render, best_c2w, views)
    best_truth = render_in(source.render_truth, best_c2w, views)
    best_psnr = image_psnr(best_nerf, best_truth)
    waldo_psnr = masked_psnr(best_nerf, best_truth, waldo_mask(source.room, best_c2w, source.intrinsics))
    top_psnr = image_psnr(run.top_images, run.top_truth)
    nerf, truth, mask, zoom = _closeups(source, np.asarray(best_c2w), views)
    closeup_psnr = image_psnr(nerf, truth)
    closeup_waldo_psnr = masked_psnr(nerf, truth, mask)
    return {
        "cvir_mean": results.get("cvir_mean", results["cvir"]),
        "cvir_std": results.get("cvir_std", 0.0),
        "mcvir_mean": results.get("mcvir_mean", results["mcvir"]),
        "mcvir_std": results.get("mcvir_std", 0.0),
        "dcvir_mean": results.get("dcvir_mean", results["dcvir"]),
        "dcvir_std": results.get("dcvir_std", 0.0),
        "shots_beating_train_per_seed": [int(r.shots_beating_train) for r in run.results],
        "paper_topk_shots_per_seed": [int(r.paper_top_shots) for r in run.results],
        "coverage_mean": float(np.mean([float(r.coverage) for r in run.results])),
        "best_mean": float(np.mean([float(r.metrics.best[-1]) for r in run.results])),
        "best_visible_mean": float(np.mean(visible)),
        "best_visible_per_seed": visible.tolist(),
        "found_seeds": int(np.sum(visible >= FOUND_VISIBILITY)),
        "best_psnr_mean": float(np.mean(best_psnr)),
        "best_psnr_per_seed": best_psnr.tolist(),
        "waldo_psnr_mean": float(np.nanmean(waldo_psnr)) if np.isfinite(waldo_psnr).any() else None,
        "waldo_psnr_per_seed": [float(v) if np.isfinite(v) else None for v in waldo_psnr],
        "closeup_waldo_psnr_per_seed": [float(v) if np.isfinite(v) else None for v in closeup_waldo_psnr],
        "top_psnr_mean": float(np.mean(top_psnr)),
        "top_psnr": top_psnr.tolist(),
        "closeup_zoom": zoom,
        "closeup_psnr_mean": float(np.mean(closeup_psnr)),
        "closeup_psnr_per_seed": closeup_psnr.tolist(),
        "seconds": run.seconds["search"],
        "per_seed": results.get("per_seed"),
    }, (nerf, truth)


def _method_rows(exact, finder, renders_method: Optional[str]):
    """(key, method, criterion, scores renders) of the demo's searches: GRS, PIBS and EGPS at the low budget
    by the exact criterion, then `renders_method` on the NeRF's renders by the finder (`<method>_on_renders`)
    when there is a finder."""
    rows = [(m, m, exact, False) for m in METHOD_ORDER]
    return rows + ([(renders_method + RENDERS_SUFFIX, renders_method, finder, True)] if finder else [])


def _run_methods(out: Path, source: Source, prepared, rows, settings: DemoSettings, seed: int, say):
    """The searches of `rows` (`_method_rows`), `settings.seeds` seeds each, from their preparations
    (`_Preparing`'s futures, in the same order), written to out/<key>/: (runs, stats, close-ups) by key."""
    runs, methods, closeups = {}, {}, {}
    for (key, method, criterion, on_renders), ready in zip(rows, prepared):
        what = f" on the NeRF's renders ({criterion.name} finder)" if on_renders else ""
        say(f"[demo] {method.upper()}{what}: {settings.seeds} seeds at the low budget ...", flush=True)
        run = run_prepared(ready.result()._replace(source=source))
        title = f"{method.upper()} on procedural:{seed}, {criterion.name}"
        runs[key], methods[key], closeups[key] = _method_outputs(out, key, run, source, on_renders, title)
        m = methods[key]
        say(
            f"[demo] {method.upper()}{what}: CVIR {m['cvir_mean']:.0f} ± {m['cvir_std']:.0f} %, "
            f"mCVIR {m['mcvir_mean']:.0f} ± {m['mcvir_std']:.0f} %; Waldo {m['best_visible_mean']:.0%} visible "
            "in the best views "
            f"({m['found_seeds']}/{settings.seeds} found), NeRF {m['best_psnr_mean']:.1f} dB there, "
            f"{m['closeup_psnr_mean']:.1f} dB on Waldo's close-up",
            flush=True,
        )
    return runs, methods, closeups


class _Preparing:
    """The methods' searches prepared (`prepare_explore`: checks, the training views' scores, the compile)
    on threads, all at once: their compiles, each on one core, overlap one another and the searches that
    run meanwhile (the quick demo's three took 9 s one after another on the 2-core CPU). A context
    manager: on leaving it (Ctrl-C included) the preparations not started are cancelled."""

    def __init__(self, source: Source, rows, settings: DemoSettings, seed: int):
        self._pool = concurrent.futures.ThreadPoolExecutor(max_workers=len(rows), thread_name_prefix="prepare")
        self._futures = [
            self._pool.submit(
                prepare_explore,
                source,
                criterion,
                ExploreConfig(method=method, budget="low", min_separation=settings.min_separation),
                seed,
                settings.seeds,
            )
            for _, method, criterion, _ in rows
        ]

    def __enter__(self):
        return self._futures

    def __exit__(self, *exc):
        self._pool.shutdown(wait=exc[0] is None, cancel_futures=True)
        return False


def _method_outputs(out: Path, key: str, run, source: Source, scores_renders: bool, title: str):
    """A method's folder out/<key>/ written (`title` its figures'), and its (run, stats, close-ups)."""
    (out / key).mkdir()
    results = write_outputs(run, out / key, title=title)
    stats, closeups = _method_stats(run, results, source)
    stats["scores_renders"] = scores_renders
    stats["criterion"] = run.criterion.name
    return run, stats, closeups


def _label(key: str) -> str:
    """A method's name in tables and figures ("EGPS", "GRS on renders")."""
    return f"{key[: -len(RENDERS_SUFFIX)].upper()} on renders" if key.endswith(RENDERS_SUFFIX) else key.upper()


def _db(value) -> str:
    """A PSNR for a label or table cell: "21.3 dB", or "n/a" where Waldo has no pixel."""
    return "n/a" if value is None or not np.isfinite(value) else f"{value:.1f} dB"


def closeup_sheet(methods: Dict[str, Any], closeups: Dict[str, Any], seeds) -> np.ndarray:
    """uint8 sheet of Waldo's close-ups, one column per seed.

    Args:
      methods: per method its report statistics (`best_visible_per_seed`, `closeup_psnr_per_seed`,
        `closeup_zoom`).
      closeups: per method (close-ups by the NeRF [S, H, W, 3], by the truth [S, H, W, 3]).
      seeds: the S seeds.

    Returns:
      uint8 sheet: per method a row by the NeRF (tiles labelled with the seed and Waldo's visible share in
      its best view) above a row by the truth (labelled with the NeRF's PSNR there), under a caption.
    """
    images, labels, titles = [], [], []
    for method, (nerf, truth) in closeups.items():
        m = methods[method]
        if not len(nerf) == len(truth) == len(seeds):
            raise ValueError(f"{method}: {len(nerf)} and {len(truth)} close-ups for {len(seeds)} seeds")
        images += list(nerf) + list(truth)
        labels += [f"seed {k} {v:.0%}" for k, v in zip(seeds, m["best_visible_per_seed"], strict=True)]
        labels += [
            f"{p:.1f} | W {_db(w)}" for p, w in zip(m["closeup_psnr_per_seed"], m["closeup_waldo_psnr_per_seed"])
        ]
        titles += [f"{_label(method)} (NeRF) x{m['closeup_zoom']:.1f}", f"{_label(method)} (truth)"]
    caption = (
        "Waldo close-ups: each seed's best view, turned from its camera centre onto Waldo and zoomed (the zoom "
        f"after the method) so that he fills about {CLOSEUP_FILL:.0%} of the height; "
        f"NeRF tiles: the seed and Waldo's visible share in that best view (found: >= {FOUND_VISIBILITY:.0%}); "
        "truth tiles: the NeRF's PSNR against it in dB over the whole close-up | over Waldo's own pixels (W)"
    )
    return io.contact_sheet(images, columns=len(seeds), labels=labels, row_titles=titles, caption=caption)


def _command(quick: bool, seed: int, settings: DemoSettings) -> str:
    """The `waldo demo` command line of a run (settings beyond `--train-steps` and `--search-renders` are not
    flags)."""
    command = "waldo demo" + (" --quick" if quick else "") + ("" if seed == DEMO_ROOM_SEED else f" --seed {seed}")
    steps, renders = settings.train_steps, settings.search_renders
    command += "" if steps == demo_settings(quick, renders).train_steps else f" --train-steps {steps}"
    if renders is not None:
        command += " --search-renders" + ("" if renders == RENDERS_METHOD else f" {renders}")
    return command


def run_demo(
    out: Optional[str | Path] = None,
    quick: bool = False,
    seed: Optional[int] = None,
    progress: bool = True,
    settings: Optional[DemoSettings] = None,
) -> Path:
    """Runs the demo and returns its output directory (see the module docstring).

    Args:
      out: a new (or empty) directory; default `default_demo_dir()`.
      quick: smaller settings (fewer views and seeds, shorter training).
      seed: the room's seed and the first search seed (default `DEMO_ROOM_SEED`).
      progress: progress bar and per-epoch lines.
      settings: explicit sizes (overrides `quick`'s; `quick` still names the command in the report).
    """
    settings = settings or SETTINGS["quick" if quick else "full"]
    seed = DEMO_ROOM_SEED if seed is None else int(seed)
    if settings.search_renders is not None and settings.search_renders not in RENDERS_METHODS:
        raise WaldoError(
            f"search_renders must be one of {', '.join(RENDERS_METHODS)} (or None), got {settings.search_renders!r}"
        )
    out = io.prepare_output_dir(default_demo_dir() if out is None else out, force=False, can_force=False)
    t0 = time.perf_counter()
    say = print if progress else (lambda *a, **k: None)
    say(f"[demo] rendering {settings.views} training views of procedural:{seed} ...", flush=True)
    scene, room, test_scene = room_scenes(seed, settings)
    t_scene = time.perf_counter()
    say(f"[demo] training the hash-grid NeRF ({settings.train_steps} steps) ...", flush=True)
    (out / "nerf").mkdir()
    # With the render step given, the held-out evaluation leaves the field as it is: it runs while the
    # searches are prepared (`_Preparing`), their compiles and its own side by side. A calibrated step
    # (render_step_scale None) changes the field's renders: the evaluation comes first.
    calibrated = settings.render_step_scale is None
    trained, stats = train_room_nerf(scene, test_scene if calibrated else None, settings, seed, out / "nerf", progress)
    field = TrainedField.from_result(trained, scene)
    source = nerf_source(out / "nerf", seed, scene, room, field, stats.get("psnr_test"))
    context = CriterionContext(room=room, source=source.spec, train_c2w=source.train_c2w)
    criterion = make_criterion(settings.criterion, context)
    finder = None
    if settings.search_renders:
        reference = waldo_reference(room)
        io.save_png(out / "waldo_reference.png", reference)
        finder = make_criterion(RENDERS_CRITERION, dataclasses.replace(context, target=reference))
    rows = _method_rows(criterion, finder, settings.search_renders)
    with _Preparing(source, rows, settings, seed) as prepared:
        if not calibrated:
            trained, stats = evaluate_run(trained, (scene, test_scene), out / "nerf", seed, progress=progress)
            source = dataclasses.replace(source, info={**source.info, "psnr_test": stats["psnr_test"]})
        stats = {k: v for k, v in stats.items() if k != "history"}  # the loss history stays in nerf/train.json
        t_train = time.perf_counter()
        runs, methods, closeups = _run_methods(out, source, prepared, rows, settings, seed, say)

    # One sheet like the paper's qualitative figures: training views, then each method's best views (by
    # the exact criterion; the finder's row has its own scores, in <method>_on_renders/contact_sheet.png).
    first = runs["egps"]
    exact_runs = {k: runs[k] for k in METHOD_ORDER}
    io.save_png(out / "contact_sheet.png", methods_sheet(exact_runs, max(len(first.top_images), 1)))
    io.save_png(out / "waldo_closeups.png", closeup_sheet(methods, closeups, first.seeds))

    train_visible = np.asarray(waldo_visibility_batch(room, jnp.asarray(scene.c2w), scene.intrinsics))
    best_train = int(np.nanargmax(first.scores_train))
    total = time.perf_counter() - t0
    summary = {
        "room_seed": seed,
        "criterion": criterion.name,
        "criterion_caption": criterion_caption(criterion),
        "settings": dataclasses.asdict(settings),
        "seeds": first.seeds,
        "n_train": scene.n_images,
        "children_per_epoch": first.config.children_per_epoch,
        "best_train_score": float(first.scores_train[best_train]),
        "best_train_visible": float(train_visible[best_train]),
        "waldo_surface_seen_in_training": float(waldo_surface_seen(room, jnp.asarray(scene.c2w), scene.intrinsics)),
        "nerf": stats,
        "methods": methods,
        "egps_ahead_of_grs_on_mcvir": bool(methods["egps"]["mcvir_mean"] > methods["grs"]["mcvir_mean"]),
        "seconds": {
            "scene": round(t_scene - t0, 2),
            "train": round(t_train - t_scene, 2),
            "search_and_files": round(time.perf_counter() - t_train, 2),
            "total": round(total, 2),
        },
        "device": stats["device"],
        "command": _command(quick, seed, settings),
    }
    io.write_json(out / "summary.json", summary)
    io.write_text(out / "report.md", _report(out, summary))
    say(f"[demo] done in {total:.0f} s: {out / 'report.md'}", flush=True)
    return out

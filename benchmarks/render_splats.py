"""Rendering 3D Gaussian splats (`waldo_jax.splats.render`): views/s of populations, and beside the NeRF.

Two parts, one JSON (device, commit, versions: `bench_common.header`):

  synthetic  N splats (`--counts`, default 10k,100k,1M on an accelerator, 10k,100k on a CPU) in the
             box [-0.5, 0.5]^3: means uniform, scales 0.5 x the mean spacing N^(-1/3) with a log-normal
             spread (sigma 0.3 per axis), random unit quaternions, opacities uniform in [0.1, 0.9] (as
             logits), random colours (SH degree `--sh-degree`, default 0; higher bands N(0, 0.1)).
             Cameras on a sphere around the box (a Fibonacci spiral between +-60 deg of elevation,
             z up) looking at its centre, `--fov-deg` 50 deg, at the distance where the box's bounding
             sphere fills the view. For each (count, size, population) cell (`--sizes` 64,128,256;
             `--populations` 1,16,256 on an accelerator, 1,16 on a CPU): `max_pairs` calibrated on those
             very poses (`calibrate_max_pairs`, margin 1, so no view drops a pair), one compilation
             (timed apart), one untimed run (the stats), then the batched call timed `--repeats`
             times (best and median; fewer repeats when they would pass `--max-seconds-per-cell`):
             views/s, rays/s, max_pairs, pairs per view, pose_chunk, overflow (asserted zero). A cell
             whose estimated time passes `--max-seconds-per-cell` is skipped and recorded with its
             reason, as is every cell of the issue's grid left out of this run. `stages`: for one cell
             (`--stages-cell`), the projection alone, the projection + tile lists, and the whole render,
             timed alternately with the same pose loop: where the time goes.
  scenes     fitted splats (a run of `waldo train --model splat`) beside the trained NeRF (a run of
             `waldo train`) of the same scene: `--pair NAME=SPLAT_RUN:NERF_RUN[:SCENE_PATH[:DOWNSCALE]]`
             (repeatable; the scene and downscale default to the splat run's train.json), or
             `--splat-run/--nerf-run/--scene/--downscale` (repeatable, in step). Both render the same
             `--scene-population` (256) poses (the training poses, the held-out ones, then SLERP
             midpoints: render_trained.py's `timing_poses`) with the same square-pixel camera
             (`timing_camera`, `--scene-sizes` 128) in one call each, timed alternately
             (`timed_alternately`): views/s of each and their ratio. Held-out PSNR: each run's
             train.json, and both re-measured here on the held-out views at the training resolution
             (`splats.fit.evaluate_splats`, `nerf.trained.evaluate`), with their difference.

Peak memory: on a GPU `memory_stats()["peak_bytes_in_use"]`, on a CPU `getrusage(RUSAGE_SELF).ru_maxrss`;
both are the process's peak so far (read after each cell: a cell's figure includes every earlier
cell's), so each cell also records its compiled program's own sizes (`memory_analysis`).

  python benchmarks/render_splats.py --out benchmarks/results/render_splats_synthetic_cpu.json
  python benchmarks/render_splats.py --parts scenes --pair lego=runs/lego_splat:runs/lego_nerf \\
      --pair fox=runs/fox_splat:runs/fox_nerf:../shared/scenes/fox:8 --out
      benchmarks/results/render_splats_scenes_cpu.json
  python benchmarks/render_splats.py --quick          # tiny synthetic smoke test (seconds)

The JSON is printed; `--out` writes it (never over an earlier result; a shared machine's result goes
under its `_loaded` name).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import math
import resource
import statistics
import sys
import time
from pathlib import Path
from typing import Optional

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, timed_alternately, wait_for_quiet  # noqa: E402
from waldo_jax.cameras import look_at  # noqa: E402
from waldo_jax.pipeline.splat_sources import calibrate_max_pairs  # noqa: E402
from waldo_jax.splats.model import Splats, make_splats, sh_coefficients  # noqa: E402
from waldo_jax.splats.render import (  # noqa: E402
    SplatRenderConfig,
    default_pose_chunk,
    project,
    render_splats,
    tile_lists,
)
from waldo_jax.splats.sh import SH_C0  # noqa: E402
from waldo_jax.types import Intrinsics  # noqa: E402

# The issue's grid: every cell of it appears in the JSON, measured or skipped with its reason.
ISSUE_COUNTS = (10_000, 100_000, 1_000_000)
ISSUE_SIZES = (64, 128, 256)
ISSUE_POPULATIONS = (1, 16, 256)
# What a run measures by default, per backend (a CPU cannot do the 1M-splat or 256-pose cells in
# reasonable time; they are recorded as skipped).
DEFAULTS = {
    "cpu": {
        "counts": (10_000, 100_000),
        "sizes": ISSUE_SIZES,
        "populations": (1, 16),
        "max_seconds_per_cell": 120.0,
        "stages_cell": (100_000, 128, 16),
    },
    "accelerator": {
        "counts": ISSUE_COUNTS,
        "sizes": ISSUE_SIZES,
        "populations": ISSUE_POPULATIONS,
        "max_seconds_per_cell": 60.0,
        "stages_cell": (100_000, 128, 256),
    },
    "quick": {
        "counts": (2_000,),
        "sizes": (32,),
        "populations": (1, 4),
        "max_seconds_per_cell": 30.0,
        "stages_cell": (2_000, 32, 4),
    },
}
BOX_HALF = 0.5  # the synthetic splats fill [-BOX_HALF, BOX_HALF]^3
MAX_ELEVATION_DEG = 60.0
SCALE_SPREAD = 0.3  # sigma of the log-normal spread of the synthetic scales
# Splats x poses one calibration call projects at once (count_pairs's pose loop holds [poses, N] arrays).
CALIBRATION_SPLAT_POSES = 2**22
SCENE_TARGET = {"size": 128, "population": 256, "ratio": 5.0, "psnr_within_db": 1.0}
GPU_TARGETS = (
    {"count": 100_000, "size": 128, "population": 256, "views_per_s": 1000.0},
    {"count": 1_000_000, "size": 256, "population": None, "views_per_s": 50.0},
)


def log(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


# ---------------------------------------------------------------------------------------------
# Synthetic scenes.


def synthetic_splats(count: int, sh_degree: int = 0, seed: int = 0) -> Splats:
    """`count` random splats in [-BOX_HALF, BOX_HALF]^3 (see the module docstring)."""
    rng = np.random.default_rng(seed)
    means = rng.uniform(-BOX_HALF, BOX_HALF, (count, 3))
    spacing = (2 * BOX_HALF) * count ** (-1.0 / 3.0)
    log_scales = np.log(0.5 * spacing) + SCALE_SPREAD * rng.standard_normal((count, 3))
    quats = rng.standard_normal((count, 4))
    quats /= np.linalg.norm(quats, axis=-1, keepdims=True)
    opacity = rng.uniform(0.1, 0.9, count)
    logits = np.log(opacity / (1.0 - opacity))
    sh = np.zeros((count, sh_coefficients(sh_degree), 3))
    sh[:, 0] = (rng.uniform(0.0, 1.0, (count, 3)) - 0.5) / SH_C0
    sh[:, 1:] = 0.1 * rng.standard_normal((count, sh.shape[1] - 1, 3))
    return make_splats(means, log_scales, quats, logits, sh)


def synthetic_camera(size: int, fov_deg: float) -> Intrinsics:
    """A size x size square-pixel pinhole with a `fov_deg` field of view."""
    return Intrinsics.from_fov(size, size, math.radians(fov_deg))


def synthetic_poses(count: int, fov_deg: float) -> np.ndarray:
    """`count` cameras (OpenGL c2w float32 [count, 4, 4]) on a Fibonacci spiral over the sphere (between
    +-MAX_ELEVATION_DEG of elevation, z up) around the box, looking at its centre, at the distance where
    the box's bounding sphere just fills the field of view."""
    radius = math.sqrt(3.0) * BOX_HALF
    distance = radius / math.sin(math.radians(fov_deg) / 2)
    i = np.arange(count) + 0.5
    z = math.sin(math.radians(MAX_ELEVATION_DEG)) * (1.0 - 2.0 * i / count)
    angle = i * math.pi * (3.0 - math.sqrt(5.0))  # the golden angle
    ring = np.sqrt(1.0 - z * z)
    origins = distance * np.stack([ring * np.cos(angle), ring * np.sin(angle), z], -1)
    c2w = jax.vmap(look_at, in_axes=(0, None, None))(
        jnp.asarray(origins, jnp.float32), jnp.zeros(3, jnp.float32), jnp.array([0.0, 0.0, 1.0], jnp.float32)
    )
    return np.asarray(c2w, np.float32)


# ---------------------------------------------------------------------------------------------
# Measuring one batched render.


def calibrate(splats: Splats, c2w: np.ndarray, intrinsics: Intrinsics, config: SplatRenderConfig) -> int:
    """`calibrate_max_pairs(margin=1)` over all of `c2w`, in groups small enough for the splat count
    (the max over groups of the rounded-up maxima is the rounded-up maximum)."""
    group = max(1, min(64, CALIBRATION_SPLAT_POSES // max(splats.count, 1)))
    best = 0
    for first in range(0, len(c2w), group):
        part = c2w[first : first + group]
        if len(part) < group and len(c2w) > group:  # one compiled shape: pad with the last pose
            part = np.concatenate([part, np.repeat(part[-1:], group - len(part), axis=0)])
        best = max(best, calibrate_max_pairs(splats, part, intrinsics, config, margin=1.0))
    return best


def slots_per_view(config: SplatRenderConfig, intrinsics: Intrinsics) -> int:
    """Alpha evaluations one pass over a view's chunk slots costs: chunk_slots x chunk x tile_size^2
    (the renderer's work per view, whatever the view needs; two passes: transmittance, then colour)."""
    return config.chunk_slots(intrinsics) * config.chunk * config.tile_size**2


def peak_memory() -> dict:
    """The process's peak memory so far."""
    device = jax.devices()[0]
    stats = None
    try:
        stats = device.memory_stats()
    except Exception:  # noqa: BLE001 - a backend without memory stats
        stats = None
    if device.platform != "cpu" and stats and "peak_bytes_in_use" in stats:
        return {
            "bytes": int(stats["peak_bytes_in_use"]),
            "what": "device memory_stats()['peak_bytes_in_use']: the process's peak so far, every earlier cell "
            "included",
        }
    return {
        "bytes": int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024,
        "what": "getrusage(RUSAGE_SELF).ru_maxrss: the process's peak resident memory so far (host), every "
        "earlier cell included",
    }


def program_memory(compiled) -> Optional[dict]:
    """The compiled program's own sizes (XLA's memory analysis), or None where the backend gives none."""
    try:
        analysis = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - not every backend implements it
        return None
    if analysis is None:
        return None
    sizes = {
        name: int(getattr(analysis, f"{name}_size_in_bytes", 0) or 0)
        for name in ("argument", "output", "temp", "generated_code")
    }
    sizes["total"] = sizes["argument"] + sizes["output"] + sizes["temp"]
    return sizes


def compile_render(
    splats: Splats, c2w: np.ndarray, intrinsics: Intrinsics, config: SplatRenderConfig, background: np.ndarray
):
    """(the compiled batched render, compile seconds, its arguments): `render_splats` of all of `c2w`."""

    def run(splats, c2w, background):
        return render_splats(splats, c2w, intrinsics, config, background)

    args = (splats, jnp.asarray(c2w), jnp.asarray(background, jnp.float32))
    start = time.perf_counter()
    compiled = jax.jit(run).lower(*args).compile()
    return compiled, time.perf_counter() - start, args


def time_calls(fn, repeats: int, max_seconds: float):
    """One untimed call (its output returned), then up to `repeats` timed calls, fewer when they would
    pass `max_seconds` (at least one). Returns (output, warm-up seconds, times)."""
    start = time.perf_counter()
    output = jax.block_until_ready(fn())
    first = time.perf_counter() - start
    repeats = max(1, min(repeats, int(max_seconds // max(first, 1e-9))))
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return output, first, times


def measure_cell(splats: Splats, count: int, size: int, population: int, args, base: SplatRenderConfig):
    """One (count, size, population) cell of the synthetic part: (its record, its compiled render as a
    function of nothing)."""
    intrinsics = synthetic_camera(size, args.fov_deg)
    c2w = synthetic_poses(population, args.fov_deg)
    background = np.zeros(3, np.float32)
    start = time.perf_counter()
    max_pairs = calibrate(splats, c2w, intrinsics, base)
    calibration_s = time.perf_counter() - start
    config = dataclasses.replace(base, max_pairs=max_pairs)
    pose_chunk = min(config.pose_chunk or default_pose_chunk(intrinsics, config, splats=splats.count), population)
    compiled, compile_s, call_args = compile_render(splats, c2w, intrinsics, config, background)
    output, first_s, times = time_calls(lambda: compiled(*call_args), args.repeats, args.max_seconds_per_cell)
    stats = jax.device_get(output.stats)
    overflow = int(np.sum(stats.pair_overflow))
    lossy = int(np.sum(stats.lossy_pixels))
    best, median = min(times), statistics.median(times)
    pairs = np.asarray(stats.pairs, np.float64)
    cell = {
        "count": count,
        "size": size,
        "population": population,
        "status": "measured",
        "views_per_s": population / best,
        "views_per_s_median": population / median,
        "rays_per_s": population * size * size / best,
        "seconds_best": best,
        "seconds_median": median,
        "seconds_all": times,
        "repeats": len(times),
        "first_call_s": first_s,
        "compile_s": compile_s,
        "calibration_s": calibration_s,
        "max_pairs": max_pairs,
        "mean_pairs_per_view": float(pairs.mean()),
        "max_pairs_of_a_view": int(pairs.max()),
        "pairs_fill": float(pairs.max() / max_pairs),
        "mean_visible_splats": float(np.mean(stats.visible)),
        "mean_chunks_per_view": float(np.mean(stats.chunks)),
        "chunk_slots": config.chunk_slots(intrinsics),
        "max_tile_count": int(np.max(stats.max_tile_count)),
        "alpha_slots_per_view": slots_per_view(config, intrinsics),
        "alpha_slots_per_s": population * slots_per_view(config, intrinsics) / best,
        "pose_chunk": pose_chunk,
        "pair_overflow": overflow,
        "lossy_pixels": lossy,
        "mean_acc": float(np.mean(np.asarray(output.acc))),
        "program_memory_bytes": program_memory(compiled),
        "peak_memory_bytes": peak_memory()["bytes"],
    }
    if overflow or lossy:  # recorded, and main fails after writing the JSON
        log(
            f"  {count} splats, {size}^2, {population} poses: {overflow} pairs overflowed ({lossy} lossy pixels) "
            "with max_pairs calibrated on these very poses"
        )
    return cell, lambda: compiled(*call_args)


def estimate_seconds(cell_work: float, count: int, measured: list, runs: int) -> Optional[dict]:
    """The seconds `runs` batched calls of a cell of `cell_work` alpha slots would take, from the
    alpha slots/s of the measured cells: those of the same splat count when there are some, else the
    fastest of all (an optimistic guess: a cell is skipped only when even that passes the cap)."""
    same = [c for c in measured if c["count"] == count]
    pool = same or measured
    if not pool:
        return None
    basis = same[-1] if same else max(pool, key=lambda c: c["alpha_slots_per_s"])
    return {
        "seconds": runs * cell_work / basis["alpha_slots_per_s"],
        "basis": f"{basis['count']} splats, {basis['size']}^2, {basis['population']} poses",
    }


def synthetic_part(args, base: SplatRenderConfig) -> tuple:
    """(cells, stages) of the synthetic part."""
    cells, measured, stages_of = [], [], None
    requested = [(n, s, p) for n in args.counts for s in args.sizes for p in args.populations]
    for count in args.counts:
        log(f"{count} splats (SH degree {args.sh_degree})")
        splats = jax.device_put(synthetic_splats(count, args.sh_degree, args.seed))
        for size in args.sizes:
            for population in args.populations:
                where = f"{count} splats, {size}^2, {population} poses"
                # The work of the cell from the pairs of (at most 4 of) its poses: a cheap projection.
                intrinsics = synthetic_camera(size, args.fov_deg)
                sample = synthetic_poses(population, args.fov_deg)[:: max(1, population // 4)][:4]
                guess = dataclasses.replace(base, max_pairs=calibrate(splats, sample, intrinsics, base))
                work = population * slots_per_view(guess, intrinsics)
                estimate = estimate_seconds(work, count, measured, 1 + args.repeats)
                if estimate is not None and estimate["seconds"] > args.max_seconds_per_cell:
                    reason = (
                        f"estimated {estimate['seconds']:.0f} s for {1 + args.repeats} calls (from the alpha "
                        f"slots/s of {estimate['basis']}) > --max-seconds-per-cell {args.max_seconds_per_cell:g}"
                    )
                    cells.append(
                        {
                            "count": count,
                            "size": size,
                            "population": population,
                            "status": "skipped",
                            "reason": reason,
                            "estimated_seconds": estimate["seconds"],
                        }
                    )
                    log(f"  {where}: skipped ({reason})")
                    continue
                cell, render = measure_cell(splats, count, size, population, args, base)
                cell["estimated_seconds"] = None if estimate is None else estimate["seconds"]
                if args.stages_cell is not None and tuple(args.stages_cell) == (count, size, population):
                    stages_of = measure_stages(splats, size, population, cell["max_pairs"], render, args, base)
                    stages_of["cell"] = [count, size, population]
                cells.append(cell)
                measured.append(cell)
                log(
                    f"  {where}: {cell['views_per_s']:,.1f} views/s ({cell['seconds_best']:.3f} s), "
                    f"{cell['mean_pairs_per_view']:,.0f} pairs/view, max_pairs {cell['max_pairs']:,}, "
                    f"pose_chunk {cell['pose_chunk']}, compile {cell['compile_s']:.1f} s"
                )
        del splats
    if not args.quick:
        for count in ISSUE_COUNTS:
            for size in ISSUE_SIZES:
                for population in ISSUE_POPULATIONS:
                    if (count, size, population) not in requested:
                        cells.append(
                            {
                                "count": count,
                                "size": size,
                                "population": population,
                                "status": "skipped",
                                "reason": "not in this run's grid (--counts {} --sizes {} --populations {}, "
                                "the {} default unless given)".format(
                                    *(",".join(map(str, v)) for v in (args.counts, args.sizes, args.populations)),
                                    args.backend_kind,
                                ),
                            }
                        )
    stages = None
    if args.stages_cell is not None and stages_of is None:
        stages = {
            "cell": list(args.stages_cell),
            "status": "skipped",
            "reason": "the stages cell was not measured in this run (--stages-cell)",
        }
    elif stages_of is not None:
        stages = stages_of
    return cells, stages


# ---------------------------------------------------------------------------------------------
# Where the time goes: projection, tile lists, compositing.


def _checksum(*arrays) -> jax.Array:
    """One float32 scalar that depends on every element of `arrays` (so no stage is optimised away)."""
    return sum(jnp.sum(jnp.asarray(a, jnp.float32)) for a in arrays)


def stage_functions(
    splats: Splats, c2w, intrinsics: Intrinsics, config: SplatRenderConfig, pose_chunk: int, render
) -> dict:
    """Functions of nothing, each with the renderer's pose loop over `c2w` (`lax.map`, `pose_chunk`): the
    projection alone, the projection + tile lists, and `render` (the cell's compiled `render_splats`)."""

    def projected(pose):
        p = project(splats, pose, intrinsics, config)
        return p, _checksum(p.mean2d, p.conic, p.depth, p.opacity, p.rgb, p.extent, p.visible)

    def project_only(c2w):
        return jax.lax.map(lambda pose: projected(pose)[1], c2w, batch_size=pose_chunk)

    def with_lists(c2w):
        def one(pose):
            p, total = projected(pose)
            return total + _checksum(*tile_lists(p, intrinsics, config))

        return jax.lax.map(one, c2w, batch_size=pose_chunk)

    c2w = jnp.asarray(c2w)
    return {
        "project": functools.partial(jax.jit(project_only), c2w),
        "project_tile_lists": functools.partial(jax.jit(with_lists), c2w),
        "render": render,
    }


def measure_stages(
    splats: Splats, size: int, population: int, max_pairs: int, render, args, base: SplatRenderConfig
) -> dict:
    """Where one cell's time goes (see `stage_functions`); `render` is the cell's compiled render."""
    intrinsics = synthetic_camera(size, args.fov_deg)
    c2w = synthetic_poses(population, args.fov_deg)
    config = dataclasses.replace(base, max_pairs=max_pairs)
    pose_chunk = min(config.pose_chunk or default_pose_chunk(intrinsics, config, splats=splats.count), population)
    fns = stage_functions(splats, c2w, intrinsics, config, pose_chunk, render)
    times = timed_alternately(fns, args.repeats)
    project_s = times["project"][0]
    lists_s = times["project_tile_lists"][0] - project_s
    render_s = times["render"][0]
    composite_s = render_s - times["project_tile_lists"][0]
    result = {
        "status": "measured",
        "pose_chunk": pose_chunk,
        "max_pairs": max_pairs,
        "repeats": args.repeats,
        "seconds_best": {name: t[0] for name, t in times.items()},
        "seconds_median": {name: t[1] for name, t in times.items()},
        "project_s": project_s,
        "tile_lists_s": lists_s,
        "composite_s": composite_s,
        "render_s": render_s,
        "fraction": {
            "project": project_s / render_s,
            "tile_lists": lists_s / render_s,
            "composite": composite_s / render_s,
        },
        "note": "best of each, timed alternately; tile_lists = (project + tile_lists) - project, composite = "
        "render - (project + tile_lists) (gathers, the two chunk passes, the segmented scans, the image)",
    }
    log(
        f"stages ({splats.count} splats, {size}^2, {population} poses): project {project_s:.3f} s, tile lists "
        f"{lists_s:.3f} s, composite {composite_s:.3f} s of {render_s:.3f} s"
    )
    return result


# ---------------------------------------------------------------------------------------------
# Fitted splats beside the trained NeRF of the same scene.


@dataclasses.dataclass(frozen=True)
class ScenePair:
    """One scene's fitted splat run and trained NeRF run (and the scene both were fitted to)."""

    name: str
    splat_run: str
    nerf_run: str
    scene_path: Optional[str] = None
    downscale: Optional[float] = None


def parse_pair(text: str) -> ScenePair:
    """`NAME=SPLAT_RUN:NERF_RUN[:SCENE_PATH[:DOWNSCALE]]` as a `ScenePair`."""
    if "=" not in text:
        raise ValueError(f"--pair {text!r}: expected NAME=SPLAT_RUN:NERF_RUN[:SCENE_PATH[:DOWNSCALE]]")
    name, rest = text.split("=", 1)
    parts = rest.split(":")
    if not name or len(parts) < 2 or len(parts) > 4 or not all(parts[:2]):
        raise ValueError(f"--pair {text!r}: expected NAME=SPLAT_RUN:NERF_RUN[:SCENE_PATH[:DOWNSCALE]]")
    scene = parts[2] if len(parts) > 2 and parts[2] else None
    downscale = float(parts[3]) if len(parts) > 3 and parts[3] else None
    return ScenePair(name, parts[0], parts[1], scene, downscale)


def pairs_from_args(args) -> list:
    """The scene pairs of `--pair` and of `--splat-run/--nerf-run/--scene/--downscale` (in step)."""
    pairs = [parse_pair(text) for text in args.pair or []]
    splat_runs, nerf_runs = args.splat_run or [], args.nerf_run or []
    if len(splat_runs) != len(nerf_runs):
        raise SystemExit("--splat-run and --nerf-run must be given as many times as each other")
    scenes, downscales = args.scene or [], args.downscale or []
    if len(scenes) > len(splat_runs) or len(downscales) > len(splat_runs):
        raise SystemExit("--scene and --downscale go with a --splat-run / --nerf-run pair each")
    for i, (splat_run, nerf_run) in enumerate(zip(splat_runs, nerf_runs)):
        pairs.append(
            ScenePair(
                Path(splat_run).name,
                splat_run,
                nerf_run,
                scenes[i] if i < len(scenes) else None,
                downscales[i] if i < len(downscales) else None,
            )
        )
    return pairs


def read_train_json(folder) -> dict:
    """A run folder's train.json ({} when it has none)."""
    path = Path(folder) / "train.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def resolve_pair(pair: ScenePair) -> ScenePair:
    """The pair with its scene path and downscale filled from the runs' train.json where not given."""
    records = (read_train_json(pair.splat_run), read_train_json(pair.nerf_run))
    scene = pair.scene_path or next((r["scene_path"] for r in records if r.get("scene_path")), None)
    if scene is None:
        raise SystemExit(f"{pair.name}: no scene path given and none in the runs' train.json")
    downscale = pair.downscale
    if downscale is None:
        downscale = next((r["downscale"] for r in records if r.get("downscale") is not None), None)
    return dataclasses.replace(pair, scene_path=scene, downscale=downscale)


def scene_poses(train_c2w, test_c2w, population: int) -> np.ndarray:
    """The scenes part's poses, float32 [population, 4, 4]: the training poses, the held-out poses, then
    SLERP points between consecutive training poses (novel views), cut to `population`.

    render_trained.py's `timing_poses` takes the midpoints (t = 1/2) only, which leaves lego_tiny (90 + 10
    + 89) short of 256 poses; this goes on with t = 1/4, 3/4, then 1/8, 3/8, ... (its first
    len(train) + len(test) + len(train) - 1 poses are `timing_poses`' own)."""
    from waldo_jax.cameras import slerp_c2w

    train = np.asarray(train_c2w, np.float32).reshape(-1, 4, 4)
    poses = [train, np.asarray(test_c2w, np.float32).reshape(-1, 4, 4)]
    have = sum(len(p) for p in poses)
    if have < population and len(train) < 2:
        raise SystemExit(f"only {have} poses and no two training poses to interpolate: asked for {population}")
    a, b = jnp.asarray(train[:-1]), jnp.asarray(train[1:])
    between = jax.vmap(slerp_c2w, in_axes=(0, 0, None))
    level = 1
    while have < population:
        for k in range(2 ** (level - 1)):
            if have >= population:
                break
            t = (2 * k + 1) / 2**level
            points = np.asarray(between(a, b, t), np.float32)[: population - have]
            poses.append(points)
            have += len(points)
        level += 1
    return np.concatenate(poses)[:population]


def scene_camera(intrinsics: Intrinsics, size: int) -> Intrinsics:
    """A size x size square-pixel camera seeing what the scene camera's longer side sees (`timing_camera`)."""
    from render_trained import timing_camera

    return timing_camera(intrinsics, size, size)


def scene_part(pair: ScenePair, args) -> dict:
    """One scene: the fitted splats beside the trained NeRF at the same poses and camera."""
    from waldo_jax.nerf.checkpoint import load_checkpoint
    from waldo_jax.nerf.runs import load_splits
    from waldo_jax.nerf.trained import TrainedField, evaluate, render_trained
    from waldo_jax.splats.fit import evaluate_splats
    from waldo_jax.splats.io import load_splat_model

    pair = resolve_pair(pair)
    splat_record, nerf_record = read_train_json(pair.splat_run), read_train_json(pair.nerf_run)
    model = load_splat_model(pair.splat_run)
    splats = jax.device_put(model.splats)
    checkpoint = load_checkpoint(pair.nerf_run)
    config, scene = checkpoint.config, checkpoint.scene
    params, grid = jax.device_put(checkpoint.params), jax.device_put(checkpoint.occupancy)
    _, test_scene = load_splits(pair.scene_path, pair.downscale)
    if test_scene is None:
        raise SystemExit(f"{pair.name}: {pair.scene_path} has no held-out views")
    size = [test_scene.width, test_scene.height]
    for what, have in (
        ("NeRF", [scene.intrinsics.width, scene.intrinsics.height]),
        ("splat", splat_record.get("image_size")),
    ):
        if have is not None and list(have) != size:
            raise SystemExit(
                f"{pair.name}: held-out images are {size[0]}x{size[1]}, the {what} run was trained at "
                f"{have[0]}x{have[1]}: give the runs' downscale"
            )
    nerf_background = np.zeros(3, np.float32) if scene.background is None else np.asarray(scene.background, np.float32)
    splat_background = np.asarray(splat_record.get("background", nerf_background), np.float32)
    nerf_field = TrainedField.create(params, grid, config, scene.near, scene.far, nerf_background, scene.aabb)
    base = SplatRenderConfig(
        tile_size=args.tile_size, chunk=args.chunk, background=tuple(float(v) for v in splat_background)
    )

    log(f"{pair.name}: held-out PSNR of {test_scene.n_images} views at {size[0]}x{size[1]}")
    psnr_splats = evaluate_splats(splats, test_scene, base)
    psnr_nerf = evaluate(params, grid, config, test_scene)["psnr"]
    log(f"  splats {psnr_splats:.3f} dB, NeRF {psnr_nerf:.3f} dB")

    c2w = scene_poses(scene.c2w, test_scene.c2w, args.scene_population)
    population = len(c2w)
    rows = []
    for side in args.scene_sizes:
        camera = scene_camera(scene.intrinsics, side)
        splat_config = dataclasses.replace(base, max_pairs=calibrate(splats, c2w, camera, base))
        compiled, compile_s, call_args = compile_render(splats, c2w, camera, splat_config, splat_background)
        stats = jax.device_get(compiled(*call_args).stats)
        overflow = int(np.sum(stats.pair_overflow))  # recorded; main fails after writing the JSON
        c2w_device = jnp.asarray(c2w)

        def nerf():
            return render_trained(nerf_field, c2w_device, camera).rgb

        times = timed_alternately({"splats": lambda: compiled(*call_args).rgb, "nerf": nerf}, args.scene_repeats)
        splat_best, nerf_best = times["splats"][0], times["nerf"][0]
        ratio = nerf_best / splat_best
        row = {
            "size": side,
            "population": population,
            "splats": {
                "views_per_s": population / splat_best,
                "rays_per_s": population * side * side / splat_best,
                "seconds_best": splat_best,
                "seconds_median": times["splats"][1],
                "seconds_all": times["splats"][2],
                "compile_s": compile_s,
                "max_pairs": splat_config.max_pairs,
                "mean_pairs_per_view": float(np.mean(stats.pairs)),
                "pair_overflow": overflow,
                "lossy_pixels": int(np.sum(stats.lossy_pixels)),
                "pose_chunk": min(default_pose_chunk(camera, splat_config, splats=splats.count), population),
            },
            "nerf": {
                "views_per_s": population / nerf_best,
                "rays_per_s": population * side * side / nerf_best,
                "seconds_best": nerf_best,
                "seconds_median": times["nerf"][1],
                "seconds_all": times["nerf"][2],
                "render_step_scale": config.render_step_scale,
            },
            "ratio_views_per_s": ratio,
            "peak_memory_bytes": peak_memory()["bytes"],
        }
        rows.append(row)
        log(
            f"  {side}^2, {population} poses: splats {row['splats']['views_per_s']:,.1f} views/s, NeRF "
            f"{row['nerf']['views_per_s']:,.1f} views/s ({ratio:.2f}x)"
        )
    difference = psnr_splats - psnr_nerf
    at_target = next(
        (r for r in rows if r["size"] == SCENE_TARGET["size"] and r["population"] == SCENE_TARGET["population"]), None
    )
    cpu = jax.default_backend() == "cpu"
    met = None
    if at_target is not None and cpu:
        met = bool(
            at_target["ratio_views_per_s"] >= SCENE_TARGET["ratio"] and difference >= -SCENE_TARGET["psnr_within_db"]
        )
    return {
        "name": pair.name,
        "splat_run": str(Path(pair.splat_run).resolve()),
        "nerf_run": str(Path(pair.nerf_run).resolve()),
        "scene_path": str(Path(pair.scene_path).resolve()),
        "downscale": pair.downscale,
        "training_resolution": size,
        "held_out_views": test_scene.n_images,
        "splats": int(np.sum(np.asarray(model.splats.valid))),
        "sh_degree": model.splats.sh_degree,
        "backgrounds": {"splats": splat_background.tolist(), "nerf": nerf_background.tolist()},
        "psnr": {
            "splats_train_json": splat_record.get("psnr_test"),
            "nerf_train_json": nerf_record.get("psnr_test", checkpoint.info.get("psnr_test")),
            "splats_measured": psnr_splats,
            "nerf_measured": psnr_nerf,
            "difference_db": difference,
        },
        "sizes": rows,
        "ratio_views_per_s": None if at_target is None else at_target["ratio_views_per_s"],
        "target_met": met,
        "target_note": (
            ""
            if met is not None
            else "a CPU target, not judged on this backend"
            if not cpu
            else f"{SCENE_TARGET['size']}^2 x {SCENE_TARGET['population']} poses not measured"
        ),
    }


# ---------------------------------------------------------------------------------------------
# Targets and the whole run.


def targets(cells: list, scenes: list, platform: str) -> list:
    """The issue's targets as target / measured / met (met null where not measured on this backend)."""
    rows = []

    def add(target, measured, met, unit, note=""):
        rows.append({"target": target, "measured": measured, "met": met, "unit": unit, "note": note})

    gpu = platform == "gpu"
    for goal in GPU_TARGETS:
        match = [
            c
            for c in cells
            if c.get("status") == "measured"
            and c["count"] == goal["count"]
            and c["size"] == goal["size"]
            and (goal["population"] is None or c["population"] == goal["population"])
        ]
        best = max(match, key=lambda c: c["views_per_s"], default=None)
        pop = f"populations of {goal['population']}" if goal["population"] else "any population"
        text = f"GPU: >= {goal['views_per_s']:,.0f} views/s at {goal['size']}^2 for {goal['count']:,} splats ({pop})"
        measured = None if best is None else best["views_per_s"]
        note = "" if best is None else f"{best['population']} poses"
        if best is None:
            note = "not measured"
        elif not gpu:
            note += f"; measured on {platform}, not a GPU"
        add(
            text, measured, (measured >= goal["views_per_s"]) if gpu and measured is not None else None, "views/s", note
        )
    for scene in scenes:
        text = (
            f"CPU: {scene['name']}: fitted splats >= {SCENE_TARGET['ratio']:g}x the NeRF's views/s at "
            f"{SCENE_TARGET['size']}^2 in populations of {SCENE_TARGET['population']}, held-out PSNR within "
            f"{SCENE_TARGET['psnr_within_db']:g} dB or better"
        )
        measured = {
            "ratio_views_per_s": scene["ratio_views_per_s"],
            "psnr_difference_db": scene["psnr"]["difference_db"],
        }
        add(text, measured, scene["target_met"], "x, dB", scene["target_note"])
    if not scenes:
        add(
            f"CPU: fitted splats >= {SCENE_TARGET['ratio']:g}x the NeRF's views/s at {SCENE_TARGET['size']}^2 "
            f"(populations of {SCENE_TARGET['population']}), held-out PSNR within {SCENE_TARGET['psnr_within_db']:g} "
            f"dB",
            None,
            None,
            "x, dB",
            "not measured (the scenes part needs --pair)",
        )
    return rows


def _ints(text: str) -> tuple:
    return tuple(int(float(v)) for v in text.split(",") if v.strip())


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument(
        "--parts",
        default=None,
        help="comma list of synthetic, scenes (default: synthetic, plus scenes when pairs are given)",
    )
    parser.add_argument(
        "--quick",
        action="store_true",
        help="tiny synthetic settings for a smoke test: 2k splats, 32^2, populations 1 and 4, 1 repeat",
    )
    parser.add_argument("--counts", type=_ints, default=None, help="splat counts (default per backend)")
    parser.add_argument("--sizes", type=_ints, default=None, help="square image sides (default 64,128,256)")
    parser.add_argument("--populations", type=_ints, default=None, help="poses per call (default per backend)")
    parser.add_argument("--repeats", type=int, default=None, help="timed calls per cell (default 3; --quick 1)")
    parser.add_argument(
        "--max-seconds-per-cell",
        type=float,
        default=None,
        help="skip a cell whose estimated timed calls pass this; cut its repeats to fit it "
        "(default 120 on a CPU, 60 on an accelerator)",
    )
    parser.add_argument("--sh-degree", type=int, default=0, help="SH degree of the synthetic splats")
    parser.add_argument("--fov-deg", type=float, default=50.0, help="field of view of the synthetic cameras")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--tile-size", type=int, default=SplatRenderConfig.tile_size)
    parser.add_argument("--chunk", type=int, default=SplatRenderConfig.chunk)
    parser.add_argument(
        "--stages-cell",
        default=None,
        help="COUNT,SIZE,POPULATION of the stage breakdown, or 'none' (default per backend)",
    )
    parser.add_argument("--pair", action="append", help="NAME=SPLAT_RUN:NERF_RUN[:SCENE_PATH[:DOWNSCALE]] (repeatable)")
    parser.add_argument("--splat-run", action="append", help="a splat run folder (repeatable, with --nerf-run)")
    parser.add_argument("--nerf-run", action="append", help="a NeRF run folder (repeatable, with --splat-run)")
    parser.add_argument("--scene", action="append", help="the pair's scene (default: from the runs' train.json)")
    parser.add_argument("--downscale", action="append", type=float, help="the pair's downscale (default: train.json)")
    parser.add_argument("--scene-population", type=int, default=SCENE_TARGET["population"])
    parser.add_argument("--scene-sizes", type=_ints, default=(SCENE_TARGET["size"],))
    parser.add_argument(
        "--scene-repeats", type=int, default=None, help="timed rounds of the scenes part (default --repeats)"
    )
    parser.add_argument("--load-threshold", type=float, default=1.5)
    parser.add_argument("--out", default=None, help="also write the JSON here (never overwrites)")
    args = parser.parse_args(argv)
    refuse_existing_out(args.out)

    platform = jax.default_backend()
    args.backend_kind = "quick" if args.quick else ("cpu" if platform == "cpu" else "accelerator")
    defaults = DEFAULTS[args.backend_kind]
    args.counts = args.counts or defaults["counts"]
    args.sizes = args.sizes or defaults["sizes"]
    args.populations = args.populations or defaults["populations"]
    args.repeats = args.repeats or (1 if args.quick else 3)
    args.scene_repeats = args.scene_repeats or args.repeats
    args.max_seconds_per_cell = args.max_seconds_per_cell or defaults["max_seconds_per_cell"]
    if args.stages_cell is None:
        args.stages_cell = defaults["stages_cell"]
    elif args.stages_cell.lower() == "none":
        args.stages_cell = None
    else:
        args.stages_cell = _ints(args.stages_cell)
        if len(args.stages_cell) != 3:
            parser.error("--stages-cell takes COUNT,SIZE,POPULATION or 'none'")
    pairs = pairs_from_args(args)
    parts = (
        {"synthetic"} | ({"scenes"} if pairs else set())
        if args.parts is None
        else {p.strip() for p in args.parts.split(",") if p.strip()}
    )
    if parts - {"synthetic", "scenes"}:
        parser.error(f"--parts: unknown {sorted(parts - {'synthetic', 'scenes'})}")
    if "scenes" in parts and not pairs:
        parser.error("the scenes part needs --pair (or --splat-run and --nerf-run)")
    base = SplatRenderConfig(tile_size=args.tile_size, chunk=args.chunk)

    quiet = wait_for_quiet(args.load_threshold)
    cells, stages, scenes = [], None, []
    if "synthetic" in parts:
        cells, stages = synthetic_part(args, base)
    if "scenes" in parts:
        scenes = [scene_part(pair, args) for pair in pairs]

    measured = [c for c in cells if c["status"] == "measured"]
    result = header("render_splats")
    result.update(
        {
            "settings": {
                "parts": sorted(parts),
                "quick": args.quick,
                "defaults_of": args.backend_kind,
                "counts": list(args.counts),
                "sizes": list(args.sizes),
                "populations": list(args.populations),
                "repeats": args.repeats,
                "max_seconds_per_cell": args.max_seconds_per_cell,
                "sh_degree": args.sh_degree,
                "fov_deg": args.fov_deg,
                "seed": args.seed,
                "box": [-BOX_HALF, BOX_HALF],
                "scale": f"0.5 x N^(-1/3) x exp(N(0, {SCALE_SPREAD}^2)) per axis",
                "opacity": "uniform [0.1, 0.9]",
                "poses": f"Fibonacci spiral, elevation within +-{MAX_ELEVATION_DEG:g} deg, z up, looking at the box "
                f"centre, "
                "distance = bounding-sphere radius / sin(fov / 2)",
                "renderer": {k: v for k, v in dataclasses.asdict(base).items() if k not in ("max_pairs", "background")},
                "calibration": "max_pairs = calibrate_max_pairs(margin=1.0) on each cell's own poses",
                "scene_population": args.scene_population,
                "scene_sizes": list(args.scene_sizes),
                "scene_repeats": args.scene_repeats,
            },
            "synthetic": cells,
            "views_per_s": {f"{c['count']}/{c['size']}/{c['population']}": c["views_per_s"] for c in measured},
            "pair_overflow_total": int(sum(c["pair_overflow"] for c in measured)),
            "stages": stages,
            "scenes": scenes,
            "peak_memory": peak_memory(),
            "targets": targets(cells, scenes, platform),
            "definitions": {
                "views_per_s": "population / best seconds of one batched render_splats call of the whole population "
                "(compilation and the first call excluded, block_until_ready)",
                "rays_per_s": "views_per_s x size^2",
                "views_per_s key": "count/size/population",
                "max_pairs": "(splat, tile) pairs a view may hold: calibrate_max_pairs(margin=1.0) on the cell's own "
                "poses",
                "mean_pairs_per_view": "pairs the views needed (SplatStats.pairs), mean over the population",
                "pairs_fill": "the most pairs a view needed / max_pairs",
                "alpha_slots_per_view": "chunk_slots x chunk x tile_size^2: alpha evaluations of one pass over a "
                "view's "
                "chunk slots (the renderer does two passes), whatever the view needs",
                "pose_chunk": "poses per step of the renderer's pose loop (default_pose_chunk, at most the population)",
                "pair_overflow": "pairs dropped over the population (must be 0: asserted)",
                "program_memory_bytes": "XLA's memory analysis of the cell's compiled program (arguments, output, "
                "temp)",
                "peak_memory_bytes": "the process's peak memory after the cell (see peak_memory.what): cumulative",
                "stages": "one cell's projection, projection + tile lists, and whole render, each in the renderer's "
                "pose "
                "loop, timed alternately (best of --repeats); differences give each stage's share",
                "ratio_views_per_s": "splats' views/s / NeRF's views/s at the same poses and camera, timed alternately",
                "difference_db": "splats' re-measured held-out PSNR - NeRF's (both on the held-out views at the "
                "training resolution)",
                "target_met": "CPU target: ratio >= 5 at 128^2 x 256 poses and difference_db >= -1 (null off a CPU)",
            },
        }
    )
    emit_with_load(result, args.out, quiet, args.load_threshold)
    lost = [c for c in measured if c["pair_overflow"] or c["lossy_pixels"]]
    lost += [r for scene in scenes for r in scene["sizes"] if r["splats"]["pair_overflow"]]
    if lost:
        raise AssertionError(
            f"{len(lost)} cells overflowed max_pairs calibrated on their own poses (recorded in "
            "the JSON): a bug in calibrate_max_pairs or the renderer"
        )
    return result


if __name__ == "__main__":
    main()

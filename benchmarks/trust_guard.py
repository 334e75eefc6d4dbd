"""Trust in the renders: what the `trust` guard buys and costs on the demo's NeRF (issue 36, item 2).

`waldo demo` searches its NeRF of the procedural room with the exact pose criterion `waldo_found`; the best
views lie away from the training cameras, where the NeRF renders poorly. `trust` (waldo_jax/criteria/trust.py)
scores how well the training cameras cover a view, from poses alone. This benchmark, on the demo's setup
(room `procedural:1`, the demo's full settings, its NeRF trained once, as `waldo demo` trains it):

  1. sweep: the unguarded searches' top 10 views of every seed, rendered by the NeRF and by the analytic room;
     per (max_ratio, max_angle) of `trust`, the rank correlation of a view's trust with its render's PSNR, and
     the mean PSNR of the views trust >= 0.5 keeps and of those it drops;
  2. guard: per method and threshold t (none = unguarded), the searches with `waldo_found --guard trust:t`
     (low budget, 8 seeds in one vmapped call) and, at each seed's best view: Waldo's visible share (exact),
     whether he is found (>= 90 %), the view's trust and the PSNR of the NeRF's render against the truth;
     `--variants` repeats the first method's guarded rows with other (max_ratio, max_angle) of `trust`.

  python benchmarks/trust_guard.py --out benchmarks/results/trust_guard_room_cpu.json
  python benchmarks/trust_guard.py --methods egps --thresholds none,0.5 --out /tmp/trust_guard.json

About 5 minutes on a quiet 2-core CPU for the three methods; the JSON says when other jobs shared it
(`_loaded` name).
"""

from __future__ import annotations

import argparse
import math
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, wait_for_quiet  # noqa: E402
from waldo_jax.criteria import CriterionContext  # noqa: E402
from waldo_jax.criteria.combine import build_criterion, constrained  # noqa: E402
from waldo_jax.criteria.trust import MAX_ANGLE, MAX_RATIO, trust, trust_params, trust_scores  # noqa: E402
from waldo_jax.metrics import image_psnr  # noqa: E402
from waldo_jax.nerf.trained import TrainedField  # noqa: E402
from waldo_jax.pipeline import run_explore  # noqa: E402
from waldo_jax.pipeline import demo  # noqa: E402
from waldo_jax.procedural import FOUND_VISIBILITY, waldo_visibility_batch  # noqa: E402
from waldo_jax.search import ExploreConfig  # noqa: E402

RATIOS = (1.25, 1.5, 2.0, 3.0)
ANGLES_DEG = (10.0, 20.0, 30.0, 45.0)


def _ranks(x: np.ndarray) -> np.ndarray:
    return np.argsort(np.argsort(x, kind="stable"), kind="stable").astype(np.float64)


def spearman(a: np.ndarray, b: np.ndarray) -> float:
    """Rank correlation of a and b (ties broken by position; NaN when one is constant)."""
    ra, rb = _ranks(np.asarray(a)), _ranks(np.asarray(b))
    if np.std(a) == 0 or np.std(b) == 0:
        return float("nan")
    return float(np.corrcoef(ra, rb)[0, 1])


def render_psnr_of(source, c2w: np.ndarray) -> np.ndarray:
    """PSNR [V] of the NeRF's renders at c2w [V, 4, 4] against the analytic room, in calls of 8 poses."""
    return image_psnr(demo.render_in(source.render, c2w, 8), demo.render_in(source.render_truth, c2w, 8))


def sweep(source, runs: dict) -> dict:
    """Trust (per ratio and angle) against the NeRF's PSNR over the unguarded searches' top-10 views."""
    views = []
    for run in runs.values():
        for r in run.results:
            views.append(np.asarray(r.top_c2w)[np.asarray(r.top_valid)])
    c2w = np.concatenate(views).astype(np.float32)
    psnr = render_psnr_of(source, c2w)
    rows = []
    for ratio in RATIOS:
        for angle in ANGLES_DEG:
            params = trust_params(source.train_c2w, ratio, math.radians(angle))
            trust = np.asarray(trust_scores(params, jnp.asarray(c2w), source.intrinsics))
            kept = trust >= 0.5
            rows.append(
                {
                    "max_ratio": ratio,
                    "max_angle_deg": angle,
                    "spearman_trust_psnr": round(spearman(trust, psnr), 3),
                    "trust_mean": round(float(trust.mean()), 3),
                    "kept_at_0.5": int(kept.sum()),
                    "psnr_kept_at_0.5": round(float(psnr[kept].mean()), 2) if kept.any() else None,
                    "psnr_dropped_at_0.5": round(float(psnr[~kept].mean()), 2) if (~kept).any() else None,
                }
            )
    default = trust_params(source.train_c2w)
    trust = np.asarray(trust_scores(default, jnp.asarray(c2w), source.intrinsics))
    return {
        "views": int(len(c2w)),
        "psnr_mean": round(float(psnr.mean()), 2),
        "rows": rows,
        "default": {"max_ratio": MAX_RATIO, "max_angle_deg": round(math.degrees(MAX_ANGLE), 1)},
        "per_view": {"psnr": np.round(psnr, 2).tolist(), "trust_default": np.round(trust, 3).tolist()},
    }


def guarded(source, context, method: str, threshold, seeds: int, variant=None) -> tuple:
    """(run, row): `method` at the low budget on `waldo_found` guarded by trust:threshold (None: unguarded);
    `variant` (max_ratio, max_angle in degrees) replaces trust's defaults."""
    guards = [] if threshold is None or variant is not None else [f"trust:{threshold:g}"]
    criterion = build_criterion("waldo_found", context, guards)
    if variant is not None and threshold is not None:
        guard = trust(context)
        guard = guard.replace(params=trust_params(source.train_c2w, variant[0], math.radians(variant[1])))
        criterion = constrained(criterion, guard, threshold)
    t0 = time.perf_counter()
    run = run_explore(
        source, criterion, ExploreConfig(method=method, budget="low"), seed=demo.DEMO_ROOM_SEED, seeds=seeds
    )
    seconds = time.perf_counter() - t0
    best = np.stack([np.asarray(r.top_c2w[0]) for r in run.results]).astype(np.float32)
    visible = np.asarray(waldo_visibility_batch(source.room, jnp.asarray(best), source.intrinsics))
    params = trust_params(source.train_c2w, *(() if variant is None else (variant[0], math.radians(variant[1]))))
    trust_best = np.asarray(trust_scores(params, jnp.asarray(best), source.intrinsics))
    psnr = render_psnr_of(source, best)
    row = {
        "method": method,
        "threshold": threshold,
        "criterion": criterion.name,
        "trust_max_ratio": MAX_RATIO if variant is None else variant[0],
        "trust_max_angle_deg": round(math.degrees(MAX_ANGLE), 1) if variant is None else variant[1],
        "found_seeds": int(np.sum(visible >= FOUND_VISIBILITY)),
        "seeds": seeds,
        "visible_mean": round(float(visible.mean()), 4),
        "psnr_best_mean": round(float(psnr.mean()), 2),
        "trust_best_mean": round(float(trust_best.mean()), 3),
        "best_score_mean": round(float(np.mean([float(r.metrics.best[-1]) for r in run.results])), 4),
        "search_seconds": round(seconds, 1),
        "per_seed": {
            "visible": np.round(visible, 4).tolist(),
            "psnr": np.round(psnr, 2).tolist(),
            "trust": np.round(trust_best, 3).tolist(),
        },
    }
    return run, row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", default="egps,pibs,grs", help="comma-separated search methods")
    parser.add_argument("--thresholds", default="none,0.25,0.5,0.75", help="comma-separated trust thresholds")
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument(
        "--variants",
        default="1.25:20",
        help="comma-separated RATIO:ANGLE_DEG of trust, guarded at "
        "the same thresholds with the first method only (after its default rows; '' for none)",
    )
    parser.add_argument("--load-threshold", type=float, default=1.0)
    parser.add_argument("--wait", type=float, default=0.0, help="seconds to wait for a quiet machine (default 0)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    methods = [m for m in args.methods.split(",") if m]
    thresholds = [None if t == "none" else float(t) for t in args.thresholds.split(",") if t]
    variants = [tuple(float(x) for x in v.split(":")) for v in args.variants.split(",") if v]
    refuse_existing_out(args.out)
    quiet = wait_for_quiet(args.load_threshold, max_wait_s=args.wait)
    result = header("trust_guard")
    settings = demo.SETTINGS["full"]
    seed = demo.DEMO_ROOM_SEED
    t0 = time.perf_counter()
    scene, room, test_scene = demo.room_scenes(seed, settings)
    with tempfile.TemporaryDirectory() as run_dir:
        trained, stats = demo.train_room_nerf(scene, test_scene, settings, seed, Path(run_dir), progress=False)
        source = demo.nerf_source(
            Path(run_dir), seed, scene, room, TrainedField.from_result(trained, scene), stats["psnr_test"]
        )
        t_train = time.perf_counter() - t0
        print(f"NeRF: held-out {stats['psnr_test']:.2f} dB, {t_train:.0f} s", file=sys.stderr, flush=True)
        context = CriterionContext(room=room, source=source.spec, train_c2w=source.train_c2w)
        result.update(
            {
                "room_seed": seed,
                "settings": {
                    "views": settings.views,
                    "resolution": settings.resolution,
                    "train_steps": settings.train_steps,
                    "seeds": args.seeds,
                },
                "nerf": {"psnr_test": round(float(stats["psnr_test"]), 2), "seconds": round(t_train, 1)},
                "budget": "low",
                "criterion": "waldo_found",
            }
        )
        rows, unguarded = [], {}
        jobs = [(m, t, None) for t in thresholds for m in methods[:1]]
        jobs += [(methods[0], t, v) for v in variants for t in thresholds if t is not None]
        jobs += [(m, t, None) for m in methods[1:] for t in thresholds]
        for method, threshold, variant in jobs:
            run, row = guarded(source, context, method, threshold, args.seeds, variant)
            if threshold is None:
                unguarded[method] = run
            print(
                f"{method} trust:{threshold} {variant or ''}: found {row['found_seeds']}/{args.seeds}, visible "
                f"{row['visible_mean']:.2f}, PSNR {row['psnr_best_mean']:.2f} dB, "
                f"trust {row['trust_best_mean']:.2f}",
                file=sys.stderr,
                flush=True,
            )
            rows.append(row)
        result["guard"] = rows
        if unguarded:
            result["sweep"] = sweep(source, unguarded)
            for r in result["sweep"]["rows"]:
                print(r, file=sys.stderr, flush=True)
    result["seconds_total"] = round(time.perf_counter() - t0, 1)
    emit_with_load(result, args.out, quiet, args.load_threshold)


if __name__ == "__main__":
    main()

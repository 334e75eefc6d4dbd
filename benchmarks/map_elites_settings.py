"""MAP-Elites' defaults chosen by measurement: parent bias, mutation spread and grid against EGPS.

For each SOURCE:CRITERION case and budget, EGPS and each MAP-Elites setting run K seeds (one vmapped
call each, the same scored training views, the same budget): the mean best score, the mean number of
the 10 best different shots (20 degrees) that beat the best training view, and the coverage. A setting
is `elite_bias/line_probability/iso_sigma/line_sigma/AZxEL/edges`.

  python benchmarks/map_elites_settings.py --cases procedural:3:saliency,procedural:4:waldo_visible \\
      --resolution 24 --budgets low --seeds 8 --out benchmarks/results/map_elites_settings_cpu.json

The cases are rooms other than the methods table's (procedural:1) and, where given, a NeRF run; the
table's scenes are not tuned on.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from bench_common import emit_with_load, header, refuse_existing_out, wait_for_quiet  # noqa: E402
from waldo_jax.criteria import CriterionContext, build_criterion  # noqa: E402
from waldo_jax.pipeline import initial_scores, load_source, score_function, seed_keys  # noqa: E402
from waldo_jax.search import ExploreConfig, Initial, explore_seeds, map_elites  # noqa: E402
from waldo_jax.search.archive import ViewGrid  # noqa: E402

DEFAULT_SETTINGS = (
    "1/0.25/0.1/0.2/8x4/0.75,1.33",
    "1/0/0.1/0.2/8x4/0.75,1.33",
    "1/0.5/0.1/0.2/8x4/0.75,1.33",
    "1/1/0.1/0.2/8x4/0.75,1.33",
    "0/0.25/0.1/0.2/8x4/0.75,1.33",
    "2/0.25/0.1/0.2/8x4/0.75,1.33",
    "1/0.25/0.1/0.2/6x3/",
)


def parse_setting(text: str):
    """(Params, ViewGrid) of `elite_bias/line_probability/iso_sigma/line_sigma/AZxEL/edges`."""
    bias, line_probability, iso, line, grid, edges = text.split("/")
    azimuth, elevation = (int(v) for v in grid.lower().split("x"))
    params = map_elites.Params(
        elite_bias=jnp.float32(float(bias)),
        line_probability=jnp.float32(float(line_probability)),
        iso_sigma=jnp.float32(float(iso)),
        line_sigma=jnp.float32(float(line)),
    )
    cut = tuple(float(e) for e in edges.split(",")) if edges else ()
    return params, ViewGrid(azimuth_cells=azimuth, elevation_cells=elevation, distance_edges=cut)


def run(score_fn, initial, method, config, params, keys) -> dict:
    start = time.perf_counter()
    out = jax.device_get(explore_seeds(keys, score_fn, initial, method, config, params))
    results = out.results
    return {
        "best": [float(v) for v in np.asarray(results.metrics.best)[:, -1]],
        "shots_beating_train": [int(v) for v in np.asarray(results.shots_beating_train)],
        "coverage": [float(v) for v in np.asarray(results.coverage)],
        "dcvir": [float(v) for v in np.asarray(results.dcvir)],
        "seconds": round(time.perf_counter() - start, 2),
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cases", default="procedural:3:saliency,procedural:4:waldo_visible")
    parser.add_argument("--settings", default=";".join(DEFAULT_SETTINGS), help="';'-separated")
    parser.add_argument("--budgets", default="low,high")
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--load-threshold", type=float, default=1.0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    refuse_existing_out(args.out)
    quiet = wait_for_quiet(args.load_threshold, max_wait_s=300)
    result = header("map_elites_settings")
    result["settings"] = vars(args)
    rows = []
    for case in args.cases.split(","):
        spec, criterion_name = case.rsplit(":", 1)
        source = load_source(spec, args.resolution)
        criterion = build_criterion(criterion_name, CriterionContext(room=source.room, source=source.spec))
        scores, _ = initial_scores(source, criterion, "renders")
        initial = Initial(c2w=source.train_c2w, scores=scores)
        score_fn = score_function(source, criterion)
        keys = seed_keys(0, args.seeds)
        for budget in args.budgets.split(","):
            for setting in ["egps"] + args.settings.split(";"):
                if setting == "egps":
                    method, params, grid = "egps", None, ViewGrid()
                else:
                    (params, grid), method = parse_setting(setting), "map-elites"
                config = ExploreConfig(method=method, budget=budget, direction=criterion.direction, grid=grid)
                row = {"case": case, "budget": budget, "setting": setting}
                row.update(run(score_fn, initial, method, config, params, keys))
                rows.append(row)
                print(
                    f"[map-elites] {case} {budget} {setting}: best {np.mean(row['best']):.4g}, shots "
                    f"{np.mean(row['shots_beating_train']):.1f}, coverage {np.mean(row['coverage']):.2f}",
                    file=sys.stderr,
                    flush=True,
                )
                if args.out:
                    Path(args.out + ".partial").write_text(json.dumps(rows))
    lines = ["| case | budget | setting | best (mean) | shots beating the best training view (mean) | coverage |"]
    lines.append("|---|---|---|---|---|---|")
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['budget']} | {r['setting']} | {np.mean(r['best']):.4g} | "
            f"{np.mean(r['shots_beating_train']):.1f} | {np.mean(r['coverage']):.0%} |"
        )
    result.update({"rows": rows, "table": "\n".join(lines)})
    print(result["table"], file=sys.stderr)
    emit_with_load(result, args.out, quiet, args.load_threshold)
    if args.out:
        Path(args.out + ".partial").unlink(missing_ok=True)


if __name__ == "__main__":
    main()

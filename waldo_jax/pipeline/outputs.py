"""The files of an experiment (what `waldo explore` promises), written by `write_outputs`:

results.json      the run: method, criterion (its description, and criterion_caption: what the scores
                  are, their direction and range, in words), direction, seed(s), budget (null when
                  the children per epoch were set otherwise), n_train, n_generated,
                  scores_train, scores_generated (generation order), cvir and mcvir (the paper's), topk
                  [{score, c2w, image, view, ...}] (the k best different shots, `min_separation` apart),
                  train_c2w and generated_c2w (every scored pose as a 4x4 camera-to-world, in the
                  scores' order: what `waldo view` draws),
                  dcvir, shots_beating_train, paper_topk (the paper's top-k) and paper_topk_shots, archive
                  (grid, frame, coverage, QD-score, elites), epochs (per-epoch best and mean-top-N), seconds;
                  with several seeds also per_seed and the mean / std of CVIR, mCVIR and dCVIR
topk/NN.png       the top-k views, best first (the first seed's): different shots unless --min-separation 0
archive.png       the best view in each (azimuth, elevation) cell around the scene's focus (`archive_figure`)
contact_sheet.png best training views in the first row, best found views below, scores on them, the
                  criterion named above
poses.json        the top-k poses in transforms.json form (instant-ngp / nerfstudio can render them)
pose_cloud.png    every pose coloured by score at the start, after epoch 1 and at the end, the scene's
                  up vertical, with a legend
"""

from __future__ import annotations

import dataclasses

from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import jax
import numpy as np

from waldo_jax import io
from waldo_jax.pipeline.archive_figure import archive_sheet, archive_summary, view_descriptors
from waldo_jax.pipeline.experiment import ExploreRun, generated_slots
from waldo_jax.pipeline.figures import PoseCloudStyle, contact_sheet, criterion_caption, criterion_label, pose_cloud
from waldo_jax.pipeline.sources import source_world
from waldo_jax.search import Result

__all__ = ["RESULTS_JSON", "results_dict", "write_outputs"]

RESULTS_JSON = "results.json"


def _floats(values) -> List[Optional[float]]:
    """JSON-safe floats of any array (flattened; NaN / inf -> None)."""
    return [float(v) if np.isfinite(v) else None for v in np.asarray(values, np.float64).ravel()]


def _float(value) -> Optional[float]:
    return _floats([value])[0]


def _epoch_rows(result: Result) -> List[Dict[str, Any]]:
    m = result.metrics
    return [
        {
            "epoch": e,
            "best": _float(m.best[e]),
            "mean_top_n": _float(m.mean_top_n[e]),
            "scored": int(m.num_scored[e]),
            "failed": int(m.num_failed[e]),
        }
        for e in range(len(m.best))
    ]


def _budget_used(config, n_train: int) -> Any:
    """The config's budget ("low", "high" or [min, max]) when it set the children per epoch, else None: a run
    whose `children_per_epoch` was given (`--children-per-epoch`) did not use it, whatever it names."""
    try:
        derived = dataclasses.replace(config, children_per_epoch=None).resolve(n_train).children_per_epoch
    except ValueError:  # the budget leaves no children, or too few views for top_k: it cannot have set them
        return None
    if derived != config.children_per_epoch:
        return None
    return config.budget if isinstance(config.budget, str) else list(config.budget)


def results_dict(run: ExploreRun, image_names: Sequence[str]) -> Dict[str, Any]:
    """The contents of results.json (see the module docstring)."""
    config, result, source = run.config, run.result, run.source
    scores_generated, epochs_generated, slots = generated_slots(result, source.n_train)
    population = result.population
    valid = np.asarray(result.top_valid)
    indices = np.asarray(result.top_indices)[valid]
    views = view_descriptors(run, np.asarray(population.c2w)[indices])
    topk = []
    for rank, (slot, name, view) in enumerate(zip(indices, image_names, views)):
        entry = {
            "rank": rank,
            "score": _float(population.score[slot]),
            "c2w": np.round(np.asarray(population.c2w[slot], np.float64), 8).tolist(),
            "image": name,
            "epoch": int(population.epoch[slot]),
            "training_view": bool(slot < source.n_train),
            "origin": _floats(population.origin[slot]),
            "look_at": _floats(population.target[slot]),
            "up": _floats(population.up[slot]),
            "view": view,
        }
        if slot < source.n_train:
            entry["training_image"] = source.train_names[slot]
        topk.append(entry)
    paper = np.asarray(result.paper_top_indices)[np.asarray(result.paper_top_valid)]
    paper_topk = [
        {
            "rank": rank,
            "score": _float(population.score[slot]),
            "c2w": np.round(np.asarray(population.c2w[slot], np.float64), 8).tolist(),
            "epoch": int(population.epoch[slot]),
            "training_view": bool(slot < source.n_train),
            "in_topk": bool(np.any(indices == slot)),
        }
        for rank, slot in enumerate(paper)
    ]
    out: Dict[str, Any] = {
        "method": config.method,
        "criterion": run.criterion.name,
        "criterion_description": run.criterion.description,
        "criterion_caption": criterion_caption(run.criterion),
        "direction": run.criterion.direction,
        "source": source.spec,
        "source_info": source.info,
        "seed": run.seeds[0],
        "budget": _budget_used(config, source.n_train),
        "epochs_count": config.epochs,
        "children_per_epoch": config.children_per_epoch,
        "cost": config.cost(source.n_train),
        "top_k": config.top_k,
        "top_n": config.top_n,
        "resolution": [source.intrinsics.width, source.intrinsics.height],
        "initial_scores": run.initial,
        "n_train": source.n_train,
        "n_generated": int(len(slots)),
        "n_failed_generated": int(np.sum(~np.isfinite(scores_generated))),
        "scores_train": _floats(run.scores_train),
        "scores_generated": _floats(scores_generated),
        "generated_epochs": [int(e) for e in epochs_generated],
        "train_c2w": np.round(np.asarray(source.train_c2w, np.float64), 6).tolist(),
        "generated_c2w": np.round(np.asarray(population.c2w, np.float64)[slots], 6).tolist(),
        "generated_slots": [int(s) for s in slots],
        "cvir": _float(result.cvir),
        "mcvir": _float(result.mcvir),
        "min_separation": config.min_separation,
        "topk": topk,
        "dcvir": _float(result.dcvir),
        "shots_beating_train": int(result.shots_beating_train),
        "paper_topk": paper_topk,
        "paper_topk_shots": int(result.paper_top_shots),
        "archive": archive_summary(run),
        "epochs": _epoch_rows(result),
        "seconds": run.seconds,
        "device": jax.devices()[0].platform
        + (f":{jax.devices()[0].device_kind}" if getattr(jax.devices()[0], "device_kind", "") else ""),
    }
    if source.renderer_report is not None:  # what the renderer dropped over every view the run rendered
        out["renderer"] = source.renderer_report(np.asarray(population.c2w)[np.asarray(population.valid)])
    if config.method.startswith("pibs"):
        method_config = config.method_config()
        pibs_config = getattr(method_config, "base", method_config)  # a +refine method's config holds PIBS's
        out["pibs"] = {"top_c": pibs_config.top_c, "fallback": pibs_config.fallback}
    if config.gradient_renders():
        out["refine"] = dataclasses.asdict(config.refine_config())
    if len(run.seeds) > 1:
        out["seeds"] = run.seeds
        out["per_seed"] = [
            {
                "seed": s,
                "cvir": _float(r.cvir),
                "mcvir": _float(r.mcvir),
                "best": _float(r.metrics.best[-1]),
                "mean_top_n": _float(r.metrics.mean_top_n[-1]),
                "dcvir": _float(r.dcvir),
                "shots_beating_train": int(r.shots_beating_train),
                "paper_topk_shots": int(r.paper_top_shots),
                "coverage": _float(r.coverage),
                "qd_score": _float(r.qd_score),
            }
            for s, r in zip(run.seeds, run.results)
        ]
        out.update({k: _float(v) for k, v in run.stats.items()})
    return out


def write_outputs(run: ExploreRun, out: Path, title: str = "") -> Dict[str, Any]:
    """Writes results.json, topk/*.png, contact_sheet.png, archive.png, poses.json and pose_cloud.png into `out`.

    `out` must exist (see `waldo_jax.io.prepare_output_dir`). Returns the results dictionary.
    """
    out = Path(out)
    (out / "topk").mkdir(exist_ok=True)
    names = [f"topk/{i:02d}.png" for i in range(len(run.top_images))]
    written = [Path(n).name for n in names]
    for name, image in zip(names, run.top_images):
        io.save_png(out / name, image)
    if run.top_truth is not None:
        for i, image in enumerate(run.top_truth):
            io.save_png(out / "topk" / f"{i:02d}_truth.png", image)
            written.append(f"{i:02d}_truth.png")
    for path in io.stale_files(out / "topk", r"\d{2,}(_truth)?\.png", written):  # an earlier run's (--force)
        path.unlink()
    io.save_png(out / "contact_sheet.png", contact_sheet(run))
    io.save_png(out / "archive.png", archive_sheet(run))

    result = run.result
    valid_top = np.asarray(result.top_valid)
    top_scores = np.asarray(result.top_scores)[valid_top]
    io.write_transforms(
        out / "poses.json",
        np.asarray(result.top_c2w)[valid_top],
        run.source.intrinsics,
        names,
        extra={
            "waldo_explore": {
                "criterion": run.criterion.name,
                "method": run.config.method,
                "scores": _floats(top_scores),
                "min_separation": run.config.min_separation,
                "source": run.source.spec,
                "source_world": source_world(run.source),  # `waldo render --poses` on another world warns
            }
        },
    )

    population = result.population
    filled = np.asarray(population.valid)
    marker = None if run.source.room is None else np.asarray(run.source.room.waldo_center)
    style = PoseCloudStyle(
        title=title or f"{run.config.method.upper()} on {run.source.name}, {run.criterion.name}",
        marker=marker,
        marker_label="Waldo (the target)",
        score_label=criterion_label(run.criterion),
    )
    pose_cloud(
        out / "pose_cloud.png",
        np.asarray(population.c2w)[filled],
        np.asarray(population.score)[filled],
        np.asarray(population.epoch)[filled],
        run.criterion.direction,
        style=style,
    )
    results = results_dict(run, names)
    io.write_json(out / RESULTS_JSON, results)
    return results

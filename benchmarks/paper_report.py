"""The text tables of `paper_tables.py` (the paper's layout, with its own values beside ours where it
has them) and `--tables-from`: tables from one or several finished JSON runs.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Dict, List, Optional, Sequence

import paper_values


def fmt(value, digits: int = 0) -> str:
    """`value` with `digits` decimals, or n/a for None."""
    return "n/a" if value is None or not math.isfinite(float(value)) else f"{float(value):.{digits}f}"


def pm(mean, std) -> str:
    """mean ± std, or n/a."""
    return "n/a" if mean is None else f"{fmt(mean)} ± {fmt(std)}"


def _budget_label(budget: str, children: Dict[str, float]) -> str:
    return f"{budget}*" if budget in children else budget


def _undefined_notes(cells: Dict[str, Any], scenes, budgets, methods) -> List[str]:
    """Why a scene's CVIR is n/a: CVIR and mCVIR are percentages of the best training score(s).

    A cell is n/a when that base is 0 in every seed (e.g. no training render has a salient pixel at
    a small resolution) or no training view could be scored; the note gives the base and the best
    generated score, so the cell is not mistaken for a failed search.
    """
    notes = []
    for scene in scenes:
        seeds = [
            seed
            for budget in budgets
            for method in methods
            for seed in (cells.get(scene, {}).get(budget, {}).get(method) or {}).get("per_seed", [])
        ]
        if not seeds or any(s.get("cvir") is not None for s in seeds):
            continue
        bases = {s.get("best_train") for s in seeds}
        bests = [s["best"] for s in seeds if s.get("best") is not None]
        reason = (
            f"the best training score is {fmt(bases.pop(), 3)}, and CVIR is a percentage of it"
            if len(bases) == 1 and None not in bases
            else "no training view has a usable score"
        )
        best = f"; the best generated score is {max(bests):.3f}" if bests else ""
        notes.append(f"{scene}: n/a because {reason}{best}.")
    return notes


def criterion_table(criterion: str, cells: Dict[str, Any], scenes, budgets, methods, children, seeds) -> Dict[str, Any]:
    """The paper's layout for one criterion: rows (budget, method), columns (scene: CVIR, mCVIR)."""
    label = paper_values.label(criterion)
    rows, lines = [], []
    head = ["poses", "method"] + [f"{s} {m}" for s in scenes for m in ("CVIR", "mCVIR")]
    lines.append("| " + " | ".join(head) + " |")
    lines.append("|" + "---|" * len(head))
    paper_rows = []
    for budget in budgets:
        for method in methods:
            values = {}
            for scene in scenes:
                cell = cells.get(scene, {}).get(budget, {}).get(method)
                values[scene] = (
                    {
                        "cvir": pm(cell["cvir_mean"], cell["cvir_std"]),
                        "mcvir": pm(cell["mcvir_mean"], cell["mcvir_std"]),
                    }
                    if cell
                    else {"cvir": "-", "mcvir": "-"}
                )
            rows.append({"source": "ours", "budget": budget, "method": method, "cells": values})
            lines.append(
                "| "
                + " | ".join(
                    [_budget_label(budget, children), method.upper()]
                    + [values[s][k] for s in scenes for k in ("cvir", "mcvir")]
                )
                + " |"
            )
            published = {s: paper_values.lookup(criterion, s, budget, method) for s in scenes}
            if any(v is not None for v in published.values()):
                paper_cells = {
                    s: ({"cvir": fmt(v[0], 1), "mcvir": fmt(v[1], 1)} if v else {"cvir": "", "mcvir": ""})
                    for s, v in published.items()
                }
                paper_rows.append(
                    {"source": "paper", "label": label, "budget": budget, "method": method, "cells": paper_cells}
                )
                lines.append(
                    "| "
                    + " | ".join(
                        [budget, f"{method.upper()} (paper)"]
                        + [paper_cells[s][k] for s in scenes for k in ("cvir", "mcvir")]
                    )
                    + " |"
                )
    notes = [f"CVIR % | mCVIR %, mean ± std over {seeds} seeds (ours)."]
    notes += _undefined_notes(cells, scenes, budgets, methods)
    if children:
        notes.append(
            "* children per epoch overridden ("
            + ", ".join(f"{b}: {int(c)}" for b, c in children.items())
            + "): not the paper's budget."
        )
    notes += paper_values.stand_in_notes(scenes)
    table = paper_values.table_for(criterion)
    if paper_rows:
        notes.append(f"(paper) rows: {label}.")
    elif table is None:
        notes.append(f"The paper has no table for {criterion}.")
    else:
        network = paper_values.TABLES[table]["paper_network"]
        notes.append(
            f"Paper values ({network} on {paper_values.NERF}, {paper_values.SOURCE_URL}): "
            f"{paper_values.TABLES[table]['note'] or 'none for these scenes'}."
        )
    text = "\n".join([f"### {criterion}", ""] + lines + [""] + notes)
    return {
        "columns": list(scenes),
        "rows": rows,
        "paper_rows": paper_rows,
        "paper_label": label,
        "notes": notes,
        "text": text,
    }


def _reachable_note(reference: Optional[Dict[str, Any]]) -> str:
    """The footer sentence on the reachable best (empty for a JSON written before it was measured)."""
    if not reference:
        return ""
    note = (
        f" The best reachable: {reference['best']:.0%}, the best of {reference['samples']:,} poses with origins "
        f"uniform within the training cameras' bounds (the searches' origin region), aimed at Waldo; "
        f"{reference['goal_share']:.2%} of them reach {reference['goal']:.0%}."
    )
    if reference["best"] < reference["goal"]:
        note += " The goal is out of reach in this room: no method can find it."
    return note


def waldo_table(
    waldo: Dict[str, Any],
    budgets,
    methods,
    children,
    reference: Optional[Dict[str, Any]] = None,
    room_seed: Optional[int] = None,
) -> Dict[str, Any]:
    """The Waldo-room table per search criterion; `reference`: `reachable_visibility` (the known answer)."""
    lines, rows = [], []
    room = "Waldo room" if room_seed is None else f"Waldo room procedural:{room_seed}"
    for criterion, by_budget in waldo.items():
        goal = next(iter(next(iter(by_budget.values())).values()))["goal"]
        lines += [
            f"### {room}, search criterion {criterion} (visibility from the exact oracle)",
            "",
            f"| poses | method | seeds finding >= {goal:.0%} visible | best visibility (mean / max) | "
            "visibility of the best-scored view (mean) | renders to first reach it (mean) | CVIR % |",
            "|---|---|---|---|---|---|---|",
        ]
        for budget in budgets:
            for method in methods:
                r = by_budget[budget][method]
                rows.append(
                    {
                        "criterion": criterion,
                        "budget": budget,
                        "method": method,
                        "found_share": r["found_share"],
                        "best_visibility_mean": r["best_visibility_mean"],
                        "renders_to_goal_mean": r["renders_to_goal_mean"],
                    }
                )
                lines.append(
                    f"| {_budget_label(budget, children)} | {method.upper()} | "
                    f"{r['found_share']:.0%} ({round(r['found_share'] * r['seeds'])}/{r['seeds']}) | "
                    f"{fmt(r['best_visibility_mean'], 3)} / {fmt(r['best_visibility_max'], 3)} | "
                    f"{fmt(r['best_scored_visibility_mean'], 3)} | {fmt(r['renders_to_goal_mean'], 0)} | "
                    f"{fmt(r['cvir_mean'])} |"
                )
        first = next(iter(next(iter(by_budget.values())).values()))
        lines += [
            "",
            f"Best training view: {first['best_training_visibility']:.0%} of Waldo visible "
            f"({first['n_train']} training views).{_reachable_note(reference)}",
            "",
        ]
    return {"rows": rows, "text": "\n".join(lines), "reference": reference}


# Settings that must agree for runs to share a table (the scenes may differ: one run per scene).
MERGE_SETTINGS = (
    "budgets",
    "methods",
    "seeds",
    "first_seed",
    "resolution",
    "epochs",
    "top_k",
    "children_override",
    "initial_scores",
)


def _load_run(path: Path) -> Dict[str, Any]:
    try:
        data = json.loads(Path(path).read_text())
        data["settings"]["scenes"]
    except (OSError, json.JSONDecodeError, KeyError, TypeError) as error:
        raise SystemExit(f"{path}: not a paper_tables JSON ({error})") from None
    return data


def _merge_runs(paths: Sequence[Path]) -> Dict[str, Any]:
    """One run's worth of results from the JSONs of several runs of the same settings (e.g. one per scene).

    Raises SystemExit when a setting of MERGE_SETTINGS differs or two runs hold the same scene of a
    criterion (which one to print would be a guess).
    """
    runs = [_load_run(path) for path in paths]
    first = runs[0]["settings"]
    for path, run in zip(paths[1:], runs[1:]):
        for key in MERGE_SETTINGS:
            if run["settings"].get(key) != first.get(key):
                raise SystemExit(
                    f"{path}: {key} = {run['settings'].get(key)!r} differs from {paths[0]} "
                    f"({first.get(key)!r}); runs with other settings do not share a table"
                )
    results: Dict[str, Any] = {}
    for path, run in zip(paths, runs):
        for criterion, record in run["results"].items():
            merged = results.setdefault(criterion, {"scenes": {}})
            for scene, cells in record.get("scenes", {}).items():
                if scene in merged["scenes"]:
                    raise SystemExit(f"{path}: scene {scene!r} of {criterion} is also in an earlier JSON")
                merged["scenes"][scene] = cells
    scenes = list(dict.fromkeys(s for run in runs for s in run["settings"]["scenes"]))  # in the files' order
    incomplete = [f"{path}: {run['incomplete']}" for path, run in zip(paths, runs) if run.get("incomplete")]
    return {
        "settings": dict(first, scenes=scenes),
        "results": results,
        "incomplete": "; ".join(incomplete),
        "waldo": [
            (run.get("waldo") or {}, run.get("waldo_reference"), run["settings"].get("room_seed")) for run in runs
        ],
    }


def tables_from(paths) -> str:
    """The tables (Markdown) of one or several JSONs written by this script, over the scenes they completed.

    Several JSONs (runs of the same settings, e.g. one per scene) make one table per criterion.
    An interrupted run (`incomplete` in its JSON) keeps every finished cell; its tables show the
    scenes that have cells and say that the run is incomplete.
    """
    paths = [Path(paths)] if isinstance(paths, (str, Path)) else [Path(p) for p in paths]
    data = _merge_runs(paths)
    settings = data["settings"]
    budgets, methods = settings["budgets"], settings["methods"]
    children = {k: float(v) for k, v in settings.get("children_override", {}).items()}
    texts = []
    if data["incomplete"]:
        texts.append(f"**Incomplete run** ({data['incomplete']}): only the scenes with results are shown.\n")
    for criterion, record in data["results"].items():
        cells = record["scenes"]
        scenes = [s for s in settings["scenes"] if s in cells]
        if scenes:
            texts.append(
                criterion_table(criterion, cells, scenes, budgets, methods, children, settings["seeds"])["text"] + "\n"
            )
    for waldo, reference, room_seed in data["waldo"]:
        complete = all(all(m in by_budget.get(b, {}) for b in budgets for m in methods) for by_budget in waldo.values())
        if waldo and complete:
            texts.append(waldo_table(waldo, budgets, methods, children, reference, room_seed)["text"])
    return "\n".join(texts)

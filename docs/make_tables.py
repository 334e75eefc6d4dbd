"""Regenerates the generated tables of README.md and docs/*.md, and docs/data.sha256.

Every table between a pair of markers

    <!-- generated: NAME (python docs/make_tables.py) -->
    ...
    <!-- end generated: NAME -->

is rewritten from the committed result JSONs (`benchmarks/results/*.json`, which carry the date,
commit and device of each run), the paper's own numbers (read from
`$WALDO_DATA/paper/finding_waldo_tables.json` by `benchmarks/paper_values.py`: never typed in) and,
for docs/data.md, the checksums of the files under `$WALDO_DATA` (default `../shared`).

    python docs/make_tables.py            # rewrite the generated blocks (and docs/data.sha256)
    python docs/make_tables.py --check    # exit 1 when a block is out of date; write nothing

The output is committed: the docs and their tests never run this script.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import sys
from pathlib import Path
from typing import Any, Callable, Dict, List, Optional

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT))

import paper_report  # noqa: E402  (benchmarks/paper_report.py)
import paper_values  # noqa: E402  (benchmarks/paper_values.py: reads the paper's JSON)

from waldo_jax.paths import data_dir  # noqa: E402

MARKER = re.compile(
    r"(<!-- generated: (?P<name>[\w-]+) \(python docs/make_tables.py\) -->\n)"
    r"(?P<body>.*?)"
    r"(<!-- end generated: (?P=name) -->)",
    re.S,
)

IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png"}


def _json(name: str) -> dict:
    return json.loads((RESULTS / name).read_text(encoding="utf-8"))


def _shift_headings(text: str, levels: int) -> str:
    """Markdown headings of `text` moved `levels` deeper (### -> ####)."""
    return re.sub(r"^(#+) ", lambda m: "#" * (len(m.group(1)) + levels) + " ", text, flags=re.M)


def _tables(*names: str, shift: int = 0) -> str:
    """The paper-layout tables of one or several paper_tables JSONs (`paper_report.tables_from`)."""
    text = paper_report.tables_from([RESULTS / n for n in names])
    out: List[str] = []
    for line in text.strip().splitlines():
        prose = line.strip() and not line.startswith(("|", "#"))
        if prose:  # each note its own paragraph; a leading "* " is the script's mark, not a bullet
            line = re.sub(r"^\* ", r"\\* ", line)
            if out and out[-1]:
                out.append("")
        out.append(line)
    sources = ", ".join(f"`benchmarks/results/{n}`" for n in names)
    return _shift_headings("\n".join(out), shift) + f"\n\nFrom {sources}."


def _pm(mean, std, digits: int = 0) -> str:
    return f"{mean:.{digits}f} ± {std:.{digits}f}"


# ---------------------------------------------------------------------------------------------- README


def readme_paper_table() -> str:
    """Saliency at the paper's budgets on the paper's own scenes fox and face, ours beside the paper's."""
    files = {
        "fox": "paper_tables_saliency_paper_budget_cpu_fox.json",
        "face": "paper_tables_saliency_paper_budget_cpu_face_loaded.json",
    }
    lines = [
        "| scene | budget | method | CVIR % (ours) | CVIR % (paper) | mCVIR % (ours) | mCVIR % (paper) |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    seeds = set()
    for scene, name in files.items():
        data = _json(name)
        seeds.add(data["settings"]["seeds"])
        cells = data["results"]["saliency"]["scenes"][scene]
        for budget in data["settings"]["budgets"]:
            for method in data["settings"]["methods"]:
                cell = cells[budget][method]
                paper = paper_values.lookup("saliency", scene, budget, method)
                p_cvir, p_mcvir = ("n/a", "n/a") if paper is None else (f"{paper[0]:.1f}", f"{paper[1]:.1f}")
                lines.append(
                    f"| {scene} | {budget} | {method.upper()} | {_pm(cell['cvir_mean'], cell['cvir_std'])} | "
                    f"{p_cvir} | {_pm(cell['mcvir_mean'], cell['mcvir_std'])} | {p_mcvir} |"
                )
    (n_seeds,) = seeds
    label = paper_values.label("saliency")
    label = label[len("paper (") : -1] if label.startswith("paper (") and label.endswith(")") else label
    sources = " and ".join(f"`benchmarks/results/{n}`" for n in files.values())
    return "\n".join(lines) + (
        f"\n\nOurs: mean ± std over {n_seeds} seeds, CSNet saliency on 32 px renders of CPU-trained fast-preset "
        f"NeRFs, initial scores on renders at the training poses ({sources}). "
        f"Paper: {label}; read from `$WALDO_DATA/paper/finding_waldo_tables.json`."
    )


# ---------------------------------------------------------------------------------------------- results


def methods_table() -> str:
    """The methods at equal cost (room and fox), from the three methods JSONs."""
    low = _json("methods_room_fox_low_cpu_loaded.json")["table"].strip()
    high = _json("methods_fox_high_cpu_loaded.json")["table"].strip().splitlines()[2:]
    rest = _json("methods_fox_high_rest_cpu_loaded.json")["table"].strip().splitlines()[2:]
    order = ["grs", "pibs", "egps", "egps+refine", "evosax:CMA_ES", "evosax:SNES"]

    def rank(row: str) -> int:
        method = row.split("|")[3].strip().split(" ")[0]
        return order.index(method) if method in order else len(order)

    fox_high = sorted(high + rest, key=rank)
    return "\n".join([low] + fox_high) + (
        "\n\nFrom `benchmarks/results/methods_room_fox_low_cpu_loaded.json` (room, fox low), "
        "`methods_fox_high_cpu_loaded.json` (fox high: EGPS, `egps+refine`) and "
        "`methods_fox_high_rest_cpu_loaded.json` (fox high: the others)."
    )


# Different shots (issue 41): one methods.py run per scene, in this order (a `_loaded` name when the CPU was shared).
SHOTS = ("fox", "room", "donut", "lego")


def _shots_json(scene: str) -> str:
    """The scene's run: both budgets where measured, else the low budget alone (`_low`)."""
    names = [f"methods_shots_{scene}{budget}_cpu{load}.json" for budget in ("", "_low") for load in ("", "_loaded")]
    return next((name for name in names if (RESULTS / name).exists()), names[0])


def shots_table() -> str:
    """Different shots per scene, budget and method, from the `methods_shots_<scene>_cpu` JSONs."""
    names = [_shots_json(scene) for scene in SHOTS if (RESULTS / _shots_json(scene)).exists()]
    runs = [_json(name) for name in names]
    rows = [line for run in runs for line in run["shots_table"].strip().splitlines()[2:]]
    header = runs[0]["shots_table"].strip().splitlines()[:2]
    settings = runs[0]["settings"]

    def scene_text(run: dict) -> str:
        cell, s = run["cells"][0], run["settings"]
        what = {
            "fox": "a fast-preset fox NeRF",
            "donut": "the real splats, a ring of views",
            "lego": "a fast-preset lego_tiny NeRF",
        }
        budgets = "" if s["budgets"] == "low,high" else f", {s['budgets']} budget only"
        if cell["scene"] == "room":
            return f"room (`{cell['criterion']}`, exact, `procedural:{s['room_seeds']}`{budgets})"
        return f"{cell['scene']} (`{cell['criterion']}`, {cell['resolution']} px, {what[cell['scene']]}{budgets})"

    used = [scene_text(run) for run in runs]
    return "\n".join(header + rows) + (
        f"\n\n{settings['seeds']} seeds per cell, equal cost (the budget's renders, training views included), "
        f"different shots at least {settings['min_separation']:g} degrees apart, coverage over the default "
        f"{runs[0]['cells'][0]['grid']['cells']}-cell archive; in brackets 95 % bootstrap intervals over the seeds. "
        f"Scenes: {'; '.join(used)}. From " + ", ".join(f"`benchmarks/results/{n}`" for n in names) + "."
    )


REFINE_FOX = "methods_fox_refine_cpu_loaded.json"
# The same fox run and seeds, `egps+refine` alone with 4 poses x 3 steps (compared with REFINE_FOX's EGPS).
REFINE_FOX_4X3 = "methods_fox_refine_4x3_cpu.json"


def refine_fox_table() -> str:
    """EGPS against `egps+refine` on fox with the reverse-mode gradient, both budgets: REFINE_FOX (2 poses x
    3 steps, with EGPS in the same run) and, where committed, REFINE_FOX_4X3 (4 poses x 3 steps)."""
    data = _json(REFINE_FOX)
    cost = data["gradient_cost"]["fox"]
    egps = {cell["budget"]: cell for cell in data["cells"] if cell["method"] == "egps"}
    cells = data["cells"]
    sources = f"`benchmarks/results/{REFINE_FOX}`"
    if (RESULTS / REFINE_FOX_4X3).exists():
        cells = cells + _json(REFINE_FOX_4X3)["cells"]
        sources += f" and `benchmarks/results/{REFINE_FOX_4X3}`"
    lines = [
        "| budget | method | refined poses x steps | children | gradient evaluations x renders each | "
        "CVIR % [95 % CI] | mCVIR % [95 % CI] |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for cell in sorted(cells, key=lambda cell: cell["budget"] != "low"):
        c, m, k = cell["cost"], cell["mcvir"], cell["cvir"]
        grads = f"{c['gradient_evaluations']} x {c['renders_per_gradient_evaluation']}"
        grads = grads if c["gradient_evaluations"] else ""
        refine = cell.get("refine")
        shape = f"{refine['poses']} x {refine['steps']}" if refine else ""
        above = refine and m["ci95"][0] > egps[cell["budget"]]["mcvir"]["ci95"][1]
        mark = " **(> EGPS)**" if above else ""
        lines.append(
            f"| {cell['budget']} | {cell['method']}{mark} | {shape} | {c['children']} | {grads} | "
            f"{k['mean']:.1f} [{k['ci95'][0]:.1f}, {k['ci95'][1]:.1f}] | "
            f"{m['mean']:.1f} [{m['ci95'][0]:.1f}, {m['ci95'][1]:.1f}] |"
        )
    return "\n".join(lines) + (
        f"\n\n{data['settings']['seeds']} seeds per cell; a gradient measured at {cost['ratio']:.2f} renders "
        f"({cost['resolution'][1]}x{cost['resolution'][0]} px, {cost['gradient_mode']} mode), charged "
        f"{data['cells'][-1]['cost']['renders_per_gradient_evaluation']}; **(> EGPS)**: mCVIR interval wholly above "
        f"EGPS's at that budget. From {sources}."
    )


REFINE_FOX_HIGH = "methods_fox_refine_high_dec02_cpu.json"
# The same comparison on a second fox NeRF (trained with --seed 1), where committed.
REFINE_FOX_HIGH_SECOND = "methods_fox_refine_high_dec07_seed1_cpu_loaded.json"


def _fox_nerf(data: Dict[str, Any]) -> str:
    """The fox NeRF a methods run searched: its seed and held-out PSNR (`fox_nerf`, else the note's)."""
    nerf = data.get("fox_nerf")
    if nerf:
        return f"seed {nerf['seed']}, {nerf['psnr_test']:.2f} dB"
    found = re.search(r"held-out ([0-9.]+) dB", data.get("note", ""))
    return f"seed 0, {found.group(1)} dB" if found else "?"


def refine_fox_high_table() -> str:
    """EGPS against `egps+refine` on fox at the high budget with the cheaper reverse-mode gradient (issue 45),
    both in one run per fox NeRF: REFINE_FOX_HIGH and, where committed, REFINE_FOX_HIGH_SECOND."""
    runs = [REFINE_FOX_HIGH] + ([REFINE_FOX_HIGH_SECOND] if (RESULTS / REFINE_FOX_HIGH_SECOND).exists() else [])
    lines = [
        "| fox NeRF (held out) | budget | method | refined poses x steps | children | gradient evaluations x renders "
        "each | CVIR % [95 % CI] | mCVIR % [95 % CI] |",
        "|---|---|---|---:|---:|---:|---:|---:|",
    ]
    costs = []
    for name in runs:
        data = _json(name)
        cost = data["gradient_cost"]["fox"]
        costs.append(
            f"{cost['ratio']:.2f} ({cost['resolution'][1]}x{cost['resolution'][0]} px, {cost['gradient_mode']} mode)"
        )
        egps = {cell["budget"]: cell for cell in data["cells"] if cell["method"] == "egps"}
        for cell in data["cells"]:
            c, m, k = cell["cost"], cell["mcvir"], cell["cvir"]
            grads = (
                f"{c['gradient_evaluations']} x {c['renders_per_gradient_evaluation']}"
                if c["gradient_evaluations"]
                else ""
            )
            refine = cell.get("refine")
            shape = f"{refine['poses']} x {refine['steps']}" if refine else ""
            above = refine and m["ci95"][0] > egps[cell["budget"]]["mcvir"]["ci95"][1]
            lines.append(
                f"| {_fox_nerf(data)} | {cell['budget']} | {cell['method']}{' **(> EGPS)**' if above else ''} | "
                f"{shape} | {c['children']} | {grads} | {k['mean']:.1f} [{k['ci95'][0]:.1f}, {k['ci95'][1]:.1f}] | "
                f"{m['mean']:.1f} [{m['ci95'][0]:.1f}, {m['ci95'][1]:.1f}] |"
            )
    sources = " and ".join(f"`benchmarks/results/{name}`" for name in runs)
    return "\n".join(lines) + (
        f"\n\n{_json(runs[0])['settings']['seeds']} seeds per cell; a gradient measured at {' and '.join(costs)}, "
        "charged the next whole number of renders; **(> EGPS)**: mCVIR interval wholly above EGPS's on the same "
        f"NeRF. From {sources}."
    )


def waldo_found_table() -> str:
    """Waldo found: per room and method, the seeds whose best view shows him >= 90 % visible."""
    data = _json("methods_room_found_cpu_loaded.json")
    seeds = data["settings"]["seeds"]
    lines = [
        "| room | method | Waldo found (seeds) | Waldo visible in the best view (mean) | mCVIR % (95 % CI) |",
        "|---|---|---:|---:|---:|",
    ]
    for cell in data["cells"]:
        visible = sum(cell["best_visible"]) / len(cell["best_visible"])
        low, high = cell["mcvir"]["ci95"]
        lines.append(
            f"| {cell['source']} | {cell['method'].upper()} | {cell['found_seeds']} / {seeds} | "
            f"{visible:.0%} | {cell['mcvir']['mean']:.0f} [{low:.0f}, {high:.0f}] |"
        )
    budget = data["settings"]["budgets"]
    return "\n".join(lines) + (
        f"\n\nCriterion `{data['settings']['room_criterion']}`, budget {budget}, {seeds} seeds per cell, exact "
        f"(the room's oracle scores the poses; no NeRF). From `benchmarks/results/methods_room_found_cpu_loaded.json`."
    )


def paths_table() -> str:
    """Camera paths on the room: found paths against the straight path and the training trajectory."""
    data = _json("paths_room_cpu_loaded.json")
    seeds = data["settings"]["seeds"]

    def stat(entry: dict) -> str:
        return f"{entry['mean']:.4f} ± {entry['std']:.4f} [{entry['ci95'][0]:.4f}, {entry['ci95'][1]:.4f}]"

    def motion(entry: dict) -> str:
        return f"{max(entry['max_speed']['values']):.3f} / {max(entry['max_turn_degrees']['values']):.1f}"

    lines = [
        "| path | objective | mean per-frame score | worst frame | beats straight (mean / worst) | max speed / turn |",
        "|---|---|---|---|---|---|",
    ]
    for cell in data["cells"]:
        beats = cell["beats_straight_rate"]
        lines.append(
            f"| found, {cell['method']} | {cell['aggregate']} | {stat(cell['found']['mean'])} | "
            f"{stat(cell['found']['worst'])} | {round(beats['mean'] * seeds)}/{seeds} / "
            f"{round(beats['worst'] * seeds)}/{seeds} | {motion(cell['found'])} |"
        )
    first = data["cells"][0]
    lines.append(
        f"| straight, two best anchors | | {stat(first['straight']['mean'])} | "
        f"{stat(first['straight']['worst'])} | | {motion(first['straight'])} |"
    )
    lines.append(
        f"| training trajectory | | {stat(first['training']['mean'])} | {stat(first['training']['worst'])} | "
        f"| {motion(first['training'])} (breaks the limits) |"
    )
    return "\n".join(lines) + (
        f"\n\n`waldo_oracle` per frame, mean ± std over {seeds} seeds [95 % bootstrap interval]; speed in scene "
        "extents per frame and turn in degrees per frame, the largest over the seeds. From "
        "`benchmarks/results/paths_room_cpu_loaded.json`."
    )


def iqa_composition_fox_table() -> str:
    """iqa_cnn and composition on fox at the paper's budgets (the paper's rows beside ours)."""
    return _tables("paper_tables_iqa_composition_paper_budget_cpu_fox_loaded.json")


# ---------------------------------------------------------------------------------------------- performance


def perf_table() -> str:
    """The collected CPU performance report without its per-row device / commit / date columns."""
    name = "perf_cpu_collected_packed_loaded.json"
    rows = [r for r in _json(name)["table_markdown"].strip().splitlines() if r.startswith("|")]
    head = [c.strip() for c in rows[0].strip("|").split("|")]
    keep = [i for i, c in enumerate(head) if c not in ("device", "commit", "date")]
    out = []
    for row in rows:
        cells = [c.strip() for c in row.strip().strip("|").split("|")]
        out.append("| " + " | ".join(cells[i] for i in keep) + " |")
    return "\n".join(out) + (
        f"\n\nFrom `benchmarks/results/{name}` (each part's device, commit and date are in the JSON and in "
        "[the index of result files](../benchmarks/results/INDEX.md); `loaded`: measured while other jobs "
        "shared the cores, so those timings are pessimistic)."
    )


def packed_table() -> str:
    """The packed renderer and training step beside the code before them, on the same runs and settings."""
    before = _json("before_packed_renderer_cpu.json")
    fox, lego = _json("render_trained_fox_cpu.json"), _json("render_trained_lego_tiny_cpu.json")
    quick = _json("render_trained_quick_lego_tiny_cpu.json")
    step_fox, step_lego = _json("train_step_fox_cpu.json"), _json("train_step_lego_tiny_cpu.json")
    population = _json("render_population_cpu_p256.json")
    bf, bl = before["render"]["fox"], before["render"]["lego_tiny"]
    tf, tl = before["train_step"]["fox"], before["train_step"]["lego_tiny"]
    size = "x".join(str(v) for v in fox["timing_size"])
    speedups = ", ".join(f"{x['speedup_batched_over_loop']:.3f}x at {x['resolution']}^2" for x in population["sizes"])
    rows = [
        (
            "trained fox (fast preset, 1000 steps), held-out PSNR",
            f"{bf['psnr_test']:.3f} dB",
            f"{fox['psnr_test']:.3f} dB ({fox['psnr_delta_db']:+.3f} dB, step x{fox['render_step_scale']:g} chosen by "
            f"the "
            "run's own calibration)",
            ">= -0.1 dB",
            "render_trained_fox_cpu.json",
        ),
        (
            "trained fox, field evaluations per ray (held-out views)",
            f"{bf['evaluations_per_ray_psnr_views']:.0f}",
            f"**{fox['evaluations_per_ray_psnr_views']:.0f}**",
            "<= 80",
            "same",
        ),
        (
            f"trained fox, field passes per {size} view ({fox['timing_poses']} poses in one call)",
            f"{bf['passes_per_view']:.0f}",
            f"**{fox['passes_per_view']:.1f}**",
            "<= 10",
            "same",
        ),
        (
            f"trained fox, {fox['timing_poses']} poses at {size}, rays/s",
            f"{bf['rays_per_s']:,.0f}",
            f"{fox['rays_per_s']:,.0f} ({fox['rays_per_s'] / bf['rays_per_s']:.2f}x)",
            "",
            "same",
        ),
        (
            "trained fox, render efficiency (rays/s x evaluations/ray / field alone points/s)",
            "",
            f"{fox['render_efficiency']:.2f}",
            "(a GPU figure)",
            "same",
        ),
        (
            "trained fox, one batched call / loop of one-pose calls",
            "",
            f"{fox['speedup_batched_over_loop']:.2f}x",
            "",
            "same",
        ),
        (
            "trained lego_tiny (fast, 1000 steps), held-out PSNR",
            f"{bl['psnr_test']:.3f} dB",
            f"{lego['psnr_test']:.3f} dB (step x{lego['render_step_scale']:g})",
            ">= -0.1 dB",
            "render_trained_lego_tiny_cpu.json",
        ),
        (
            "trained lego_tiny, evaluations per ray (held-out) / passes per view",
            f"{bl['evaluations_per_ray_psnr_views']:.1f} / {bl['passes_per_view']:.0f}",
            f"{lego['evaluations_per_ray_psnr_views']:.1f} / **{lego['passes_per_view']:.1f}**",
            "<= 10 passes",
            "same",
        ),
        (
            f"trained lego_tiny, {lego['timing_poses']} poses at {size}, rays/s",
            f"{bl['rays_per_s']:,.0f}",
            f"{lego['rays_per_s']:,.0f} ({lego['rays_per_s'] / bl['rays_per_s']:.2f}x)",
            "",
            "same",
        ),
        (
            "trained lego_tiny, render efficiency; batched / loop",
            "",
            f"{lego['render_efficiency']:.2f}; {lego['speedup_batched_over_loop']:.2f}x",
            "",
            "same",
        ),
        (
            f"`render_trained.py --quick` (lego_tiny, {quick['run_info']['steps']} steps, trained in the run)",
            "",
            f"{quick['rays_per_s']:,.0f} rays/s, {quick['passes_per_view']:.1f} passes/view, efficiency "
            f"{quick['render_efficiency']:.2f}",
            "",
            "render_trained_quick_lego_tiny_cpu.json",
        ),
        (
            f"fox training step (fast, {step_fox['samples_per_batch']:,} samples), ms",
            f"{tf['ms_per_step']:.0f}",
            f"**{step_fox['ms_per_step']:.1f}**",
            "",
            "train_step_fox_cpu.json",
        ),
        (
            "fox step / the field's forward + backward alone on the same budget",
            f"{tf['step_over_field']:.2f}",
            f"**{step_fox['step_over_field']:.2f}**",
            "<= 3",
            "same",
        ),
        (
            "lego_tiny training step, ms; step / field",
            f"{tl['ms_per_step']:.1f}; {tl['step_over_field']:.2f}",
            f"{step_lego['ms_per_step']:.1f}; **{step_lego['step_over_field']:.2f}**",
            "<= 3",
            "train_step_lego_tiny_cpu.json",
        ),
        (
            f"`render_views`, {population['poses']} poses, batched / per-pose loop (best of {population['repeats']})",
            "",
            speedups,
            ">= 1.0",
            "render_population_cpu_p256.json",
        ),
    ]
    lines = ["| figure (CPU) | before | now | target (CPU) | file |", "|---|---|---|---|---|"]
    lines += ["| " + " | ".join(row[:4]) + f" | {row[4] if row[4] == 'same' else '`' + row[4] + '`'} |" for row in rows]
    return "\n".join(lines) + (
        '\n\n"before": the renderer and training step before the packed ones, measured on the same trained runs '
        "and settings (`benchmarks/results/before_packed_renderer_cpu.json`)."
    )


DEMO_CLOSEUPS = "demo_training_closeups_cpu_loaded.json"


def demo_closeups_table() -> str:
    """The room NeRF's training settings against its PSNR at the found views and on Waldo's close-ups."""
    data = _json(DEMO_CLOSEUPS)
    views = data["evaluation_views"]
    lines = [
        "| setting | training views | image | steps | N_max | held-out | found views | best views | Waldo close-ups "
        "| training time |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for row in data["settings"]:
        lines.append(
            f"| {row['name']} | {row['views']} | {row['resolution']} px | {row['steps']} | {row['n_max']} | "
            f"{row['psnr_test']:.2f} dB | {row['psnr_found']:.2f} dB | {row['psnr_best']:.2f} dB | "
            f"{row['psnr_closeup']:.2f} dB | {row['seconds']['train']:.0f} s |"
        )
    return "\n".join(lines) + (
        f"\n\nPSNR against the analytic room at {views['count']} found views ({views['best_views']} per-seed best "
        f"views of GRS, PIBS and EGPS, {views['seeds']} seeds, `{views['criterion']}`) and on Waldo's close-ups from "
        f"the best views (zoom x{views['closeup_zoom']:.1f}); renders at 64 px. "
        f"From `benchmarks/results/{DEMO_CLOSEUPS}`."
    )


def training_table() -> str:
    """Held-out PSNR against training time, fast preset (the packed step where measured, else the one before)."""
    names = [
        "train_quality_lego_tiny_cpu_packed.json",
        "train_quality_fox_cpu_packed.json",
        "train_quality_face_cpu_loaded.json",
        "train_quality_fern_cpu_loaded.json",
    ]
    lines = [
        "| scene | image | steps | held-out PSNR | training time | on the way | training step | file |",
        "|---|---|---:|---:|---:|---|---|---|",
    ]
    for name in names:
        d = _json(name)
        marks = ", ".join(f"{c['psnr_test']:.1f} dB at {c['train_seconds']:.0f} s" for c in d["checkpoints"][:-1])
        step = "packed" if "render_step_curve" in d else "before the packed step"
        lines.append(
            f"| {d['scene']} | {d['image_size'][0]}x{d['image_size'][1]} | {d['steps']} | "
            f"{d['psnr_test']:.2f} dB | {d['seconds']:.0f} s | {marks} | {step} | `{name}` |"
        )
    return "\n".join(lines) + (
        "\n\nFast preset, 2-core CPU; training time excludes the held-out evaluations. Rows measured while other "
        "jobs shared the machine carry `_loaded` in their file name."
    )


# ---------------------------------------------------------------------------------------------- data


def _data_root() -> Path:
    root = data_dir()
    if root is None or not root.is_dir():
        raise SystemExit("docs/data.md needs the data folder: set WALDO_DATA (default ../shared)")
    return root


def _is_image_folder(folder: Path) -> bool:
    files = [p for p in folder.iterdir()]
    return len(files) > 1 and all(p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES for p in files)


def _data_items(root: Path):
    """(files, image folders) under scenes/, splats/, weights/ and paper/, relative to `root`, sorted."""
    files, folders = [], []
    for top in ("scenes", "splats", "weights", "paper"):
        for path in sorted((root / top).rglob("*")):
            if path.is_dir() and _is_image_folder(path):
                folders.append(path)
            elif path.is_file() and not _is_image_folder(path.parent):
                files.append(path)
    return files, folders


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def folder_manifest(folder: Path) -> str:
    """The sha256 of the folder's manifest: exactly what
    `find . -type f -print0 | LC_ALL=C sort -z | xargs -0 sha256sum | sha256sum` prints inside it."""
    names = sorted(
        (p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()), key=lambda n: ("./" + n).encode()
    )
    manifest = "".join(f"{_sha256(folder / n)}  ./{n}\n" for n in names)
    return hashlib.sha256(manifest.encode()).hexdigest()


def data_files_table() -> str:
    root = _data_root()
    files, _ = _data_items(root)
    lines = ["| file (under `$WALDO_DATA`) | bytes | sha256 |", "|---|---:|---|"]
    for path in files:
        lines.append(f"| `{path.relative_to(root).as_posix()}` | {path.stat().st_size:,} | `{_sha256(path)}` |")
    return "\n".join(lines)


def data_folders_table() -> str:
    root = _data_root()
    _, folders = _data_items(root)
    lines = ["| image folder (under `$WALDO_DATA`) | files | sha256 of the sorted manifest |", "|---|---:|---|"]
    for folder in folders:
        count = sum(1 for p in folder.rglob("*") if p.is_file())
        lines.append(f"| `{folder.relative_to(root).as_posix()}/` | {count} | `{folder_manifest(folder)}` |")
    return "\n".join(lines)


def data_sha256_file() -> str:
    """docs/data.sha256: `sha256sum -c` input for every single file, paths relative to $WALDO_DATA."""
    root = _data_root()
    files, _ = _data_items(root)
    return "".join(f"{_sha256(p)}  {p.relative_to(root).as_posix()}\n" for p in files)


# ---------------------------------------------------------------------------------------------- driver

DEMO_SETTINGS_RUNS = (
    "demo_settings_base_cpu_loaded.json",
    "demo_settings_nmax_cpu_loaded.json",
    "demo_settings_steps_cpu_loaded.json",
)


def demo_waldo_pixels_table() -> str:
    """Waldo's own pixels in the demo's NeRF under other settings (`benchmarks/demo_settings.py`)."""
    lines = [
        "| setting | steps | Waldo size | stripes | covering views | N_max x | T | held-out | Waldo's surface seen "
        "| EGPS found | EGPS Waldo-pixel PSNR (mean, best seed) | seeds >= 20 dB | demo time |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name in DEMO_SETTINGS_RUNS:
        for row in _json(name)["rows"]:
            o, e = row["overrides"], row["methods"]["egps"]
            waldo = [v for v in e["waldo_psnr_per_seed"] if v is not None]
            camera = o.get("camera", {})
            lines.append(
                f"| {row['name']} | {o.get('train_steps', 500)}"
                + (f" ({o['samples_per_batch']} samples)" if "samples_per_batch" in o else "")
                + f" | x{o.get('waldo_scale', 1.0):g} | {100 * o.get('stripe_width', 0.05):.0f} cm | "
                f"{camera.get('cover_views', 0)} | {o.get('finest_resolution_scale', 0.5):g} | "
                f"2^{o.get('hash_table_log2', 16)} | {row['psnr_test']:.2f} dB | {row['waldo_surface_seen']:.0%} | "
                f"{e['found_seeds']}/{len(e['waldo_psnr_per_seed'])} | "
                f"{sum(waldo) / len(waldo):.1f} dB, {max(waldo):.1f} dB | "
                f"{e['waldo_psnr_20db_seeds']} | {row['seconds']['total']:.0f} s |"
            )
    return "\n".join(lines) + (
        "\n\nThe demo's former full settings otherwise (48 training views at 64 px, 2^15 samples per step, renders "
        "at twice the training step, 8 seeds at the low budget, `waldo_found`, room 1); `waldo demo` used "
        "scale15_stripes15_close16_steps2500 in room 1, then close16_error_x2_steps1200 in room 6 (below); "
        "stripes 5 cm x Waldo's size unless given; "
        "covering views on a ring 1.2 to 2.2 x his size from him. Times with other benchmarks on the same 2 cores. "
        "From " + ", ".join(f"`benchmarks/results/{n}`" for n in DEMO_SETTINGS_RUNS) + "."
    )


DEMO_ROOMS_RUNS = (
    "demo_settings_rooms_cpu.json",
    "demo_settings_room6_ab_cpu.json",
    "demo_settings_room6_render1_cpu.json",
    "demo_settings_room6_uniform_cpu.json",
)


def demo_rooms_table() -> str:
    """The whole demo per room and training setting: EGPS found, Waldo's pixels, time (benchmarks/demo_settings.py)."""
    lines = [
        "| room | setting | steps | pixels | training step | held-out | EGPS found | EGPS Waldo-pixel PSNR per seed "
        "| seeds >= 20 dB | training | demo time |",
        "|---:|---|---:|---|---:|---:|---:|---|---:|---:|---:|",
    ]
    for name in DEMO_ROOMS_RUNS:
        for row in _json(name)["rows"]:
            o, e = row["overrides"], row["methods"]["egps"]
            per_seed = ", ".join("n/a" if v is None else f"{v:.1f}" for v in e["waldo_psnr_per_seed"])
            lines.append(
                f"| {row['room_seed']} | {row['name']} | {o.get('train_steps', 500)} | "
                f"{o.get('pixel_sampling', 'uniform')} | x{o.get('train_step_scale', 1.0):g} | "
                f"{row['psnr_test']:.2f} dB | "
                f"{e['found_seeds']}/{len(e['waldo_psnr_per_seed'])} | {per_seed} | {e['waldo_psnr_20db_seeds']} | "
                f"{row['seconds']['train']:.0f} s | {row['seconds']['total']:.0f} s |"
            )
    return "\n".join(lines) + (
        "\n\nThe whole `waldo demo` per room (its room seed and first search seed; 8 seeds, low budget, `waldo_found`, "
        "48 training views at 64 px, Waldo 1.5 x his size with 15 cm stripes, 16 covering views). Training: the "
        "NeRF's training and held-out evaluation; demo time: the whole run. The runs after the first in one "
        "process (one file) reuse its compiled programs, so only each file's first row times a first run. From "
        + ", ".join(f"`benchmarks/results/{n}`" for n in DEMO_ROOMS_RUNS)
        + "."
    )


ROOM_REACHABLE = "room_reachable_cpu.json"


def room_reachable_table() -> str:
    """Per room and method the best visible share reached at the low budget beside the reachable best."""
    data = _json(ROOM_REACHABLE)
    within = {}
    for row in data["rows"]:
        got = within.setdefault(row["method"], [0, 0])
        got[0], got[1] = got[0] + row["within_tolerance"], got[1] + row["seeds"]
    tol = data["settings"]["tolerance"]
    summary = "; ".join(f"{m} {a}/{b} ({a / b:.0%})" for m, (a, b) in within.items())
    above: Dict[str, List[str]] = {}
    for row in data["rows"]:
        if max(row["best_visible"]) > row["reachable"]["best"]:
            above.setdefault(row["method"], []).append(str(row["room"]))
    beyond = "; ".join(f"{m} in room{'s' * (len(r) > 1)} {', '.join(r)}" for m, r in above.items())
    costs = {row["method"]: row["cost"] for row in data["rows"] if "cost" in row}
    refined = [
        f"{m}: {c['gradient_evaluations']} gradient evaluations a seed at {c['renders_per_gradient_evaluation']} "
        f"renders each and {c['children']} children, {c['renders']} renders in all"
        for m, c in costs.items()
        if c["gradient_evaluations"]
    ]
    plain = sorted({c["renders"] for c in costs.values() if not c["gradient_evaluations"]})
    budget = (
        f" Every method within the same budget ({'/'.join(map(str, plain))} renders a seed; {'; '.join(refined)})."
        if refined
        else ""
    )
    return data["table"] + (
        f"\n\nSeeds within {tol:g} of the reachable best over all rooms: {summary}. The reachable best is a dense "
        f"exact search of {data['settings']['samples']} camera centres in the training cameras' box, each aimed at "
        "Waldo: a lower bound of the true best (a method that does not aim exactly at him can do a little better"
        + (f": {beyond}" if beyond else "")
        + "). Rooms as `waldo demo` builds them, criterion `waldo_visible`, "
        f"{data['rows'][0]['seeds']} seeds per method, low budget.{budget} From `benchmarks/results/{ROOM_REACHABLE}`."
    )


BLOCKS: Dict[str, Callable[[], str]] = {
    "readme-paper-table": readme_paper_table,
    "paper-tables-cpu": lambda: _tables("paper_tables_cpu_loaded.json"),
    "saliency-paper-budgets": lambda: _tables(
        "paper_tables_saliency_paper_budget_cpu_fox.json",
        "paper_tables_saliency_paper_budget_cpu_face_loaded.json",
        "paper_tables_saliency_paper_budget_cpu_fern_loaded.json",
        "paper_tables_saliency_paper_budget_cpu_garden.json",
        "paper_tables_saliency_paper_budget_cpu_room_loaded.json",
    ),
    "iqa-composition-fox": iqa_composition_fox_table,
    "cpu64": lambda: _tables("paper_tables_cpu64_saliency.json", "paper_tables_cpu64_iqa_composition.json"),
    "waldo-room": lambda: _tables(
        "paper_tables_room_seed1_paper_budget_cpu.json", "paper_tables_room_seed0_paper_budget_cpu.json"
    ),
    "methods": methods_table,
    "shots": shots_table,
    "paths": paths_table,
    "waldo-found": waldo_found_table,
    "refine-fox": refine_fox_table,
    "refine-fox-high": refine_fox_high_table,
    "demo-closeups": demo_closeups_table,
    "demo-waldo-pixels": demo_waldo_pixels_table,
    "demo-rooms": demo_rooms_table,
    "room-reachable": room_reachable_table,
    "perf-collected": perf_table,
    "packed": packed_table,
    "training": training_table,
    "data-files": data_files_table,
    "data-folders": data_folders_table,
}

PAGES = ["README.md", "docs/results.md", "docs/performance.md", "docs/data.md"]


def regenerate(text: str, cache: Dict[str, str]) -> str:
    def replace(match: re.Match) -> str:
        name = match.group("name")
        if name not in BLOCKS:
            raise SystemExit(f"unknown generated block {name!r}; known: {', '.join(BLOCKS)}")
        if name not in cache:
            cache[name] = BLOCKS[name]().strip() + "\n"
        return match.group(1) + cache[name] + match.group(4)

    return MARKER.sub(replace, text)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="report out-of-date blocks, write nothing")
    args = parser.parse_args(argv)
    if not paper_values.TABLES["saliency"]["values"]:
        raise SystemExit(f"the paper's values are not readable: {paper_values.TABLES['saliency']['note']}")
    cache: Dict[str, str] = {}
    stale = []
    outputs = {ROOT / page: None for page in PAGES}
    for path in outputs:
        old = path.read_text(encoding="utf-8")
        outputs[path] = (old, regenerate(old, cache))
    outputs[ROOT / "docs" / "data.sha256"] = (
        (ROOT / "docs" / "data.sha256").read_text(encoding="utf-8") if (ROOT / "docs" / "data.sha256").exists() else "",
        data_sha256_file(),
    )
    for path, (old, new) in outputs.items():
        if old != new:
            stale.append(path.relative_to(ROOT).as_posix())
            if not args.check:
                path.write_text(new, encoding="utf-8")
    if args.check:
        print("out of date: " + ", ".join(stale) if stale else "all generated blocks are up to date")
        return 1 if stale else 0
    print("rewrote: " + ", ".join(stale) if stale else "nothing to rewrite")
    return 0


if __name__ == "__main__":
    sys.exit(main())

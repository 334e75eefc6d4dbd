"""The issue's targets, read from the steps' results as target / measured / met (`summary.targets` of
device_check.json): rays/s and render efficiency of the trained fox, the fox explore's search seconds,
ms per training step, batched against loop, the test suite, determinism, and the splat renderer's GPU rows.
"""

from __future__ import annotations

from typing import Optional


def targets(steps: dict, platform_name: Optional[str]) -> list:
    """The targets of the issue, each {target, measured, met, unit, note}, from the steps' results; `met`
    is None when not measured, and every note says so when the device is not a GPU."""

    def result(name):
        entry = steps.get(name) or {}
        return entry.get("result") or {}

    rows = []

    def add(target, measured, met, unit="", note=""):
        rows.append({"target": target, "measured": measured, "met": met, "unit": unit, "note": note})

    trained = result("rendering").get("render_trained") or {}
    rays = trained.get("rays_per_s")
    setting = (
        f"{trained.get('timing_poses')} poses at {'x'.join(map(str, trained.get('timing_size') or []))}"
        if trained
        else "not measured"
    )
    add("trained fox >= 5 M rays/s", rays, None if rays is None else rays >= 5e6, "rays/s", setting)
    efficiency = trained.get("render_efficiency")
    add("render efficiency >= 0.3", efficiency, None if efficiency is None else efficiency >= 0.3, "x")
    if not result("search").get("runs"):
        add("fox explore (EGPS, saliency, low budget) <= 10 s of search", None, None, "s", "not measured")
    for run in result("search").get("runs", []):
        search = (run.get("seconds") or {}).get("search")
        size = (
            "x".join(map(str, run["resolution"])) if run.get("resolution") else f"--resolution {run['resolution_arg']}"
        )
        add(
            f"fox explore ({' '.join(result('search').get('args', []))}) at {size} <= 10 s of search",
            search,
            None if search is None else search <= 10.0,
            "s",
        )
    ms = result("training").get("ms_per_step")
    add("quality training <= 10 ms per step", ms, None if ms is None else ms <= 10.0, "ms")
    ratios = result("rendering").get("batched_over_loop") or {"every size": None}
    for size, ratio in ratios.items():
        add(
            f"batched >= loop at {size}" + ("^2" if size.isdigit() else ""),
            ratio,
            None if ratio is None else ratio >= 1.0,
            "x",
        )
    correctness = result("correctness")
    totals = correctness.get("totals")
    if totals:
        bad = totals["failed"] + totals["errors"] + totals["collection_errors"]
        measured = {k: totals[k] for k in ("passed", "failed", "errors", "skipped", "not_run", "collection_errors")}
        complete = correctness.get("suite_complete")
        met = False if bad else (True if complete else None)
        add(
            "every test passes",
            measured,
            met,
            "tests",
            "" if complete else "the suite did not run to its end within the step's time (met: null)",
        )
    else:
        add("every test passes", None, None, "tests", "not measured")
    identical = result("determinism").get("identical")
    add("same-seed reruns byte-identical", identical, identical, "")
    for row in (result("splats").get("render_splats") or {}).get("targets", []):
        if row.get("target", "").startswith("GPU"):
            add(row["target"], row.get("measured"), row.get("met"), row.get("unit", ""), row.get("note", ""))
    for row in rows:
        if row["measured"] is None:
            row["note"] = row["note"] or "not measured"
        if platform_name != "gpu":
            done = "measured" if row["measured"] is not None else "run"
            where = f"{done} on {platform_name or 'an unknown device'}, not a GPU"
            row["note"] = (row["note"] + "; " if row["note"] else "") + where
    return rows

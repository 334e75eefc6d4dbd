"""The gradient step: benchmarks/gradient_cost.py (what one gradient evaluation costs in renders), the fox
run's case included when the training step left one.
"""

from __future__ import annotations

import time

from .common import HERE, Context, command_status, need_fox_run, read_json


def step(ctx: Context, deadline: float) -> dict:
    """gradient_cost.py over the cases; `RUN:` cases read the fox run, left out without it."""
    settings = ctx.settings
    cases, note = [], None
    for case in settings.gradient_cases:
        if case.startswith("RUN:"):
            if ctx.fox_run is None:
                note = f"{case} left out: {need_fox_run(ctx)}"
                continue
            case = f"{ctx.fox_run}:{case[4:]}"
        cases.append(case)
    if not cases:
        return {"status": "skipped", "reason": note, "commands": [], "result": None}
    path = ctx.work / "gradient_cost.json"
    argv = ctx.python(
        HERE / "gradient_cost.py",
        "--cases",
        ",".join(cases),
        "--resolution",
        settings.gradient_resolution,
        "--poses",
        settings.gradient_poses,
        "--repeats",
        settings.gradient_repeats,
        "--load-threshold",
        "1000",
        "--out",
        path,
    )
    command = ctx.run("gradient cost", argv, deadline - time.monotonic())
    return {
        "status": command_status([command]),
        "commands": [command],
        "result": read_json(path),
        **({"note": note} if note else {}),
    }

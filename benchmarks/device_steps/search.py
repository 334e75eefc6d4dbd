"""The search step: `waldo explore` on the training step's fox run (EGPS, saliency, low budget) at each
resolution; the `seconds.search` of its results.json is the measurement.
"""

from __future__ import annotations

from .common import Context, command_status, need_fox_run, read_json, split_box


def step(ctx: Context, deadline: float) -> dict:
    """One explore of the fox run per resolution, each its share of the step's time."""
    reason = need_fox_run(ctx)
    if reason:
        return {"status": "skipped", "reason": reason, "commands": [], "result": None}
    settings = ctx.settings
    resolutions = list(settings.explore_resolutions)
    box = split_box(deadline, [1] * len(resolutions))
    commands, runs = [], []
    for i, resolution in enumerate(resolutions):
        out = ctx.work / f"explore_{resolution}"
        argv = ctx.waldo(
            "explore",
            ctx.fox_run,
            *settings.explore_args,
            "--resolution",
            resolution,
            "--seed",
            "0",
            "--quiet",
            "--out",
            out,
        )
        commands.append(ctx.run(f"search: explore at {resolution}", argv, box(i)))
        r = read_json(out / "results.json")
        runs.append(
            {
                "resolution_arg": resolution,
                "wall_s": commands[-1]["seconds"],
                **(
                    {}
                    if r is None
                    else {
                        k: r.get(k)
                        for k in ("resolution", "seconds", "n_train", "n_generated", "cost", "cvir", "mcvir", "device")
                    }
                ),
            }
        )
    return {
        "status": command_status(commands),
        "commands": commands,
        "result": {"args": list(settings.explore_args), "runs": runs},
    }

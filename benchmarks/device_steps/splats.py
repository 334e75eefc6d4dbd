"""The splats step: benchmarks/render_splats.py at the GPU targets' sizes (100k and 1M splats, 128^2 and
256^2, 256 poses), then `waldo explore` on the packed donut.
"""

from __future__ import annotations

import time

from .common import HERE, Context, command_status, read_json


def step(ctx: Context, deadline: float) -> dict:
    """benchmarks/render_splats.py's synthetic cells (the GPU targets'), then `waldo explore` on the donut."""
    settings = ctx.settings
    path = ctx.work / "render_splats.json"
    argv = ctx.python(HERE / "render_splats.py", *settings.splats_args, "--load-threshold", "1000", "--out", path)
    commands = [ctx.run("render_splats", argv, 0.7 * (deadline - time.monotonic()))]
    donut = ctx.data / "splats" / "donut" / "point_cloud.ply"
    explore = None
    if donut.is_file():
        out = ctx.work / "explore_donut"
        commands.append(
            ctx.run(
                "explore donut",
                ctx.waldo("explore", donut, *settings.splats_explore_args, "--quiet", "--out", out),
                deadline - time.monotonic(),
            )
        )
        r = read_json(out / "results.json")
        explore = (
            None
            if r is None
            else {
                k: r.get(k) for k in ("resolution", "seconds", "cost", "cvir", "mcvir", "renderer", "refine", "device")
            }
        )
    return {
        "status": command_status(commands),
        "commands": commands,
        "result": {
            "render_splats": read_json(path),
            "explore_donut": explore,
            **({} if donut.is_file() else {"note": f"{donut} not packed: the donut explore left out"}),
        },
    }

"""The rendering step: benchmarks/render_trained.py on the training step's fox run (rays/s, evaluations/ray,
passes/view, the field alone, render efficiency), then benchmarks/render_population.py batched vs loop,
one process per size so that a size cut short by the time box leaves the smaller sizes measured.
"""

from __future__ import annotations

from .common import HERE, Context, command_status, need_fox_run, read_json, split_box


def step(ctx: Context, deadline: float) -> dict:
    """render_trained.py on the fox run (when there is one), then render_population.py per size."""
    settings = ctx.settings
    commands, result = [], {}
    sizes = list(settings.population_resolutions)
    # render_trained first (needs the fox run), then one process per population size, so that a size cut
    # short by the time box leaves the smaller sizes measured.
    weights = ([3] if ctx.fox_run is not None else []) + [1] * len(sizes)
    box = split_box(deadline, weights)
    i = 0
    if ctx.fox_run is not None:
        path = ctx.work / "render_trained.json"
        argv = ctx.python(
            HERE / "render_trained.py",
            ctx.fox_run,
            ctx.data / settings.fox,
            "--downscale",
            settings.fox_downscale,
            "--poses",
            settings.render_poses,
            "--size",
            settings.render_size,
            "--repeats",
            settings.render_repeats,
            "--skip",
            "curve",
            "--load-threshold",
            "1000",
            "--out",
            path,
        )
        commands.append(ctx.run("rendering: render_trained", argv, box(i)))
        result["render_trained"] = read_json(path)
        i += 1
    else:
        result["render_trained"] = None
        result["render_trained_skipped"] = need_fox_run(ctx)
    population = []
    for size in sizes:
        path = ctx.work / f"render_population_{size}.json"
        argv = ctx.python(
            HERE / "render_population.py",
            "--poses",
            settings.population_poses,
            "--resolutions",
            size,
            "--samples",
            settings.population_samples,
            "--repeats",
            settings.population_repeats,
            "--load-threshold",
            "1000",
            "--out",
            path,
        )
        commands.append(ctx.run(f"rendering: render_population {size}^2", argv, box(i)))
        i += 1
        population.append(read_json(path))
    result["render_population"] = population
    result["batched_over_loop"] = {
        str(size): (None if p is None else p["speedup_batched_over_loop"][str(size)])
        for size, p in zip(sizes, population)
    }
    return {"status": command_status(commands), "commands": commands, "result": result}

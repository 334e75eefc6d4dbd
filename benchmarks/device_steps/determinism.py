"""The determinism step: the same seed's rendered-criterion `waldo explore` twice, its scores and top poses
compared as JSON text, byte for byte; then once with WALDO_DETERMINISTIC=0 (its search time beside the
default's: what determinism costs).
"""

from __future__ import annotations

import hashlib
import json

from .common import Context, command_status, read_json, split_box


def step(ctx: Context, deadline: float) -> dict:
    """Three explores of the same seed: two as configured, one with WALDO_DETERMINISTIC=0."""
    runs = (
        ("default, first", {}),
        ("default, second", {}),
        ("WALDO_DETERMINISTIC=0", {"WALDO_DETERMINISTIC": "0", "XLA_FLAGS": strip_determinism(ctx.env)}),
    )
    box = split_box(deadline, [1, 1, 1])
    commands, results = [], []
    for i, (label, env) in enumerate(runs):
        out = ctx.work / f"determinism_{i}"
        argv = ctx.waldo(
            "explore", *ctx.settings.determinism_args, "--method", "egps", "--seed", "0", "--quiet", "--out", out
        )
        commands.append(ctx.run(f"determinism: {label}", argv, box(i), env=env))
        results.append(read_json(out / "results.json"))
        if results[-1] is None and i < 2:
            break
    texts = [None if r is None else scores_text(r) for r in results]
    result = {"source_args": list(ctx.settings.determinism_args), "method": "egps", "seed": 0, "runs": []}
    for (label, env), command, r, text in zip(runs, commands, results, texts):
        result["runs"].append(
            {
                "label": label,
                "env": env,
                "wall_s": command["seconds"],
                "seconds": None if r is None else r.get("seconds"),
                "scores_sha256": None if text is None else hashlib.sha256(text.encode()).hexdigest(),
                "n_generated": None if r is None else r.get("n_generated"),
            }
        )
    if len(texts) >= 2 and texts[0] is not None and texts[1] is not None:
        result["identical"] = texts[0] == texts[1]
        result["compared"] = "scores_train, scores_generated and the top-k c2w of results.json, as JSON text"
    else:
        result["identical"] = None
    if len(texts) == 3 and texts[2] is not None and texts[0] is not None:
        result["nondeterministic_run_same_as_default"] = texts[2] == texts[0]
        searches = [r["seconds"]["search"] for r in results]
        result["search_seconds"] = {"default": searches[:2], "WALDO_DETERMINISTIC=0": searches[2]}
    status = command_status(commands)
    if status == "done" and len(commands) < 3:
        status = "failed"
    return {"status": status, "commands": commands, "result": result}


def strip_determinism(env: dict) -> str:
    """XLA_FLAGS of `env` without the flags that make GPU reductions deterministic."""
    flags = env.get("XLA_FLAGS", "").split()
    return " ".join(
        f for f in flags if not f.startswith(("--xla_gpu_deterministic_ops", "--xla_gpu_exclude_nondeterministic_ops"))
    )


def scores_text(results: dict) -> str:
    """What two same-seed runs must agree on, as JSON text: the scores and the top-k poses."""
    return json.dumps(
        [results.get("scores_train"), results.get("scores_generated"), [t.get("c2w") for t in results.get("topk", [])]]
    )

"""`waldo explore`: one experiment (source + criterion + method) from the command line.

    waldo explore SOURCE --criterion NAME --method METHOD --budget low|high --seed N
                  [--seeds K] [--resolution R] --out DIR

METHOD is grs, pibs, egps, map-elites (an archive of the best view per view cell), one of them +
"+refine" (gradient refinement in the last epoch) or evosax:NAME (any evosax strategy). The top-k
written are the best views pairwise at least --min-separation degrees apart (default 20: different
shots; 0: the paper's top-k).

SOURCE is `procedural[:SEED]` or a run directory of `waldo train` / `waldo demo`; see
`waldo_jax.pipeline.outputs` for what is written.
"""

from __future__ import annotations

import argparse
import time
import warnings
from typing import Optional

import numpy as np

from waldo_jax import io
from waldo_jax.cli.conventions import Progress, add_quiet
from waldo_jax.cli.flags import (
    add_criterion_arguments,
    add_splat_pose_arguments,
    criterion_before_source,
    criterion_from_args,
    splat_pose_options,
)
from waldo_jax.cli.shots import add_shot_arguments, shot_separation, view_grid
from waldo_jax.errors import WaldoError, check_float32, check_int
from waldo_jax.pipeline import INITIAL_MODES, load_source, refine_for_source, run_explore, write_outputs
from waldo_jax.pipeline.experiment import epoch_check
from waldo_jax.search import BUDGETS, METHODS, ExploreConfig, RefineConfig, get_method, method_names

__all__ = ["add_command", "cmd_explore", "explore_config_from_args"]

TOP_C = 5  # PIBS's default: the best views it pairs


def add_command(subparsers) -> None:
    """Registers `explore` on an argparse subparsers object (function as `handler`)."""
    p = subparsers.add_parser(
        "explore",
        help="search a scene for the views that best satisfy a criterion (GRS, PIBS, EGPS, MAP-Elites)",
        description="Run one of the paper's searches (Algorithm 1) on SOURCE: start from the scored training "
        "views, add children_per_epoch rendered and scored poses per epoch, report CVIR/mCVIR and "
        "write the top-k different shots, a contact sheet, the archive of views, poses.json, a pose-cloud "
        "plot and results.json.",
    )
    p.add_argument(
        "source",
        metavar="SOURCE",
        help="procedural, procedural:SEED, a RUN_DIR of waldo train, or a splat scene (.ply or 3DGS folder)",
    )
    add_splat_pose_arguments(p)
    add_criterion_arguments(p, default="waldo_oracle")
    p.add_argument("--method", default="egps", help=f"one of {method_names()}")
    p.add_argument(
        "--budget",
        default=None,  # None: "low", and a --budget given beside --children-per-epoch can be told from it
        choices=tuple(BUDGETS),
        help="low (250-300 images in total) or high (900-1000) (default: low; it sets the children per epoch, so "
        "--children-per-epoch overrides it)",
    )
    p.add_argument("--seed", type=int, default=0, help="random seed")
    p.add_argument("--seeds", type=int, default=1, help="run K seeds (seed, seed+1, ...) in one vmapped call")
    p.add_argument(
        "--resolution",
        type=int,
        default=None,
        help="longer image side of the renders (default: procedural 64, runs: the training size, at most 256)",
    )
    p.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    p.add_argument("--epochs", type=int, default=5, help="epochs (default: 5, as the paper)")
    p.add_argument(
        "--children-per-epoch",
        type=int,
        default=None,
        help="poses per epoch (default: derived from the budget and the number of training views)",
    )
    p.add_argument("--top-k", type=int, default=10, help="views returned")
    add_shot_arguments(p)
    p.add_argument("--top-c", type=int, default=TOP_C, help="PIBS: how many best views are paired")
    p.add_argument("--pibs-fallback", default="none", choices=("none", "grs"), help="PIBS once its pairs run out")
    p.add_argument(
        "--initial",
        default="images",
        choices=INITIAL_MODES,
        help="score the initial population on the real training 'images' (as the paper) "
        "or on 'renders' at the training poses",
    )
    p.add_argument(
        "--views", type=int, default=None, help="procedural only: number of training views, at most 1000 (default: 24)"
    )
    defaults = RefineConfig()
    p.add_argument(
        "--refine-poses", type=int, default=defaults.poses, help="+refine: best poses refined in the last epoch"
    )
    p.add_argument(
        "--refine-steps", type=int, default=defaults.steps, help="+refine: gradient evaluations per refined pose"
    )
    p.add_argument(
        "--refine-step-size",
        type=float,
        default=defaults.step_size,
        help="+refine: largest step per coordinate, as a fraction of the scene extent",
    )
    p.add_argument(
        "--gradient-cost",
        type=int,
        default=None,
        help="+refine: renders one gradient evaluation counts as in the budget, >= 2 (default: "
        "measured, 2 for a pose oracle, 12 through a render; README 'Which method when')",
    )
    p.add_argument("--force", action="store_true", help="write into a non-empty output folder")
    add_quiet(p, "per-epoch progress lines nor progress bars")
    p.set_defaults(handler=cmd_explore)


def _warn_unused_method_flags(args: argparse.Namespace, method: str, options) -> None:
    """A warning line for each flag of a method option `method` does not take, given a value other than its
    default (the others' flags keep their defaults unused: `--top-c 8` with egps changed nothing)."""
    refine = RefineConfig()
    flags = {
        "top_c": (("--top-c", args.top_c, TOP_C),),
        "fallback": (("--pibs-fallback", args.pibs_fallback, "none"),),
        "refine": (
            ("--refine-poses", args.refine_poses, refine.poses),
            ("--refine-steps", args.refine_steps, refine.steps),
            ("--refine-step-size", args.refine_step_size, refine.step_size),
            ("--gradient-cost", args.gradient_cost, None),
        ),
    }
    for option, given in flags.items():
        if option in options:
            continue
        owners = ", ".join(name for name, spec in METHODS.items() if option in spec.options)
        for flag, value, default in given:
            if value != default:
                warnings.warn(f"{flag} {value} has no effect with --method {method} (it is for {owners})", stacklevel=3)


def explore_config_from_args(args: argparse.Namespace, method: Optional[str] = None):
    """An `ExploreConfig` from parsed arguments; bad values raise `WaldoError` naming the flag."""
    method = args.method if method is None else method
    try:
        search_method = get_method(method)
    except ValueError:
        raise WaldoError(f"unknown --method {method!r}: expected one of {method_names()}") from None
    budget = "low" if args.budget is None else args.budget
    if budget not in BUDGETS:
        raise WaldoError(f"unknown --budget {budget!r}: expected one of {', '.join(BUDGETS)}")
    for flag, value, minimum in (
        ("--epochs", args.epochs, 1),
        ("--top-k", args.top_k, 1),
        ("--top-c", args.top_c, 2),
        ("--seeds", args.seeds, 1),
        ("--children-per-epoch", args.children_per_epoch, 1),
        ("--refine-poses", args.refine_poses, 1),
        ("--refine-steps", args.refine_steps, 1),
        ("--gradient-cost", args.gradient_cost, 2),
    ):
        if value is not None:
            check_int(value, flag, minimum)  # counts are int32 under jit
    check_float32(args.refine_step_size, "--refine-step-size", positive=True)  # 1e-300: 0 in float32
    if args.budget is not None and args.children_per_epoch is not None:
        warnings.warn(
            f"--budget {args.budget} has no effect: --children-per-epoch {args.children_per_epoch} wins (the "
            "budget only derives the children per epoch)",
            stacklevel=2,
        )
    if args.pibs_fallback not in ("none", "grs"):
        raise WaldoError(f"unknown --pibs-fallback {args.pibs_fallback!r}: expected none or grs")
    try:
        refine = RefineConfig(
            poses=args.refine_poses,
            steps=args.refine_steps,
            step_size=args.refine_step_size,
            **({} if args.gradient_cost is None else {"gradient_cost": args.gradient_cost}),
        )
    except ValueError as e:
        message = str(e)
        for field, flag in (
            ("poses", "--refine-poses"),
            ("steps", "--refine-steps"),
            ("step_size", "--refine-step-size"),
            ("gradient_cost", "--gradient-cost"),
        ):
            message = message.replace(f"RefineConfig.{field}", flag)
        raise WaldoError(message) from None
    # The method's own options from the flags it has (--top-c and --pibs-fallback are PIBS's, the
    # --refine-* flags the +refine methods'); the others' flags keep their defaults unused.
    flags = {"top_c": args.top_c, "fallback": args.pibs_fallback, "refine": refine}
    options = {name: value for name, value in flags.items() if name in search_method.options}
    _warn_unused_method_flags(args, method, search_method.options)
    try:
        return ExploreConfig(
            method=method,
            epochs=args.epochs,
            children_per_epoch=args.children_per_epoch,
            budget=budget,
            top_k=args.top_k,
            min_separation=shot_separation(args),
            grid=view_grid(args),
            options=options,
        )
    except ValueError as e:
        raise WaldoError(str(e)) from None


def _warn_nothing_generated(run, results: dict) -> None:
    """Warns where a search asked for children and generated none: EGPS breeds each child from two views
    with a finite score and PIBS pairs them (both mask every child of an epoch without such a pair), so a run of
    one training view, or of views that all failed, adds nothing and reports a CVIR of 0 as if searched."""
    epochs = results["epochs_count"]
    if results["n_generated"] or not epochs or not results["children_per_epoch"]:
        return
    finite = int(np.sum(np.isfinite(np.asarray(results["scores_train"], dtype=float))))
    warnings.warn(
        f"{run.config.method} generated no views in {epochs} epochs: {finite} of the run's {results['n_train']} "
        "training views scored (a finite score), and EGPS and PIBS make each child from two of them. "
        "Use --method grs (or map-elites), or --pibs-fallback grs with PIBS",
        stacklevel=2,
    )


def cmd_explore(args: argparse.Namespace) -> int:
    """`waldo explore`: runs the search and writes its files into --out."""
    config = explore_config_from_args(args)
    if args.initial not in INITIAL_MODES:
        raise WaldoError(f"unknown --initial {args.initial!r}: expected one of {', '.join(INITIAL_MODES)}")
    io.check_output_dir(args.out, force=args.force)  # refuse early, before any slow work
    start = time.perf_counter()
    method = get_method(config.method)
    criterion = criterion_before_source(args)  # a bad criterion is refused before the source loads
    if method.differentiable and criterion is not None:
        criterion.smooth()  # a criterion gradient steps cannot follow, refused before the source loads too
    with Progress(args.quiet) as progress:  # on a terminal's stderr; the epochs print their own lines
        progress.phase(f"loading {args.source}")
        check = epoch_check(config, args.seeds) if isinstance(args.seeds, int) and args.seeds >= 1 else None
        source = load_source(args.source, args.resolution, args.views, check=check, **splat_pose_options(args))
    if criterion is None:  # a poses criterion: the room's oracles need the source
        criterion = criterion_from_args(args, room=source.room, source=source.spec, train_c2w=source.train_c2w)
    if method.differentiable:
        criterion.smooth()  # refuses a criterion gradient steps cannot follow, before any work
        config = config.with_options(
            refine=refine_for_source(config.refine_config(), source, criterion, args.gradient_cost is None)
        )
    try:
        resolved = config.resolve(source.n_train)
        resolved.method_config(method)
    except ValueError as e:
        raise WaldoError(f"{source.spec}: {e}") from None
    capacity = resolved.capacity(source.n_train)
    if "top_c" in method.options and args.top_c > capacity:  # PIBS takes min(top_c, capacity): said, not silent
        warnings.warn(
            f"--top-c {args.top_c} exceeds the {capacity} views of the run ({source.n_train} training + "
            f"{resolved.epochs} epochs x {resolved.children_per_epoch} children): all {capacity} are paired",
            stacklevel=2,
        )
    # run_explore checks the batched epoch fits in memory before it scores or renders anything.
    setup = time.perf_counter() - start
    run = run_explore(
        source,
        criterion,
        config,
        seed=args.seed,
        seeds=args.seeds,
        initial=args.initial,
        setup_seconds=setup,
        progress=not args.quiet,
    )
    out = io.prepare_output_dir(args.out, force=args.force)  # created only once everything is valid
    with Progress(args.quiet) as progress:
        progress.phase("rendering the top views and writing the results")
        results = write_outputs(run, out)
    best = results["topk"][0]["score"] if results["topk"] else None
    _warn_nothing_generated(run, results)

    def percent(value, spread=None):  # None where no score was usable (every view failed a guard, or NaN)
        if value is None:
            return "n/a"
        return f"{value:.1f} %" if spread is None else f"{value:.1f} +/- {spread:.1f} %"

    spread = (
        f" (mean over {args.seeds} seeds: CVIR {percent(results['cvir_mean'], results['cvir_std'])}, "
        f"mCVIR {percent(results['mcvir_mean'], results['mcvir_std'])})"
        if args.seeds > 1
        else ""
    )
    print(
        f"{run.config.method.upper()} on {source.name} with {criterion.name}: {results['n_train']} training + "
        f"{results['n_generated']} generated views; best {'n/a' if best is None else format(best, '.4g')}; "
        f"CVIR {percent(results['cvir'])}, mCVIR {percent(results['mcvir'])}{spread}; "
        f"{run.seconds['total']:.1f} s; wrote {out}"
    )
    return 0

"""The pipeline: a scene to explore (`sources`), an experiment = source + criterion + method
(`experiment`), its files (`outputs`, `figures`), camera paths (`path_run`) and the end-to-end demo
on the procedural room (`demo`).

    from waldo_jax import io
    from waldo_jax.criteria import CriterionContext, make_criterion
    from waldo_jax.pipeline import load_source, run_explore, write_outputs
    from waldo_jax.search import ExploreConfig

    source = load_source("procedural:0")
    run = run_explore(source, make_criterion("waldo_oracle", CriterionContext(room=source.room)),
                      ExploreConfig(method="egps", budget="low"), seed=0, seeds=4)
    write_outputs(run, io.prepare_output_dir("runs/egps"))
"""

from waldo_jax.pipeline.experiment import GRADIENT_COSTS as GRADIENT_COSTS
from waldo_jax.pipeline.experiment import INITIAL_MODES as INITIAL_MODES
from waldo_jax.pipeline.experiment import ExploreRun as ExploreRun
from waldo_jax.pipeline.experiment import generated_slots as generated_slots
from waldo_jax.pipeline.experiment import gradient_cost_for as gradient_cost_for
from waldo_jax.pipeline.experiment import initial_scores as initial_scores
from waldo_jax.pipeline.experiment import objective_function as objective_function
from waldo_jax.pipeline.experiment import refine_for_source as refine_for_source
from waldo_jax.pipeline.experiment import run_explore as run_explore
from waldo_jax.pipeline.experiment import score_function as score_function
from waldo_jax.pipeline.experiment import seed_keys as seed_keys
from waldo_jax.pipeline.figures import PlotFrame as PlotFrame
from waldo_jax.pipeline.figures import PoseCloudStyle as PoseCloudStyle
from waldo_jax.pipeline.figures import contact_sheet as contact_sheet
from waldo_jax.pipeline.figures import criterion_caption as criterion_caption
from waldo_jax.pipeline.figures import criterion_label as criterion_label
from waldo_jax.pipeline.figures import methods_sheet as methods_sheet
from waldo_jax.pipeline.figures import plot_frame as plot_frame
from waldo_jax.pipeline.figures import pose_cloud as pose_cloud
from waldo_jax.pipeline.figures import scene_up as scene_up
from waldo_jax.pipeline.outputs import RESULTS_JSON as RESULTS_JSON
from waldo_jax.pipeline.outputs import results_dict as results_dict
from waldo_jax.pipeline.outputs import write_outputs as write_outputs
from waldo_jax.pipeline.sources import Source as Source
from waldo_jax.pipeline.sources import SourceError as SourceError
from waldo_jax.pipeline.load import load_source as load_source
from waldo_jax.pipeline.sources import procedural_source as procedural_source
from waldo_jax.pipeline.sources import run_source as run_source
from waldo_jax.pipeline.sources import with_gradient as with_gradient

__all__ = [
    "GRADIENT_COSTS",
    "INITIAL_MODES",
    "RESULTS_JSON",
    "ExploreRun",
    "PlotFrame",
    "PoseCloudStyle",
    "Source",
    "SourceError",
    "contact_sheet",
    "criterion_caption",
    "criterion_label",
    "generated_slots",
    "gradient_cost_for",
    "initial_scores",
    "objective_function",
    "refine_for_source",
    "load_source",
    "methods_sheet",
    "plot_frame",
    "pose_cloud",
    "procedural_source",
    "results_dict",
    "run_explore",
    "run_source",
    "scene_up",
    "score_function",
    "seed_keys",
    "with_gradient",
    "write_outputs",
]

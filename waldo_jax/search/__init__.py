"""Scene-space search of "Finding Waldo" (MMSys'24), Algorithm 1: GRS, PIBS and EGPS, and beyond the
paper: MAP-Elites (`map_elites`, over the view archive of `archive`), different shots (`views`: the
distance between two views and the k best views pairwise apart), gradient refinement (`refine`:
`refine`, `refine_poses` and the `+refine` methods) and any evosax strategy (`strategy`: "evosax:NAME").

One module per method (`grs`, `pibs`, `egps`), each with a numeric `Params` pytree, a static `Config`
(its own options: `ExploreConfig(options=...)`) and a pure `ask(key, population, params, config, epoch)`
(evosax's `init` / `ask` / `tell` for a method with a state: `method`); the population buffer in `population`;
CVIR / mCVIR in `metrics`; the registry of methods by name in `registry` (`get_method`); the compiled exploration loop
in `explore`.

    from waldo_jax.search import ExploreConfig, Initial, explore
    result = explore(jax.random.key(0), score_fn, Initial(c2w=train_c2w, scores=train_scores), "egps",
                     ExploreConfig(budget="low"))
"""

from waldo_jax.search import egps as egps
from waldo_jax.search import grs as grs
from waldo_jax.search import map_elites as map_elites
from waldo_jax.search import pibs as pibs
from waldo_jax.search.archive import Archive as Archive
from waldo_jax.search.archive import ViewGrid as ViewGrid
from waldo_jax.search.archive import archive_of as archive_of
from waldo_jax.search.explore import BUDGETS as BUDGETS
from waldo_jax.search.explore import ExploreConfig as ExploreConfig
from waldo_jax.search.explore import Initial as Initial
from waldo_jax.search.explore import Result as Result
from waldo_jax.search.explore import SeedsResult as SeedsResult
from waldo_jax.search.explore import budget_children as budget_children
from waldo_jax.search.explore import explore as explore
from waldo_jax.search.explore import explore_loop as explore_loop
from waldo_jax.search.explore import explore_seeds as explore_seeds
from waldo_jax.search.explore import result_bytes as result_bytes
from waldo_jax.search.explore import search_memory as search_memory
from waldo_jax.search.metrics import EpochMetrics as EpochMetrics
from waldo_jax.search.metrics import cvir as cvir
from waldo_jax.search.metrics import epoch_metrics as epoch_metrics
from waldo_jax.search.metrics import mcvir as mcvir
from waldo_jax.search.metrics import mean_top_n as mean_top_n
from waldo_jax.search.method import SearchMethod as SearchMethod
from waldo_jax.search.population import Population as Population
from waldo_jax.search.population import init_population as init_population
from waldo_jax.search.population import top_k_indices as top_k_indices
from waldo_jax.search.population import training_look_at as training_look_at
from waldo_jax.search.population import training_poses as training_poses
from waldo_jax.search.population import write_children as write_children
from waldo_jax.search.refine import RefineConfig as RefineConfig
from waldo_jax.search.refine import RefineResult as RefineResult
from waldo_jax.search.refine import SceneBox as SceneBox
from waldo_jax.search.refine import refine as refine
from waldo_jax.search.refine import refine_poses as refine_poses
from waldo_jax.search.refine import scene_box as scene_box
from waldo_jax.search.registry import METHODS as METHODS
from waldo_jax.search.registry import get_method as get_method
from waldo_jax.search.registry import method_names as method_names
from waldo_jax.search.views import DEFAULT_MIN_SEPARATION as DEFAULT_MIN_SEPARATION
from waldo_jax.search.views import SceneFrame as SceneFrame
from waldo_jax.search.views import distinct_count as distinct_count
from waldo_jax.search.views import distinct_top_k as distinct_top_k
from waldo_jax.search.views import scene_frame as scene_frame
from waldo_jax.search.views import view_separation as view_separation
from waldo_jax.search.path import PathLimits as PathLimits
from waldo_jax.search.path import path_c2w as path_c2w
from waldo_jax.search.path import path_motion as path_motion
from waldo_jax.search.path import sample_path as sample_path
from waldo_jax.search.path import straight_path as straight_path
from waldo_jax.search.path_search import PATH_BUDGETS as PATH_BUDGETS
from waldo_jax.search.path_search import PathConfig as PathConfig
from waldo_jax.search.path_search import PathResult as PathResult
from waldo_jax.search.path_search import path_limits as path_limits
from waldo_jax.search.path_search import search_path as search_path
from waldo_jax.search.path_search import search_path_loop as search_path_loop
from waldo_jax.search.path_search import search_path_seeds as search_path_seeds

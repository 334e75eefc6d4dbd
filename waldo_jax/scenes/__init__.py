"""Loading posed image sets from disk: instant-ngp, nerfstudio, Blender and LLFF scenes.

`load_scene(path)` detects the format, reads images and cameras, and returns a host-side `Scene`
(see `waldo_jax.types`): images float32 [N, H, W, 3] in [0, 1], c2w float32 [N, 4, 4] (OpenGL),
intrinsics at the loaded size, aabb float32 [2, 3], near/far. One module per format (`transforms`
for instant-ngp / nerfstudio / Blender, `llff`), beside `common` (detection, checks, splits),
`images`, `ply` and `poses_file` (cameras without images). The conventions and their reasons are in
docs/design.md, "Scenes".
"""

from waldo_jax.cameras import camera_focus as camera_focus
from waldo_jax.scenes.common import BLENDER_SPLITS as BLENDER_SPLITS
from waldo_jax.scenes.common import FORMATS as FORMATS
from waldo_jax.scenes.common import MAX_COORDINATE as MAX_COORDINATE
from waldo_jax.scenes.common import MIN_NEAR_FRACTION as MIN_NEAR_FRACTION
from waldo_jax.scenes.common import RIGID_TOL as RIGID_TOL
from waldo_jax.scenes.common import SPLITS as SPLITS
from waldo_jax.scenes.common import TEST_EVERY as TEST_EVERY
from waldo_jax.scenes.common import SceneArgumentError as SceneArgumentError
from waldo_jax.scenes.common import camera_bounds as camera_bounds
from waldo_jax.scenes.common import detect_format as detect_format
from waldo_jax.scenes.images import IMAGE_EXTENSIONS as IMAGE_EXTENSIONS
from waldo_jax.scenes.llff import LLFF_DEFAULT_FACTOR as LLFF_DEFAULT_FACTOR
from waldo_jax.scenes.llff import LLFF_FAR_MARGIN as LLFF_FAR_MARGIN
from waldo_jax.scenes.llff import LLFF_NEAR_MARGIN as LLFF_NEAR_MARGIN
from waldo_jax.scenes.loader import load_scene as load_scene
from waldo_jax.scenes.ply import read_ply_points as read_ply_points
from waldo_jax.scenes.poses_file import PosesFile as PosesFile
from waldo_jax.scenes.poses_file import load_poses_file as load_poses_file
from waldo_jax.scenes.poses_file import read_poses_file as read_poses_file
from waldo_jax.scenes.splits import load_splits as load_splits
from waldo_jax.scenes.transforms import BLENDER_AABB as BLENDER_AABB
from waldo_jax.scenes.transforms import BLENDER_FAR as BLENDER_FAR
from waldo_jax.scenes.transforms import BLENDER_NEAR as BLENDER_NEAR
from waldo_jax.scenes.transforms import NGP_DEFAULT_OFFSET as NGP_DEFAULT_OFFSET
from waldo_jax.scenes.transforms import NGP_DEFAULT_SCALE as NGP_DEFAULT_SCALE
from waldo_jax.scenes.transforms import ORIGIN_PAD as ORIGIN_PAD
from waldo_jax.scenes.transforms import PLY_PAD as PLY_PAD
from waldo_jax.scenes.transforms import PLY_PERCENTILES as PLY_PERCENTILES

__all__ = [
    "FORMATS",
    "PosesFile",
    "SPLITS",
    "SceneArgumentError",
    "camera_bounds",
    "camera_focus",
    "detect_format",
    "load_poses_file",
    "load_scene",
    "load_splits",
    "read_ply_points",
    "read_poses_file",
]

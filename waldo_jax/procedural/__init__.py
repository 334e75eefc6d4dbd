"""The procedural "Waldo room": an analytic radiance field with a known answer.

A seeded room (a checkered floor, four walls, coloured boxes, spheres and cylinders) hides one small
striped Waldo figure in a pen of crates. Densities come from signed distance functions, so nothing is
trained and `waldo_jax.render` renders it like any other field:
  * `make_room(seed) -> WaldoRoom`, the geometry and the field's params; `room_field(room, x, d)`;
  * `training_cameras(key, room, ...)`: views that see Waldo at most partly; `room_scene(seed, ...)`:
    those views rendered as a `waldo_jax.types.Scene` (its metadata rebuild the room:
    `room_from_metadata`);
  * `waldo_visibility`, `waldo_coverage(room, c2w, intrinsics)`, both at once `waldo_view`: exact
    oracles from the geometry; `FOUND_VISIBILITY` (0.9), the share of Waldo a view must show to find him.
Modules, bottom to top: `room` (geometry and field), `visibility` (the oracles), `cameras`, `scene`.
Units are metres, +y is up, the floor is y = 0. The cameras, the oracle and the density model: see
docs/design.md, section "Procedural room".
"""

from waldo_jax.procedural.cameras import RoomCameraConfig as RoomCameraConfig
from waldo_jax.procedural.cameras import training_cameras as training_cameras
from waldo_jax.procedural.visibility import FOUND_VISIBILITY as FOUND_VISIBILITY
from waldo_jax.procedural.visibility import waldo_coverage as waldo_coverage
from waldo_jax.procedural.visibility import waldo_visibility as waldo_visibility
from waldo_jax.procedural.visibility import waldo_view as waldo_view
from waldo_jax.procedural.visibility import waldo_surface_seen as waldo_surface_seen
from waldo_jax.procedural.visibility import waldo_visibility_batch as waldo_visibility_batch
from waldo_jax.procedural.room import DENSITY as DENSITY
from waldo_jax.procedural.room import WaldoRoom as WaldoRoom
from waldo_jax.procedural.room import make_room as make_room
from waldo_jax.procedural.room import room_field as room_field
from waldo_jax.procedural.room import room_sdf as room_sdf
from waldo_jax.procedural.scene import held_out_scene as held_out_scene
from waldo_jax.procedural.scene import waldo_mask as waldo_mask
from waldo_jax.procedural.scene import waldo_reference as waldo_reference
from waldo_jax.procedural.scene import room_render_config as room_render_config
from waldo_jax.procedural.scene import room_scene as room_scene
from waldo_jax.procedural.scene import room_from_metadata as room_from_metadata

__all__ = [
    "DENSITY",
    "FOUND_VISIBILITY",
    "RoomCameraConfig",
    "WaldoRoom",
    "held_out_scene",
    "waldo_mask",
    "waldo_reference",
    "make_room",
    "room_field",
    "room_from_metadata",
    "room_render_config",
    "room_scene",
    "room_sdf",
    "training_cameras",
    "waldo_coverage",
    "waldo_view",
    "waldo_visibility",
    "waldo_visibility_batch",
    "waldo_surface_seen",
]

"""Population rendering sharded over devices equals the single-device result.

Runs in a subprocess with 4 forced CPU devices (XLA_FLAGS must be set before JAX starts).
"""

import os
import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent(
    """
    import os
    import numpy as np
    import waldo_jax  # noqa: F401
    import jax, jax.numpy as jnp
    from waldo_jax.cameras import look_at
    from waldo_jax.procedural import make_room, room_field, room_render_config
    from waldo_jax.render import pose_mesh, render_views, render_views_sharded
    from waldo_jax.types import Intrinsics

    assert jax.device_count() == 4, jax.devices()
    room = make_room(0)
    origins = jax.random.uniform(jax.random.key(0), (7, 3), minval=-2.0, maxval=2.0) + jnp.array([0.0, 1.5, 0.0])
    c2w = jax.vmap(look_at, in_axes=(0, None, None))(origins, jnp.zeros(3), jnp.array([0.0, 1.0, 0.0]))
    intr = Intrinsics.from_fov(12, 12, 1.0)
    cfg = room_render_config(room, num_samples=24)
    for key in (None, jax.random.key(3)):
        single = render_views(room_field, room, c2w, intr, cfg, key)
        sharded = render_views_sharded(room_field, room, c2w, intr, cfg, key, mesh=pose_mesh())
        for name in ("rgb", "depth", "acc"):
            np.testing.assert_array_equal(np.asarray(getattr(single, name)), np.asarray(getattr(sharded, name)))
    # The work really is split: a population that divides the mesh stays sharded over 4 devices.
    out = render_views_sharded(room_field, room, c2w[:4], intr, cfg)
    assert len(out.rgb.sharding.device_set) == 4
    print("OK")
    """
)


def test_sharded_population_equals_single_device():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4")
    result = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith("OK")

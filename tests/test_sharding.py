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


TRAINED_SCRIPT = textwrap.dedent(
    """
    import numpy as np
    import waldo_jax  # noqa: F401
    import jax, jax.numpy as jnp
    from waldo_jax.cameras import look_at
    from waldo_jax.nerf import HashGridConfig, NGPFieldConfig
    from waldo_jax.nerf.config import TrainConfig
    from waldo_jax.nerf.trained import TrainedField, render_trained, render_trained_counted
    from waldo_jax.nerf.samplers import make_sampler
    from waldo_jax.nerf.step import init_train_state
    from waldo_jax.render import pose_mesh
    from waldo_jax.types import Intrinsics

    assert jax.device_count() == 4, jax.devices()
    aabb = np.array([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]], np.float32)
    field = NGPFieldConfig(aabb=aabb, hashgrid=HashGridConfig(L=4, T=2**12, F=2, N_min=8, N_max=64),
                           density_hidden=(16,), color_hidden=(16,))
    origins = jax.random.uniform(jax.random.key(0), (7, 3), minval=-1.0, maxval=1.0) * 3.0 + 4.0
    c2w = jax.vmap(look_at, in_axes=(0, None, None))(origins, jnp.zeros(3), jnp.array([0.0, 1.0, 0.0]))
    intr = Intrinsics.from_fov(10, 8, 0.8)
    for sampler in ("occupancy", "dense"):
        config = TrainConfig(field=field, steps=1, chunk=1, rays_per_batch=64, num_samples=16,
                             samples_per_batch=1024, eval_samples=16, occupancy_resolution=16,
                             steps_per_diagonal=64.0, sampler=sampler)
        state = init_train_state(jax.random.key(1), config)
        # a grid with structure: one density update from the random field (warm-up samples every cell)
        grid = make_sampler(config).update(jax.random.key(2), state.sampler_state, state.params, True)
        args = (TrainedField.create(state.params, grid, config, 1.0, 12.0), c2w, intr)
        sharded = render_trained(*args, mesh=pose_mesh())  # over the 4 local devices
        one = render_trained_counted(*args).output  # the single-device renderer
        assert len(sharded.rgb.sharding.device_set) == 4, sampler
        # With no mesh, a CPU's host devices are left alone (on accelerators it splits by default).
        default = render_trained(*args)
        assert len(default.rgb.sharding.device_set) == 1, sampler
        np.testing.assert_array_equal(np.asarray(default.rgb), np.asarray(one.rgb))
        # Each device packs only its own poses' rays into passes: the per-pass sums of a ray may be
        # split differently, so the images agree to float32 rounding.
        for name in ("rgb", "depth", "acc"):
            np.testing.assert_allclose(np.asarray(getattr(one, name)), np.asarray(getattr(sharded, name)),
                                       atol=2e-6 if name != "depth" else 2e-5)
        assert float(jnp.std(one.rgb)) > 0  # not a blank image
        explicit = render_trained(*args, mesh=pose_mesh(jax.devices()[:2]))
        np.testing.assert_allclose(np.asarray(explicit.rgb), np.asarray(one.rgb), atol=2e-6)
    print("OK")
    """
)


def test_trained_renderer_sharded_equals_single_device():
    """`render_trained` (occupancy marching and dense) splits the poses over 4 devices, the same images;
    with no mesh on a CPU it renders on one device."""
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4")
    result = subprocess.run(
        [sys.executable, "-c", TRAINED_SCRIPT], env=env, capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith("OK")


SPLAT_SCRIPT = textwrap.dedent(
    """
    import dataclasses
    import numpy as np
    import waldo_jax  # noqa: F401
    import jax, jax.numpy as jnp
    from waldo_jax.cameras import look_at
    from waldo_jax.pipeline.splat_sources import splat_renderer
    from waldo_jax.splats.model import make_splats
    from waldo_jax.splats.render import SplatRenderConfig, render_splats, render_splats_on_devices
    from waldo_jax.types import Intrinsics

    assert jax.device_count() == 3, jax.devices()
    rng = np.random.default_rng(0)
    n = 300
    splats = make_splats(
        means=rng.uniform(-1, 1, (n, 3)), log_scales=np.log(rng.uniform(0.03, 0.15, (n, 3))),
        quats=rng.normal(size=(n, 4)), logits=rng.normal(size=n), sh=rng.uniform(-1, 1, (n, 3)),
    )
    origins = rng.uniform(-1, 1, (7, 3)).astype(np.float32) + np.array([0.0, 0.0, 4.0], np.float32)
    c2w = jax.vmap(look_at, in_axes=(0, None, None))(jnp.asarray(origins), jnp.zeros(3), jnp.array([0.0, 1.0, 0.0]))
    intr = Intrinsics.from_fov(24, 16, 0.9)
    config = SplatRenderConfig(max_pairs=4096)
    one = jax.jit(render_splats, static_argnames="config")(splats, c2w, intr, config=config)
    split = render_splats_on_devices(splats, c2w, intr, config)
    assert len(split.rgb.sharding.device_set) == 3  # 7 poses padded to 9: three a device
    for name in ("rgb", "depth", "acc"):
        np.testing.assert_array_equal(np.asarray(getattr(one, name)), np.asarray(getattr(split, name)))
    # The search's renderer (a Partial called inside its jitted program) splits the same way.
    search_like = jax.jit(lambda r, c: r(c, intr))
    renderer = splat_renderer(splats, config)
    compiled = search_like.lower(renderer, c2w).compile()
    assert len(jax.tree.leaves(compiled.output_shardings)[0].device_set) == 3  # the program spans them
    views = search_like(renderer, c2w)
    np.testing.assert_array_equal(np.asarray(views.rgba[..., :3]), np.asarray(one.rgb))
    np.testing.assert_array_equal(np.asarray(views.rgba[..., 3]), np.asarray(one.acc))
    print("OK")
    """
)


def test_splat_renderer_split_over_devices_equals_one_device():
    """With several devices the splat renderer (alone and inside a search's jit) splits the poses over
    them and gives the single-device images bit for bit (WALDO_CPU_DEVICES=3, a subprocess)."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["WALDO_CPU_DEVICES"] = "3"
    result = subprocess.run([sys.executable, "-c", SPLAT_SCRIPT], env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith("OK")


MEMORY_SCRIPT = textwrap.dedent(
    """
    import waldo_jax  # noqa: F401
    import jax, jax.numpy as jnp
    from waldo_jax.render.sharding import shard_over_poses
    from waldo_jax.search.explore import program_memory

    assert jax.device_count() == 2, jax.devices()

    def local(scale, posed):
        return jnp.tile(posed[0][..., None], (1, 1, 1, 50000)) * scale

    c2w = jnp.ones((8, 3, 4))
    split = jax.jit(lambda s, c: shard_over_poses(local, s, c).sum()).lower(2.0, c2w).compile()
    whole = jax.jit(lambda s, c: local(s, (c, None)).sum()).lower(2.0, c2w).compile()
    per_device = split.memory_analysis().temp_size_in_bytes
    assert per_device < 0.6 * whole.memory_analysis().temp_size_in_bytes  # XLA's figure: one device's
    assert abs(program_memory(split) - program_memory(whole)) < 0.05 * program_memory(whole)
    print("OK")
    """
)


def test_the_memory_of_a_program_split_over_host_devices_counts_every_device():
    """`program_memory` (the search's memory check) of a program split over 2 CPU devices is the whole
    host's, about the unsplit program's; XLA's own figure is half of it."""
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
    env["WALDO_CPU_DEVICES"] = "2"
    result = subprocess.run([sys.executable, "-c", MEMORY_SCRIPT], env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert result.stdout.strip().endswith("OK")

"""Rendering across several processes (hosts) equals the single-process render (issue 35, item 6).

Two Python processes on this machine play two hosts: each calls `jax.distributed.initialize` with the
coordinator at localhost:PORT (`num_processes=2`, its `process_id`), has 2 forced CPU devices, and the
CPU collectives are gloo's (jaxlib's default). Both render the same 8 poses of the procedural room at
16x16 with `render_views_sharded` on `global_pose_mesh()` (4 devices over 2 processes), each process
rendering its own 4 poses, and gather the images with `gather_to_hosts`; this process renders the same
poses with `render_views` on one device, and every image must be equal bit for bit. It is the recipe of
docs/library.md, "Several devices and several hosts".
"""

import os
import socket
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.cameras import look_at
from waldo_jax.procedural import make_room, room_field, room_render_config
from waldo_jax.render import render_views
from waldo_jax.types import Intrinsics

PROCESSES = 2
DEVICES_PER_PROCESS = 2
POSES = 8
TIMEOUT_S = 120

WORKER = textwrap.dedent(
    """
    import sys

    port, process_id, folder = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    import waldo_jax  # noqa: F401  (its XLA flags before JAX starts a backend)
    import jax

    jax.distributed.initialize(coordinator_address=f"localhost:{port}", num_processes=2, process_id=process_id,
                               initialization_timeout=90)
    import numpy as np
    from waldo_jax.procedural import make_room, room_field, room_render_config
    from waldo_jax.render import gather_to_hosts, global_pose_mesh, render_views_sharded
    from waldo_jax.types import Intrinsics

    assert jax.process_count() == 2 and jax.device_count() == 4 and jax.local_device_count() == 2, jax.devices()
    room = make_room(0)
    c2w = np.load(f"{folder}/c2w.npy")  # the same poses on every process (SPMD)
    out = render_views_sharded(room_field, room, c2w, Intrinsics.from_fov(16, 16, 1.0),
                               room_render_config(room, num_samples=16), mesh=global_pose_mesh())
    assert not out.rgb.is_fully_addressable  # a global array: each process holds only its devices' poses
    mine = sorted(i for shard in out.rgb.addressable_shards for i in range(*shard.index[0].indices(len(c2w))))
    whole = gather_to_hosts(out)
    np.savez(f"{folder}/process{process_id}.npz", rgb=whole.rgb, depth=whole.depth, acc=whole.acc, mine=mine)
    print("OK", process_id)
    """
)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _poses() -> np.ndarray:
    origins = jax.random.uniform(jax.random.key(0), (POSES, 3), minval=-2.0, maxval=2.0) + jnp.array([0.0, 1.5, 0.0])
    return np.asarray(jax.vmap(look_at, in_axes=(0, None, None))(origins, jnp.zeros(3), jnp.array([0.0, 1.0, 0.0])))


def _run_processes(folder, port):
    """Starts the two processes, waits for both (at most TIMEOUT_S), returns [(returncode, output)]."""
    flags = os.environ.get("XLA_FLAGS", "") + f" --xla_force_host_platform_device_count={DEVICES_PER_PROCESS}"
    env = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu")
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", WORKER, str(port), str(i), str(folder)],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in range(PROCESSES)
    ]
    try:
        outputs = [p.communicate(timeout=TIMEOUT_S)[0] for p in procs]
        return [(p.returncode, output) for p, output in zip(procs, outputs)]
    except subprocess.TimeoutExpired:
        pytest.fail(f"the {PROCESSES} processes did not finish in {TIMEOUT_S} s")
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.communicate()


def test_two_processes_render_what_one_does(tmp_path):
    if "jax_cpu_collectives_implementation" not in jax.config.values:
        pytest.skip(f"jax {jax.__version__} has no CPU collectives across processes")
    c2w = _poses()
    np.save(tmp_path / "c2w.npy", c2w)
    results = _run_processes(tmp_path, _free_port())
    failed = [f"process {i} (exit {code}):\n{output[-2000:]}" for i, (code, output) in enumerate(results) if code]
    if failed and all("implemented on the CPU backend" in out for _, out in results):
        pytest.skip("this jaxlib has no CPU collectives across processes")
    assert not failed, "\n".join(failed)

    room = make_room(0)
    single = render_views(
        room_field, room, jnp.asarray(c2w), Intrinsics.from_fov(16, 16, 1.0), room_render_config(room, num_samples=16)
    )
    mine = []
    for i in range(PROCESSES):
        gathered = np.load(tmp_path / f"process{i}.npz")
        for name in ("rgb", "depth", "acc"):  # every process holds every pose's image, equal to one process's
            np.testing.assert_array_equal(gathered[name], np.asarray(getattr(single, name)), err_msg=f"{i} {name}")
        mine.append(list(gathered["mine"]))
    assert mine == [[0, 1, 2, 3], [4, 5, 6, 7]]  # the work was split: each process rendered its half
    assert float(np.asarray(single.acc).max()) > 0.5  # the views show the room, not an empty frame

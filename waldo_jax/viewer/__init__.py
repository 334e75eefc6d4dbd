"""See a scene and a search in 3D: `waldo view` and `waldo_jax.view` (a top layer beside `cli` and `pipeline`).

    import waldo_jax
    viewer = waldo_jax.view("runs/donut_explore")   # in a notebook: shows it inline; viewer.url in a browser
    viewer.stop()

`load` reads PATH (an output of `waldo explore`, `waldo path` or `waldo demo`, or a SOURCE) into a `ViewScene`
(`scene`, `demo`, `nerf_points`) without a browser library; `server` draws it with viser (imported only there; the
`view` extra installs it); `live` renders and scores the browser's camera, `paths` exports the path shown.
"""

from __future__ import annotations

from waldo_jax.viewer.scene import Frustum as Frustum
from waldo_jax.viewer.scene import SplatCloud as SplatCloud
from waldo_jax.viewer.scene import ViewerError as ViewerError
from waldo_jax.viewer.scene import ViewScene as ViewScene
from waldo_jax.viewer.load import load_view_scene as load_view_scene

__all__ = ["Frustum", "SplatCloud", "ViewScene", "ViewerError", "load_view_scene", "view"]


def view(path: str, port: int = 0, host: str = "127.0.0.1", height: int = 600):
    """Serves PATH (an explore output folder or a SOURCE) in the browser and returns the `Viewer`.

    In IPython (a notebook) it also displays an IFrame of the viewer's page. `port` 0 takes a free one;
    `viewer.url` is the address, `viewer.stop()` ends it.

    Args:
      path: an output folder of `waldo explore`, `waldo path` or `waldo demo`, a splat scene, a NeRF run or
        `procedural[:SEED]`.
      port: the port to serve on (0: any free one).
      host: the address to listen on (127.0.0.1: this machine only).
      height: the IFrame's height in pixels.

    Returns:
      A `waldo_jax.viewer.server.Viewer` (its `server` is the `viser.ViserServer`).
    """
    from waldo_jax.viewer.server import serve

    viewer = serve(load_view_scene(path), host=host, port=port)
    try:
        from IPython import get_ipython

        if get_ipython() is not None:
            from IPython.display import IFrame, display

            display(IFrame(viewer.url, width="100%", height=height))
    except ImportError:
        pass
    return viewer

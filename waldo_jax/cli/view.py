"""`waldo view PATH [--port N] [--host H] [--export FILE.html]`: a scene and a search in 3D, in the browser.

PATH is an output folder of `waldo explore`, `waldo path` or `waldo demo`, or a SOURCE (a splat scene,
`procedural[:SEED]`, a NeRF run); see `waldo_jax.viewer`. Without --export it serves the viewer (viser) until
Ctrl-C (or --seconds) and prints its URL; with --export it writes a self-contained HTML snapshot instead and
serves nothing.
"""

from __future__ import annotations

import argparse
import os
import stat
import time
import warnings
from pathlib import Path

from waldo_jax.cli.conventions import Progress, add_quiet
from waldo_jax.errors import WaldoError

__all__ = ["add_command", "cmd_view"]


def add_command(subparsers) -> None:
    """Registers `view` on an argparse subparsers object (function as `handler`)."""
    p = subparsers.add_parser(
        "view",
        help="see a scene and a search in 3D in the browser (viser): splats, cameras, views by score",
        description="Serve an interactive 3D viewer of PATH: the scene (Gaussian splats; the procedural room or a "
        "NeRF's density as points), the training cameras and the search's views as frustums coloured by score, the "
        "top-k highlighted with their images (a demo: each method's in its colour); click a camera to fly there "
        "and see its rank and score; render and score the current view; play a camera path; export the path "
        "shown for nerfstudio / Instant-NGP. Needs viser (the `view` extra).",
    )
    p.add_argument(
        "path",
        metavar="PATH",
        help="an output folder of waldo explore, path or demo, or a SOURCE (splats, procedural, a NeRF run)",
    )
    p.add_argument("--port", type=int, default=8080, help="port to serve on (the next free one if taken; 0: any)")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (0.0.0.0: every interface)")
    p.add_argument("--export", metavar="FILE.html", default=None, help="write a self-contained HTML snapshot")
    p.add_argument("--force", action="store_true", help="with --export: overwrite an existing FILE.html")
    p.add_argument("--seconds", type=float, default=None, help="stop serving after this long (default: Ctrl-C)")
    add_quiet(p, "progress (the loading phase)")
    p.set_defaults(handler=cmd_view)


# A year: "serve until then" past it is "serve until Ctrl-C" (leave --seconds out).
MAX_SECONDS = 365 * 24 * 3600.0


def check_host(host: str) -> None:
    """Refuses a --host this machine cannot listen on (not an address, or none of its own) by binding a socket
    there (any port) and closing it: viser, given one, tried port after port for ever. A taken --port is
    left to viser, which moves to the next free one."""
    import socket

    try:
        infos = socket.getaddrinfo(host, 0, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (socket.gaierror, UnicodeError, OSError) as e:
        raise WaldoError(f"--host {host}: not an address this machine can resolve ({e})") from None
    problem = None
    for family, kind, proto, _, address in infos:
        with socket.socket(family, kind, proto) as probe:
            probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                probe.bind(address)
                return
            except OSError as e:
                problem = e
    raise WaldoError(
        f"--host {host}: cannot listen there ({problem.strerror or problem}): not an address of this machine"
    )


def _check(args: argparse.Namespace) -> None:
    """Refuses bad flags before anything is loaded, served or written."""
    if not 0 <= args.port <= 65535:
        raise WaldoError(f"--port {args.port}: expected 0 .. 65535")
    if args.seconds is not None and not 0 < args.seconds <= MAX_SECONDS:  # inf and 1e400 served for ever
        raise WaldoError(f"--seconds {args.seconds}: expected a positive number of seconds, at most {MAX_SECONDS:g}")
    if args.export is not None and args.seconds is not None:
        raise WaldoError("--seconds bounds the serving; --export writes a file and serves nothing: give one")
    if args.export is None:
        check_host(args.host)
        if args.force:
            warnings.warn("--force has no effect without --export (it overwrites an existing FILE.html)", stacklevel=2)
    if args.export is not None:
        target = Path(args.export)
        if target.suffix.lower() not in (".html", ".htm"):
            raise WaldoError(f"--export {args.export}: expected a file name ending in .html")
        if not target.parent.is_dir():
            raise WaldoError(f"--export {args.export}: no such folder {target.parent}")
        if not os.access(target.parent, os.W_OK | os.X_OK):  # found before loading, not after building the page
            raise WaldoError(f"--export {args.export}: cannot write into {target.parent} (permission denied)")
        # lexists: a dangling link is something there too (the page was written through it, wherever it
        # pointed); a folder, a FIFO (opening it for writing waited for a reader for ever) or a device is
        # never replaced, --force or not.
        if os.path.lexists(target):
            try:
                mode = os.stat(target).st_mode
            except OSError:  # a dangling link or a link loop
                mode = None
            if mode is not None and not stat.S_ISREG(mode):
                kind = "a folder" if stat.S_ISDIR(mode) else "a FIFO, socket or device"
                raise WaldoError(f"--export {args.export}: {kind}, not a file to write the page to")
            if not args.force:
                raise WaldoError(f"--export {args.export}: exists (--force overwrites it)")


def cmd_view(args: argparse.Namespace) -> int:
    """`waldo view`: serves PATH until interrupted, or writes the --export snapshot."""
    from waldo_jax.viewer import load_view_scene
    from waldo_jax.viewer.server import export_html, import_viser, serve

    _check(args)
    import_viser()  # a missing viser is one line before the scene loads
    with Progress(args.quiet) as progress:
        progress.phase(f"loading {args.path}")
        scene = load_view_scene(args.path)
    for note in scene.notes:
        print(f"waldo: note: {note}")
    if args.export is not None:
        size, seconds = export_html(scene, Path(args.export))
        print(f"wrote {args.export} ({size / 1e6:.1f} MB, {len(scene.frustums)} cameras) in {seconds:.1f} s")
        return 0
    start = time.perf_counter()
    viewer = serve(scene, host=args.host, port=args.port)
    print(
        f"waldo view: {viewer.url} ({len(scene.frustums)} cameras, ready in {time.perf_counter() - start:.1f} s); "
        "Ctrl-C stops it",
        flush=True,
    )
    try:
        deadline = None if args.seconds is None else time.monotonic() + args.seconds
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.2)
    finally:
        viewer.stop()
    return 0

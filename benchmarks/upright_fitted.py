"""How well `waldo_jax.splats.upright` finds the up of splat scenes whose true up is known, and of
tilted copies of them (issue 43, part 3).

For each MODEL=UP given (a splat scene `load_splat_model` reads and its true up in the scene's own
coordinates), the scene is turned by a fixed set of rotations (the identity, then 30 to 180 degrees
about fixed axes); each copy's up is estimated as `waldo explore` does (`splat_upright`: the support
plane, the format's axis, the flattest direction; the true up turned along with the splats is the
answer) and the angle between them reported, with the rule that decided and the layout chosen. The
format prior (3DGS PLYs are y-down) only holds for the untilted copy; tilted ones show what the scene
alone gives.

  python benchmarks/upright_fitted.py runs/lego_splats=0,0,1 ../shared/splats/donut=0,0,1 \\
      --out benchmarks/results/upright_fitted_cpu.json
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import waldo_jax  # noqa: E402,F401  (XLA flags before the first computation)
from bench_common import emit, header, refuse_existing_out  # noqa: E402
from waldo_jax.pipeline.splat_sources import splat_upright  # noqa: E402
from waldo_jax.splats.io import load_splat_model  # noqa: E402
from waldo_jax.splats.upright import parse_up  # noqa: E402

# (angle in degrees, axis): the copies of each scene.
TILTS = [
    (0.0, (1.0, 0.0, 0.0)),
    (30.0, (1.0, 0.0, 0.0)),
    (45.0, (0.0, 0.0, 1.0)),
    (60.0, (1.0, 1.0, 0.0)),
    (90.0, (0.0, 1.0, 0.0)),
    (90.0, (1.0, 0.0, 0.0)),
    (120.0, (1.0, -1.0, 1.0)),
    (180.0, (1.0, 0.0, 0.0)),
]


def rotation(angle_deg: float, axis) -> np.ndarray:
    """The 3x3 rotation by `angle_deg` about `axis` (Rodrigues)."""
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    t = math.radians(angle_deg)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * k @ k


def quat_of(r: np.ndarray) -> np.ndarray:
    """The unit quaternion (w, x, y, z) of a rotation matrix."""
    w = math.sqrt(max(1.0 + r[0, 0] + r[1, 1] + r[2, 2], 1e-12)) / 2
    if w > 1e-3:
        x, y, z = r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]
        return np.array([w, x / (4 * w), y / (4 * w), z / (4 * w)])
    i = int(np.argmax(np.diag(r)))
    j, k = (i + 1) % 3, (i + 2) % 3
    s = math.sqrt(max(1.0 + r[i, i] - r[j, j] - r[k, k], 1e-12)) * 2
    q = np.zeros(4)
    q[0] = (r[k, j] - r[j, k]) / s
    q[1 + i] = s / 4
    q[1 + j] = (r[j, i] + r[i, j]) / s
    q[1 + k] = (r[k, i] + r[i, k]) / s
    return q


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton products a * b of (w, x, y, z) quaternions, broadcast over b's rows."""
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        -1,
    )


def tilted(model, r: np.ndarray):
    """`model` with its splats turned by `r` about the origin (means, orientations; scales and colours kept:
    the SH beyond degree 0 are not turned, which the up estimate does not read)."""
    s = model.splats
    means = np.asarray(s.means, np.float64) @ r.T
    quats = quat_mul(quat_of(r), np.asarray(s.quats, np.float64))
    splats = s.replace(means=np.asarray(means, np.float32), quats=np.asarray(quats, np.float32))
    return dataclasses.replace(model, splats=splats, cameras=None, bounds=None)  # the bounds move with the splats


def angle_deg(a, b) -> float:
    c = float(np.dot(a, b) / (np.linalg.norm(a) * np.linalg.norm(b)))
    return math.degrees(math.acos(min(1.0, max(-1.0, c))))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+", help="MODEL=X,Y,Z: a splat scene and its true up")
    parser.add_argument("--tolerance", type=float, default=10.0, help="degrees counted as right (default 10)")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    refuse_existing_out(args.out)
    result = header("upright_fitted")
    result["settings"] = {"models": args.models, "tilts": TILTS, "tolerance_deg": args.tolerance}
    rows = []
    for item in args.models:
        path, _, up_text = item.rpartition("=")
        true_up = parse_up(up_text)
        model = load_splat_model(path)
        for angle, axis in TILTS:
            r = rotation(angle, axis)
            start = time.perf_counter()
            found = splat_upright(tilted(model, r))
            want = r @ true_up
            rows.append(
                {
                    "model": path,
                    "splats": int(np.asarray(model.splats.valid).sum()),
                    "tilt_deg": angle,
                    "axis": list(axis),
                    "true_up": [round(float(v), 6) for v in want],
                    "found_up": [round(float(v), 6) for v in found.up],
                    "error_deg": round(angle_deg(found.up, want), 2),
                    "rule": found.rule,
                    "layout": found.layout,
                    "reason": found.reason,
                    "seconds": round(time.perf_counter() - start, 2),
                }
            )
            print(
                f"{path} tilt {angle:g} about {axis}: error {rows[-1]['error_deg']} deg ({found.rule}, {found.layout})",
                file=sys.stderr,
                flush=True,
            )
    result["rows"] = rows
    right = [r for r in rows if r["error_deg"] <= args.tolerance]
    result["within_tolerance"] = f"{len(right)}/{len(rows)}"
    emit(result, args.out)


if __name__ == "__main__":
    main()

"""A brute-force float64 NumPy reference of the splat renderer's semantics, for tests.

Every pixel composites every splat, sorted by camera depth (stable), with no tiles and no
capacities: the projection, the EWA covariance with the clamped Jacobian and the 0.3 px^2 low-pass,
the SH colour, alpha = min(0.99, o exp(power)) skipped below 1/255 (and where power > 0), front to back,
stopping at the splat that would take the transmittance below 1e-4. Written from the description
of the reference 3DGS rasteriser, independently of `waldo_jax.splats.render` (no code shared).
"""

from __future__ import annotations

import numpy as np

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = [1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396]
SH_C3 = [
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
]


def sh_colour(sh: np.ndarray, d: np.ndarray) -> np.ndarray:
    """sh [K, 3], unit d [3] -> rgb [3] (one splat, the reference's basis written out term by term)."""
    x, y, z = d
    k = sh.shape[0]
    c = SH_C0 * sh[0]
    if k > 1:
        c = c - SH_C1 * y * sh[1] + SH_C1 * z * sh[2] - SH_C1 * x * sh[3]
    if k > 4:
        c = (
            c
            + SH_C2[0] * x * y * sh[4]
            + SH_C2[1] * y * z * sh[5]
            + SH_C2[2] * (2 * z * z - x * x - y * y) * sh[6]
            + SH_C2[3] * x * z * sh[7]
            + SH_C2[4] * (x * x - y * y) * sh[8]
        )
    if k > 9:
        c = (
            c
            + SH_C3[0] * y * (3 * x * x - y * y) * sh[9]
            + SH_C3[1] * x * y * z * sh[10]
            + SH_C3[2] * y * (4 * z * z - x * x - y * y) * sh[11]
            + SH_C3[3] * z * (2 * z * z - 3 * x * x - 3 * y * y) * sh[12]
            + SH_C3[4] * x * (4 * z * z - x * x - y * y) * sh[13]
            + SH_C3[5] * z * (x * x - y * y) * sh[14]
            + SH_C3[6] * x * (x * x - 3 * y * y) * sh[15]
        )
    return np.maximum(c + 0.5, 0.0)


def rotation(q: np.ndarray) -> np.ndarray:
    """Unit-normalised quaternion (w, x, y, z) -> 3x3 rotation."""
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def render_reference(
    means,
    log_scales,
    quats,
    logits,
    sh,
    c2w,
    width,
    height,
    fx,
    fy,
    cx,
    cy,
    *,
    near=0.01,
    background=(0.0, 0.0, 0.0),
    low_pass=0.3,
    clamp=1.3,
    return_depth=False,
):
    """The image [H, W, 3] and accumulated opacity [H, W] of splats (raw parameters, float64) seen from
    the OpenGL camera-to-world `c2w` [4, 4] through a pinhole; with `return_depth`, also the
    alpha-weighted camera depth [H, W] (the same weights as the colour, 0 where empty)."""
    means, log_scales, quats = (np.asarray(a, np.float64) for a in (means, log_scales, quats))
    logits, sh, c2w = (np.asarray(a, np.float64) for a in (logits, sh, c2w))
    # OpenGL c2w -> world-to-camera in OpenCV axes (x right, y down, z forward).
    w2c = np.diag([1.0, -1.0, -1.0]) @ c2w[:3, :3].T
    centre = c2w[:3, 3]
    splats = []
    for i in range(means.shape[0]):
        p = w2c @ (means[i] - centre)
        if p[2] <= near:
            continue
        opacity = 1.0 / (1.0 + np.exp(-logits[i]))
        r = rotation(quats[i])
        s = np.diag(np.exp(log_scales[i]))
        cov3 = r @ s @ s.T @ r.T
        limx, limy = clamp * width / (2 * fx), clamp * height / (2 * fy)
        tx = p[2] * np.clip(p[0] / p[2], -limx, limx)
        ty = p[2] * np.clip(p[1] / p[2], -limy, limy)
        jac = np.array([[fx / p[2], 0.0, -fx * tx / p[2] ** 2], [0.0, fy / p[2], -fy * ty / p[2] ** 2]])
        cov2 = jac @ w2c @ cov3 @ w2c.T @ jac.T + low_pass * np.eye(2)
        if np.linalg.det(cov2) <= 0:
            continue
        d = (means[i] - centre) / np.linalg.norm(means[i] - centre)
        uv = np.array([fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy])
        splats.append((p[2], i, uv, np.linalg.inv(cov2), opacity, sh_colour(sh[i], d)))
    splats.sort(key=lambda s: (s[0], s[1]))
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    image = np.zeros((height, width, 3))
    depth = np.zeros((height, width))
    transmittance = np.ones((height, width))
    done = np.zeros((height, width), bool)
    for z, _, uv, inv, opacity, colour in splats:
        dx, dy = xs - uv[0], ys - uv[1]
        power = -0.5 * (inv[0, 0] * dx * dx + inv[1, 1] * dy * dy) - inv[0, 1] * dx * dy
        alpha = np.minimum(0.99, opacity * np.exp(np.minimum(power, 0.0)))
        use = (power <= 0) & (alpha >= 1.0 / 255.0) & ~done
        after = transmittance * (1 - alpha)
        stop = use & (after < 1e-4)
        done |= stop
        use &= ~stop
        image += np.where(use[..., None], (alpha * transmittance)[..., None] * colour, 0.0)
        depth += np.where(use, alpha * transmittance * z, 0.0)
        transmittance = np.where(use, after, transmittance)
    image = image + transmittance[..., None] * np.asarray(background, np.float64)
    return (image, 1.0 - transmittance, depth) if return_depth else (image, 1.0 - transmittance)

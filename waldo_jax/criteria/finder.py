"""The Waldo finder: template matching of a reference image of the object over positions and scales.

A view's score is the best, over all windows and scales, of max(NCC, 0) * BC: the normalised
cross-correlation of the window with the target resampled to that scale (Lewis 1995: FFT correlation,
integral images) times the Bhattacharyya coefficient of their colour histograms (Comaniciu, Ramesh
and Meer 2003), in [0, 1] (1 for an exact copy of the target, 0.1 to 0.3 for views without Waldo).
Both factors are exact per window; the histogram keeps NCC from matching any similar light-dark
layout (on the procedural room the product agrees best with the oracle). `find_target` and
`finder_score(s)` score views, `ncc_map` / `colour_map` give the maps, `waldo(context)` the criterion.

The symbols, how each factor is computed, the measured agreement with the oracle, the scales and the
resampling: see docs/design.md, section "Criteria > The Waldo finder".
"""

from __future__ import annotations

import functools
from typing import NamedTuple, Sequence, Tuple

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.criteria.base import (
    Criterion,
    CriterionContext,
    CriterionError,
    CriterionSpec,
    finite_or_worst,
    register,
    sanitize_images,
    worst_score,
)
from waldo_jax.types import Array

__all__ = [
    "BINS",
    "DEFAULT_SCALES",
    "MIN_SIDE",
    "MIN_STD",
    "VALUE_RANGE",
    "FinderParams",
    "Match",
    "make_finder_params",
    "template_sizes",
    "resample_target",
    "ncc_map",
    "colour_map",
    "find_target",
    "finder_score",
    "finder_scores",
    "waldo",
]

DEFAULT_SCALES: Tuple[float, ...] = tuple(float(2.0 ** (k / 4.0 - 3.0)) for k in range(13))  # 1/8 ... 1
MIN_SIDE = 4  # pixels: a template smaller than this in a side has too few pixels to mean anything
MIN_STD = 0.02  # windows (and templates) with a smaller standard deviation are flat: NCC 0
BINS = 4  # histogram levels per channel (64 joint colour bins)
VALUE_RANGE = (0.0, 1.0)
# Views per step of `finder_scores`: a 256x256 view needs about 70 MB (its integral image of colour
# counts and a scale's window histograms are [H, W, 64]), so a chunk of 8 bounds a batch's memory
# to about half a GB (peak 1.2 GB for 64 views at 256x256, measured).
CHUNK = 8
SCALES_PER_GROUP = 4  # template sizes per compiled program (see `find_target`)


@flax.struct.dataclass
class FinderParams:
    """The finder's params: the target image (traced) and its static settings.

    Attributes:
      target: float32 [h, w, 3] in [0, 1], the reference image of the object.
      scales: template heights as fractions of the view's height (static).
      min_std: the flatness threshold `MIN_STD` (static).
    """

    target: Array
    scales: Tuple[float, ...] = flax.struct.field(pytree_node=False, default=DEFAULT_SCALES)
    min_std: float = flax.struct.field(pytree_node=False, default=MIN_STD)


class Match(NamedTuple):
    """The best match of the target in one view (all [] arrays).

    Attributes:
      score: `max(NCC, 0) * BC` of the best window, in [0, 1] (0 when no scale fits the view).
      ncc: its NCC, in [-1, 1].
      colour: its Bhattacharyya coefficient, in [0, 1].
      scale: int32 index into `template_sizes(target.shape, image.shape, scales)`.
      row, col: int32 top-left corner of the window.
    """

    score: Array
    ncc: Array
    colour: Array
    scale: Array
    row: Array
    col: Array


def make_finder_params(target, scales: Sequence[float] = DEFAULT_SCALES, min_std: float = MIN_STD) -> FinderParams:
    """Checks and wraps a target image.

    Args:
      target: [h, w, 3] (or [h, w, 4], whose alpha is dropped), float in [0, 1] or uint8.
      scales: template heights relative to the view's height, each in (0, 1].
      min_std: flatness threshold.

    Raises:
      CriterionError: a target of another shape, with non-finite values, or bad scales.
    """
    target = np.asarray(target)
    if target.dtype == np.uint8:
        target = target.astype(np.float32) / 255.0
    if target.ndim != 3 or target.shape[-1] not in (3, 4) or min(target.shape[:2]) < 2:
        raise CriterionError(f"the target image must be [h, w, 3] with h, w >= 2, got shape {target.shape}")
    target = target[..., :3].astype(np.float32)
    if not np.all(np.isfinite(target)):
        raise CriterionError("the target image has NaN or infinite values")
    scales = tuple(float(s) for s in scales)
    if not scales or not all(0.0 < s <= 1.0 for s in scales):
        raise CriterionError(f"finder scales must be in (0, 1], got {scales}")
    return FinderParams(target=jnp.asarray(np.clip(target, 0.0, 1.0)), scales=scales, min_std=float(min_std))


def template_sizes(
    target_shape: Tuple[int, ...], image_shape: Tuple[int, ...], scales: Sequence[float] = DEFAULT_SCALES
) -> Tuple[Tuple[int, int], ...]:
    """The (height, width) of the template at each usable scale (static, plain Python).

    Scale s gives height round(s * H) and width round(height * w / h); sizes with a side below
    `MIN_SIDE` or beyond the view are dropped, as are repeats; the rest are sorted, smallest first.
    """
    h, w = target_shape[:2]
    height, width = image_shape[:2]
    sizes = []
    for s in scales:
        th = int(round(s * height))
        tw = int(round(th * w / h))
        if MIN_SIDE <= th <= height and MIN_SIDE <= tw <= width and (th, tw) not in sizes:
            sizes.append((th, tw))
    return tuple(sorted(sizes))


def _resample(target: Array, h: Array, w: Array, buffer: Tuple[int, int]) -> Tuple[Array, Array]:
    """The target [th, tw, 3] resampled to h x w (traced) in a zero buffer [*buffer, 3], and its mask [*buffer].

    Bilinear interpolation at the output pixel centres, source coordinates clamped to the image
    (what `jax.image.resize(..., "linear", antialias=False)` computes, for a size known only at run time).
    """
    th, tw = target.shape[:2]

    def taps(out_size, in_size, length):
        pos = (jnp.arange(length) + 0.5) * (in_size / out_size) - 0.5
        pos = jnp.clip(pos, 0.0, in_size - 1.0)
        low = jnp.floor(pos).astype(jnp.int32)
        return low, jnp.minimum(low + 1, in_size - 1), pos - low

    y0, y1, fy = taps(h, th, buffer[0])
    x0, x1, fx = taps(w, tw, buffer[1])
    rows = target[y0] * (1.0 - fy)[:, None, None] + target[y1] * fy[:, None, None]  # [buffer_h, tw, 3]
    out = rows[:, x0] * (1.0 - fx)[None, :, None] + rows[:, x1] * fx[None, :, None]
    mask = (jnp.arange(buffer[0]) < h)[:, None] & (jnp.arange(buffer[1]) < w)[None, :]
    return jnp.where(mask[..., None], out, 0.0), mask


def resample_target(target: Array, size: Tuple[int, int]) -> Array:
    """The target [h, w, 3] resampled to `size` as the finder does (bilinear at pixel centres, no low-pass filter)."""
    return _resample_compiled(jnp.asarray(target, jnp.float32), tuple(int(v) for v in size))


@functools.partial(jax.jit, static_argnames="size")
def _resample_compiled(target: Array, size: Tuple[int, int]) -> Array:
    return _resample(target, jnp.int32(size[0]), jnp.int32(size[1]), size)[0]


def _groups(sizes: Sequence[Tuple[int, int]]) -> Tuple[Tuple[Tuple[int, int], ...], ...]:
    """Consecutive runs of at most `SCALES_PER_GROUP` sizes (static)."""
    return tuple(tuple(sizes[i : i + SCALES_PER_GROUP]) for i in range(0, len(sizes), SCALES_PER_GROUP))


def _cumsum(x: Array, axis: int) -> Array:
    """Running sums along an axis as a parallel prefix sum (3 to 6 times faster than `jnp.cumsum` on XLA CPU)."""
    return jax.lax.associative_scan(jnp.add, x, axis=axis)


def _column_sums(x: Array) -> Array:
    """Running sums down the rows of x [H, W, C], with a zero first row: [H + 1, W, C]."""
    return _cumsum(jnp.pad(x, ((1, 0), (0, 0), (0, 0))), axis=0)


def _window_sums(column_sums: Array, h: Array, w: Array, shape: Tuple[int, int]) -> Array:
    """Sums over the h x w window (h, w traced) at the corners (y, x) < `shape`: [*shape, C].

    Integral-image differences from `_column_sums`, one axis at a time (rows, then columns), so the
    running sums stay as small as a strip of the image (float32 precision). Corners past H - h or
    W - w read clamped rows and columns: garbage, masked by the caller.
    """
    height, width = column_sums.shape[0] - 1, column_sums.shape[1]
    rows = jnp.take(column_sums, jnp.minimum(jnp.arange(shape[0]) + h, height), axis=0) - column_sums[: shape[0]]
    across = _cumsum(jnp.pad(rows, ((0, 0), (1, 0), (0, 0))), axis=1)  # [shape[0], W + 1, C]
    return jnp.take(across, jnp.minimum(jnp.arange(shape[1]) + w, width), axis=1) - across[:, : shape[1]]


def _bins(x: Array) -> Array:
    """One-hot joint colour bin [..., BINS**3] of pixels x [..., 3] in [0, 1]."""
    q = jnp.clip(jnp.floor(x * BINS), 0, BINS - 1).astype(jnp.int32)
    return jax.nn.one_hot((q[..., 0] * BINS + q[..., 1]) * BINS + q[..., 2], BINS**3, dtype=jnp.float32)


class _View(NamedTuple):
    """What every scale of one view needs, computed once."""

    spectrum: Array  # [H, W // 2 + 1, 3], rfft2 of the view minus its mean value (NCC does not change)
    moments: Array  # [H + 1, W, 2], column sums of sum_c centred and sum_c centred^2
    counts: Array  # int32 [H + 1 + pad, W + 1 + pad, BINS**3], integral image of the one-hot colour bins


def _view(image: Array, pad: Tuple[int, int]) -> _View:
    """Prepares a view float32 [H, W, 3]; `pad` zero rows and columns extend the integral image of counts."""
    image = jnp.asarray(image, jnp.float32)
    centred = image - jnp.mean(image)  # keeps the float32 sums small
    moments = jnp.stack([jnp.sum(centred, -1), jnp.sum(centred * centred, -1)], -1)
    counts = _cumsum(_cumsum(_bins(image).astype(jnp.int32), axis=0), axis=1)  # exact integers
    # A zero first row and column; the zeros past the end let every corner of a map read a full
    # window (those past H - h or W - w are masked out).
    counts = jnp.pad(counts, ((1, pad[0]), (1, pad[1]), (0, 0)))
    return _View(jnp.fft.rfft2(centred, axes=(0, 1)), _column_sums(moments), counts)


def _maps(
    view: _View, template: Array, mask: Array, h: Array, w: Array, shape: Tuple[int, int], min_std: float
) -> Tuple[Array, Array, Array]:
    """NCC and BC maps [*shape] of one template over a prepared view, and the mask of valid corners.

    Args:
      view: the prepared view (`_view`).
      template: [bh, bw, 3], the template in the top-left h x w of a zero buffer; `mask` [bh, bw] marks it.
      h, w: the template's size (traced int32).
      shape: the corners (y, x) computed, static; those with y > H - h or x > W - w are invalid.
      min_std: flatness threshold.

    Returns:
      (ncc, colour, valid), each [*shape]; ncc and colour are 0 at invalid corners.
    """
    height, width = view.moments.shape[0] - 1, view.moments.shape[1]
    area = (h * w).astype(jnp.float32)
    n = 3.0 * area
    valid = (jnp.arange(shape[0]) <= height - h)[:, None] & (jnp.arange(shape[1]) <= width - w)[None, :]

    t = jnp.where(mask[..., None], template - jnp.sum(template) / n, 0.0)  # zero mean over the n values
    t_norm2 = jnp.sum(t * t)
    t_spectrum = jnp.fft.rfft2(t, s=(height, width), axes=(0, 1))
    correlation = jnp.fft.irfft2(jnp.sum(view.spectrum * jnp.conj(t_spectrum), axis=-1), s=(height, width))
    numerator = correlation[: shape[0], : shape[1]]
    sums = _window_sums(view.moments, h, w, shape)  # [*shape, 2]
    deviation = jnp.maximum(sums[..., 1] - sums[..., 0] ** 2 / n, 0.0)  # sum of squared deviations
    floor = n * min_std * min_std
    ok = valid & (deviation > floor) & (t_norm2 > floor)
    denominator = jnp.sqrt(jnp.where(ok, deviation * t_norm2, 1.0))
    ncc = jnp.where(ok, jnp.clip(numerator / denominator, -1.0, 1.0), 0.0)

    p_template = jnp.sum(jnp.where(mask[..., None], _bins(template), 0.0), axis=(0, 1)) / area  # [BINS**3]
    size = (*shape, view.counts.shape[-1])
    zero = jnp.zeros_like(h)
    corner = functools.partial(jax.lax.dynamic_slice, view.counts, slice_sizes=size)
    counts = (
        corner((h, w, zero)) - corner((zero, w, zero)) - corner((h, zero, zero)) + view.counts[: shape[0], : shape[1]]
    )  # [*shape, BINS**3]
    # BC = sum_b sqrt(count_b / area * p_b), one fused reduction over the bins; counts are exact.
    colour = jnp.sum(jnp.sqrt(counts.astype(jnp.float32)) * jnp.sqrt(p_template / area), axis=-1)
    return ncc, jnp.where(valid, jnp.clip(colour, 0.0, 1.0), 0.0), valid


def _static_maps(image: Array, template: Array, min_std: float = MIN_STD) -> Tuple[Array, Array]:
    image, template = jnp.asarray(image, jnp.float32), jnp.asarray(template, jnp.float32)
    h, w = template.shape[:2]
    shape = (image.shape[0] - h + 1, image.shape[1] - w + 1)
    ncc, colour, _ = _maps(
        _view(image, (0, 0)), template, jnp.ones((h, w), bool), jnp.int32(h), jnp.int32(w), shape, min_std
    )
    return ncc, colour


def ncc_map(image: Array, template: Array, min_std: float = MIN_STD) -> Array:
    """Exact zero-mean, unit-norm cross-correlation of a template over every valid window.

    Args:
      image: float32 [H, W, 3].
      template: float32 [h, w, 3], h <= H and w <= W.
      min_std: windows (or a template) whose standard deviation over their 3 h w values is below
        this get 0.

    Returns:
      NCC float32 [H - h + 1, W - w + 1] in [-1, 1]; entry (y, x) compares image[y:y+h, x:x+w].
    """
    return _static_maps(image, template, min_std)[0]


def colour_map(image: Array, template: Array) -> Array:
    """Bhattacharyya coefficient [H - h + 1, W - w + 1] of each window's colour histogram and the template's."""
    return _static_maps(image, template)[1]


def find_target(params: FinderParams, image: Array) -> Match:
    """The best match of the target in one view.

    The template sizes are split into groups of `SCALES_PER_GROUP` consecutive sizes; a group's
    scales run one after the other (`lax.map`) through one program whose maps cover the valid
    corners of the group's smallest template, with the template's size a run-time value inside
    fixed-size buffers. So a view size compiles a few programs whatever the number of scales, and
    large templates do not pay for the corners where they do not fit.

    Args:
      params: `FinderParams`.
      image: float32 [H, W, 3] in [0, 1] (H, W static: they fix the template sizes).

    Returns:
      `Match`; a view too small for every scale gets score 0, NCC -1 and colour 0.
    """
    height, width = image.shape[:2]
    sizes = template_sizes(params.target.shape, image.shape, params.scales)
    if not sizes:
        zero = jnp.int32(0)
        return Match(jnp.float32(0.0), jnp.float32(-1.0), jnp.float32(0.0), zero, zero, zero)
    groups = _groups(sizes)
    pad = (max(g[-1][0] - g[0][0] for g in groups), max(max(w for _, w in g) - min(w for _, w in g) for g in groups))
    view = _view(image, pad)
    best = []
    for group in groups:  # static
        shape = (height - group[0][0] + 1, width - min(w for _, w in group) + 1)
        buffer = (group[-1][0], max(w for _, w in group))

        def one_scale(size, shape=shape, buffer=buffer):
            template, mask = _resample(params.target, size[0], size[1], buffer)
            ncc, colour, valid = _maps(view, template, mask, size[0], size[1], shape, params.min_std)
            match = jnp.where(valid, jnp.maximum(ncc, 0.0) * colour, -1.0)
            index = jnp.argmax(match)
            row, col = jnp.divmod(index, shape[1])
            return match.reshape(-1)[index], ncc.reshape(-1)[index], colour.reshape(-1)[index], row, col

        best.append(jax.lax.map(one_scale, jnp.asarray(group, jnp.int32)))
    score, ncc, colour, row, col = (jnp.concatenate(v) for v in zip(*best))
    k = jnp.argmax(score)
    return Match(score[k], ncc[k], colour[k], k.astype(jnp.int32), row[k].astype(jnp.int32), col[k].astype(jnp.int32))


def finder_score(params: FinderParams, image: Array) -> Array:
    """The finder score [] in [0, 1] of one view float32 [H, W, 3]: the best `max(NCC, 0) * BC`."""
    return find_target(params, image).score


def finder_scores(params: FinderParams, images: Array) -> Array:
    """`finder_score` of views [P, H, W, 3], vmapped over chunks of `CHUNK` views; returns [P]."""
    return jax.lax.map(functools.partial(finder_score, params), images, batch_size=CHUNK)


def _apply(params: FinderParams, images: Array) -> Array:
    clean, bad = sanitize_images(images)
    return finite_or_worst(finder_scores(params, clean), bad, worst_score("max", VALUE_RANGE))


def waldo(context: CriterionContext, scales: Sequence[float] = DEFAULT_SCALES) -> Criterion:
    """The `waldo` criterion: the best match of `context.target` over positions and scales (max, in [0, 1]).

    Raises:
      CriterionError: no target image in the context (pass `--target FILE`), or a malformed one.
    """
    if context.target is None:
        raise CriterionError(
            "criterion 'waldo' needs a reference image of the object to find: "
            "pass --target FILE (an image of the object, cropped)"
        )
    return Criterion(
        params=make_finder_params(context.target, scales),
        name="waldo",
        direction="max",
        value_range=VALUE_RANGE,
        inputs="images",
        apply=_apply,
        description=_DESCRIPTION,
        smooth_apply=_apply,
    )


_DESCRIPTION = "best normalised cross-correlation x colour-histogram similarity of the --target image"
register(CriterionSpec("waldo", "max", "images", _DESCRIPTION, waldo, smooth=True, reads=("target",)))

"""Every image criterion of the registry: deterministic, one compilation per batch shape, batches of 1,
8 and 64 without batch coupling, finite on black / white images, the worst score (never NaN) for NaN
images, usable by `waldo explore`; and the CNN quality criterion ranks a real view above its blurs
(NIQE and BRISQUE: tests/test_niqe_brisque.py)."""

from __future__ import annotations

import numpy as np
import pytest

import waldo_jax  # noqa: F401
import jax
import jax.numpy as jnp

from waldo_jax.criteria import CRITERIA, CriterionContext, make_criterion
from waldo_jax.criteria.base import worst_score

from conftest import require_scene, require_weights

IMAGE_CRITERIA = sorted(name for name, spec in CRITERIA.items() if spec.inputs != "poses")
NEEDS_WEIGHTS = {
    "saliency": "csnet/csnet-L-x1.pth.tar",
    "composition": "csnet/csnet-L-x1.pth.tar",
    "iqa_cnn": "cnniqa/CNNIQA-LIVE",
    "niqe": "niqe/niqe_image_params.mat",
    "brisque": "brisque/brisque_model_live.yml",
}
SIZE = 112  # NIQE needs whole 96x96 patches; the networks resize inside


def _target():
    """A small reference image for the `waldo` finder: a red-and-blue striped patch."""
    target = np.zeros((16, 12, 3), np.float32)
    target[::4, :, 0] = 1.0
    target[2::4, :, 2] = 1.0
    return target


def _build(name):
    if name in NEEDS_WEIGHTS:
        require_weights(NEEDS_WEIGHTS[name])
    return make_criterion(name, CriterionContext(target=_target()))


@pytest.fixture(scope="module")
def images():
    """Eight natural-ish test images [8, SIZE, SIZE, 3]: smooth gradients with shapes and noise."""
    rng = np.random.default_rng(0)
    ys, xs = np.mgrid[0:SIZE, 0:SIZE] / SIZE
    out = []
    for i in range(8):
        base = np.stack([xs, ys, 0.5 + 0.5 * np.sin(6 * xs + i)], -1) * rng.uniform(0.4, 1.0, 3)
        cx, cy, r = rng.uniform(0.25, 0.75, 2).tolist() + [rng.uniform(0.1, 0.25)]
        disc = (xs - cx) ** 2 + (ys - cy) ** 2 < r**2
        base[disc] = rng.uniform(0, 1, 3)
        out.append(np.clip(base + rng.normal(0, 0.02, base.shape), 0, 1))
    return np.asarray(out, np.float32)


def test_the_issue_criteria_are_registered():
    for name in ("saliency", "iqa_cnn", "niqe", "brisque", "composition", "waldo", "opacity"):
        assert name in CRITERIA, f"criterion {name!r} missing from the registry"
    assert CRITERIA["niqe"].direction == CRITERIA["brisque"].direction == "min"
    assert CRITERIA["iqa_cnn"].direction == CRITERIA["saliency"].direction == "max"


def test_each_criterion_declares_the_user_chosen_context_it_reads():
    """`CriterionSpec.reads` is what `waldo` warns by (`--weights` / `--target` with no effect): building
    each criterion reads exactly the fields it declares (the oracles stop earlier, at the missing room)."""
    from waldo_jax.criteria.base import CriterionError

    assert set(NEEDS_WEIGHTS) == {name for name, spec in CRITERIA.items() if "weights_dir" in spec.reads}
    for weights in NEEDS_WEIGHTS.values():
        require_weights(weights)
    read = set()

    class Recording(CriterionContext):
        def __getattribute__(self, field):
            if field in ("weights_dir", "target"):
                read.add(field)
            return super().__getattribute__(field)

    for name, spec in sorted(CRITERIA.items()):
        read.clear()
        try:
            make_criterion(name, Recording(target=_target()))
            built = True
        except CriterionError:
            built = False
        assert read <= set(spec.reads), (name, read)
        assert not built or read == set(spec.reads), (name, read)


@pytest.mark.parametrize("name", IMAGE_CRITERIA)
def test_criterion_contract(name, images):
    criterion = _build(name)
    worst = worst_score(criterion.direction, criterion.value_range)
    traces = []

    @jax.jit
    def score(c, x):
        traces.append(x.shape)
        return c.score_images(x)

    first = np.asarray(score(criterion, jnp.asarray(images)))
    again = np.asarray(score(criterion, jnp.asarray(images)))
    assert first.shape == (8,) and first.dtype == np.float32
    np.testing.assert_array_equal(first, again)  # deterministic
    assert np.all(np.isfinite(first))
    low, high = criterion.value_range
    assert np.all((first >= low) & (first <= high)), (name, first, criterion.value_range)
    # One image, and a batch of 64 (the eight, then 56 other images): the same scores as in the batch
    # of eight (no batch coupling; float32 fusion differs by batch), each new batch size compiled once.
    single = np.asarray(score(criterion, jnp.asarray(images[3:4])))
    np.testing.assert_allclose(single, first[3:4], rtol=1e-3, atol=1e-3)
    others = [np.clip(images[:, ::-1] * gain, 0, 1) for gain in (0.5, 0.7, 0.9, 1.1, 1.3, 1.5, 1.7)]
    big = np.asarray(score(criterion, jnp.asarray(np.concatenate([images] + others))))
    assert big.shape == (64,) and np.all(np.isfinite(big))
    np.testing.assert_allclose(big[:8], first, rtol=1e-3, atol=1e-3)
    # black, white and NaN images, in a batch of the first shape: no new trace
    special = np.concatenate(
        [np.stack([np.zeros_like(images[0]), np.ones_like(images[0]), images[1], images[2]]), images[4:]]
    )
    special[2, 10:20, 10:20, 1] = np.nan
    special[3, 0, 0, 0] = np.inf
    out = np.asarray(score(criterion, jnp.asarray(special)))
    assert np.all(np.isfinite(out)), (name, out)
    assert out[2] == pytest.approx(worst) and out[3] == pytest.approx(worst)
    np.testing.assert_allclose(out[4:], first[4:], rtol=1e-3, atol=1e-3)  # NaN in one view leaves the others alone
    assert traces == [images.shape, (1,) + images.shape[1:], (64,) + images.shape[1:]]


def _blur(image, sigma):
    from scipy.ndimage import gaussian_filter

    return np.clip(gaussian_filter(image, sigma=(sigma, sigma, 0), mode="reflect"), 0, 1).astype(np.float32)


def test_quality_criteria_rank_a_clean_fox_view_above_its_blurred_copies():
    import imageio.v3 as iio

    from waldo_jax.pipeline.sources import resize_images

    fox = require_scene("fox")
    path = sorted((fox / "images").glob("*.jpg"))[0]
    image = np.asarray(iio.imread(path), np.float32)[..., :3] / 255.0
    image = resize_images(image[None], 144, 256)[0]  # portrait 1080x1920 -> 144x256
    batch = np.stack([image, _blur(image, 1.5), _blur(image, 3.0)])
    # NIQE and BRISQUE rank the same fox view above three blurs of it in tests/test_niqe_brisque.py
    # (at 256 px, one program each): here the CNN, at the portrait's 144x256.
    for name in ("iqa_cnn",):
        criterion = _build(name)
        scores = np.asarray(criterion.score_images(batch))
        better = scores if criterion.direction == "max" else -scores
        assert better[0] > better[1] > better[2], (name, scores)

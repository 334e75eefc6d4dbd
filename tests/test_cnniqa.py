"""CNNIQA (`iqa_cnn`): the pipeline against an independent NumPy/SciPy port of the reference
(lidq92/CNNIQA), the weights converter's errors, and the score's response to blur and noise."""

import waldo_jax  # noqa: F401  (XLA flags before JAX starts)

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image
from scipy.ndimage import gaussian_filter
from scipy.signal import convolve2d

from conftest import require_scene, require_weights
from waldo_jax.criteria import cnniqa
from waldo_jax.criteria.base import CriterionContext, make_criterion
from waldo_jax.errors import DataNotFoundError
from waldo_jax.weights import TorchPickleError, WeightsError, save_native


# ---------------------------------------------------------------------------------------------
# The independent reference: NumPy/SciPy, PyTorch layouts, loops where the reference loops.


def np_local_normalisation(patch, P=3, Q=3, C=1.0):
    """`LocalNormalization` of the reference's IQADataset.py."""
    kernel = np.ones((P, Q)) / (P * Q)
    mean = convolve2d(patch, kernel, boundary="symm", mode="same")
    second = convolve2d(np.square(patch), kernel, boundary="symm", mode="same")
    return (patch - mean) / (np.sqrt(np.maximum(second - np.square(mean), 0)) + C)


def np_patches(grey):
    """`NonOverlappingCropPatches` (its loop bounds included) on a grey image [h, w] in [0, 1]."""
    h, w = grey.shape
    return np.stack(
        [
            np_local_normalisation(grey[i : i + 32, j : j + 32].astype(np.float64))
            for i in range(0, h - 32, 32)
            for j in range(0, w - 32, 32)
        ]
    )


def np_forward(sd, patches):
    """`CNNIQAnet.forward` in eval mode without dropout, on patches [N, 32, 32]; returns [N]."""
    weight, bias = sd["conv1.weight"].astype(np.float64), sd["conv1.bias"].astype(np.float64)
    k = weight.shape[-1]
    out = patches.shape[-1] - k + 1
    windows = np.lib.stride_tricks.sliding_window_view(patches, (k, k), axis=(1, 2))  # [N, 26, 26, 7, 7]
    h = np.einsum("nyxij,oij->noyx", windows, weight[:, 0]) + bias[None, :, None, None]  # [N, 50, 26, 26]
    assert h.shape[-1] == out
    h = np.concatenate([h.max(axis=(2, 3)), h.min(axis=(2, 3))], axis=1)  # [N, 100]
    for name in ("fc1", "fc2"):
        h = np.maximum(h @ sd[f"{name}.weight"].T.astype(np.float64) + sd[f"{name}.bias"], 0.0)
    return (h @ sd["fc3.weight"].T.astype(np.float64) + sd["fc3.bias"])[:, 0]


def random_state_dict(seed):
    rng = np.random.default_rng(seed)
    return {
        name: (rng.standard_normal(shape) / np.sqrt(np.prod(shape[1:]) if len(shape) > 1 else 10.0)).astype(np.float32)
        for name, shape in cnniqa.TORCH_SHAPES.items()
    }


def rgb_to_grey(image):
    return image @ np.array([0.299, 0.587, 0.114])


@pytest.fixture(scope="module")
def weights_dir():
    require_weights("cnniqa/CNNIQA-LIVE")
    from waldo_jax import paths

    return str(paths.weights_dir())


@pytest.fixture(scope="module")
def params(weights_dir):
    return cnniqa.load_params(weights_dir)


@pytest.fixture(scope="module")
def crit(weights_dir):
    return make_criterion("iqa_cnn", CriterionContext(weights_dir=weights_dir))


def load_image(path, side):
    """An RGB image resized (Lanczos) so that its longer side is `side` pixels, float32 in [0, 1]."""
    with Image.open(path) as im:
        im = im.convert("RGB")
        scale = side / max(im.size)
        im = im.resize((round(im.size[0] * scale), round(im.size[1] * scale)), Image.LANCZOS)
        return np.asarray(im, np.float32) / 255.0


@pytest.fixture(scope="module")
def real_images():
    fox = require_scene("fox") / "images"
    fern = require_scene("fern") / "images_8"
    return [
        load_image(fox / "0001.jpg", 256),
        load_image(fox / "0030.jpg", 256),
        load_image(fern / "image000.png", 256),
    ]


# ---------------------------------------------------------------------------------------------
# The pipeline against the reference port.


@pytest.mark.slow
def test_local_normalisation_and_patch_grid_match_the_reference():
    rng = np.random.default_rng(0)
    patch = rng.random((32, 32))
    np.testing.assert_allclose(
        np.asarray(cnniqa.local_normalise(jnp.asarray(patch, jnp.float32))), np_local_normalisation(patch), atol=1e-5
    )
    # A bright, textured patch: sigma is large enough here for the +1 to matter less.
    patch = 0.5 + 0.5 * np.sin(np.arange(32)[:, None] * 1.3 + np.arange(32) * 0.7)
    np.testing.assert_allclose(
        np.asarray(cnniqa.local_normalise(jnp.asarray(patch, jnp.float32))), np_local_normalisation(patch), atol=1e-5
    )
    # Grid: 100 x 70 px -> rows 0, 32, 64 and columns 0, 32; a 64 px side drops the second patch as
    # the reference's range(0, side - 32, 32) does.
    image = rng.random((100, 70, 3)).astype(np.float32)
    ours = np.asarray(cnniqa.image_patches(jnp.asarray(image)))[..., 0]
    theirs = np_patches(rgb_to_grey(image.astype(np.float64)))
    assert ours.shape == theirs.shape == (6, 32, 32)
    np.testing.assert_allclose(ours, theirs, atol=1e-5)
    assert [cnniqa.patch_grid(s) for s in (20, 32, 33, 64, 65, 96, 256, 257)] == [1, 1, 1, 1, 2, 2, 7, 8]


@pytest.mark.slow
def test_network_matches_numpy_with_converted_random_weights():
    sd = random_state_dict(1)
    variables = jax.tree.map(jnp.asarray, cnniqa.convert_state_dict(sd))
    patches = np.random.default_rng(2).standard_normal((5, 32, 32)).astype(np.float32) * 0.2
    ours = np.asarray(cnniqa.CNNIQANet().apply(variables, jnp.asarray(patches)[..., None]))
    np.testing.assert_allclose(ours, np_forward(sd, patches.astype(np.float64)), rtol=1e-4, atol=1e-4)
    # The concatenation order matters: swapping max and min pooling changes the output.
    swapped = dict(sd, **{"fc1.weight": np.concatenate([sd["fc1.weight"][:, 50:], sd["fc1.weight"][:, :50]], 1)})
    assert np.max(np.abs(np_forward(swapped, patches.astype(np.float64)) - ours)) > 1e-2


@pytest.mark.slow
def test_full_pipeline_matches_numpy_with_the_real_weights(params, real_images):
    from waldo_jax.weights import read_torch_file, state_dict

    sd = state_dict(read_torch_file(require_weights("cnniqa/CNNIQA-LIVE")))
    image = real_images[0][:140, :110]  # 4 x 3 patches of the fox
    expected = np.mean(np_forward(sd, np_patches(rgb_to_grey(image.astype(np.float64)))))
    got = float(cnniqa.cnniqa_dmos(params, jnp.asarray(image)))
    np.testing.assert_allclose(got, expected, rtol=1e-4)
    assert 0.0 < got < 60.0  # a sharp photo: low DMOS


# ---------------------------------------------------------------------------------------------
# Weights.


def test_converter_errors_name_the_file_and_the_key(tmp_path, weights_dir):
    original = require_weights("cnniqa/CNNIQA-LIVE")
    (tmp_path / "cnniqa").mkdir()
    truncated = tmp_path / "cnniqa" / "CNNIQA-LIVE"
    truncated.write_bytes(original.read_bytes()[:-1000])
    with pytest.raises(TorchPickleError, match=r"CNNIQA-LIVE.*truncated"):
        cnniqa.load_params(tmp_path)

    sd = random_state_dict(0)
    sd["fc2.weight"] = sd["fc2.weight"][:, :799]
    with pytest.raises(WeightsError, match=r"'fc2\.weight' has shape \(800, 799\), expected \(800, 800\)"):
        cnniqa.convert_state_dict(sd, "somefile")
    del sd["fc2.weight"]
    with pytest.raises(WeightsError, match=r"missing weight 'fc2\.weight'"):
        cnniqa.convert_state_dict(sd, "somefile")

    # A converted archive is checked too (it could come from another version of the network).
    tree = jax.tree.map(np.asarray, cnniqa.convert_state_dict(random_state_dict(0)))
    tree["params"]["fc1"]["kernel"] = tree["params"]["fc1"]["kernel"][:, :10]
    save_native(tmp_path / "cnniqa" / "cnniqa.npz", "cnniqa", tree, {})
    with pytest.raises(WeightsError, match=r"'params/fc1/kernel' has shape \(100, 10\)"):
        cnniqa.load_params(tmp_path)

    with pytest.raises(DataNotFoundError, match=r"empty.cnniqa.CNNIQA-LIVE"):
        cnniqa.load_params(tmp_path / "empty")


def test_converted_archive_gives_the_same_weights(tmp_path, params, weights_dir):
    from waldo_jax.weights import convert_all

    written = convert_all(weights_dir, tmp_path, models=["cnniqa"])
    assert written["cnniqa"] == tmp_path / "cnniqa" / "cnniqa.npz"
    again = cnniqa.load_params(tmp_path)
    chex.assert_trees_all_equal(again, params)


# ---------------------------------------------------------------------------------------------
# Behaviour of the score.


def blur(image, sigma):
    return image if sigma == 0 else np.stack([gaussian_filter(image[..., c], sigma) for c in range(3)], -1)


@pytest.mark.slow
def test_scores_worsen_with_blur_and_noise(crit, real_images):
    score = jax.jit(crit.score_images)
    key = jax.random.key(7)
    for i, image in enumerate(real_images):
        blurred = np.asarray(score(np.stack([blur(image, s) for s in (0, 1, 2, 4)])))
        noise = np.asarray(jax.random.normal(jax.random.fold_in(key, i), image.shape))
        noisy = np.asarray(score(np.stack([np.clip(image + level * noise, 0, 1) for level in (0, 0.02, 0.05, 0.1)])))
        # Measured (100 - DMOS) for sigma 0/1/2/4 px: 88/59/38/28 and 86/58/38/26 (fox), 73/59/39/29 (fern);
        # for noise 0/0.02/0.05/0.1: 88/85/64/44, 86/83/63/44 (fox), 73/71/62/45 (fern).
        assert np.all(np.diff(blurred) < -2.0), (i, blurred)
        assert np.all(np.diff(noisy) < -1.0), (i, noisy)
        assert blurred[0] > 60.0 and blurred[-1] < 40.0, (i, blurred)


@pytest.mark.slow
def test_clean_fox_beats_its_blurred_copies(crit, real_images):
    fox = real_images[0]
    scores = np.asarray(crit.score_images(np.stack([fox, blur(fox, 0.7), blur(fox, 1.5), blur(fox, 3.0)])))
    assert np.argmax(scores) == 0 and np.all(scores[1:] < scores[0] - 5.0), scores


@pytest.mark.slow
def test_jit_compiles_once_per_image_size(crit, params):
    traces = []

    @jax.jit
    def score(criterion, images):
        traces.append(images.shape)
        return criterion.score_images(images)

    rng = np.random.default_rng(0)
    a = score(crit, rng.random((2, 40, 48, 3)).astype(np.float32))
    score(crit, rng.random((2, 40, 48, 3)).astype(np.float32))
    # Other weights (the params are traced leaves, not constants) do not recompile either.
    other = crit.replace(params=jax.tree.map(lambda w: w * 1.01, params))
    b = score(other, rng.random((2, 40, 48, 3)).astype(np.float32))
    assert len(traces) == 1 and np.all(np.isfinite(a)) and np.all(np.isfinite(b))
    score(crit, rng.random((2, 72, 48, 3)).astype(np.float32))
    assert len(traces) == 2


@pytest.mark.slow
def test_batches_deterministic_extremes_and_failures(crit, real_images):
    fox = real_images[0][:96, :96]
    rng = np.random.default_rng(3)
    batch = np.stack(
        [
            fox,
            rng.random((96, 96, 3)).astype(np.float32),
            blur(fox, 2.0),
            np.zeros((96, 96, 3), np.float32),
            np.ones((96, 96, 3), np.float32),
        ]
    )
    score = jax.jit(lambda c, x: c.score_images(x))
    scores = np.asarray(score(crit, batch))
    singles = np.array([float(score(crit, batch[i : i + 1])[0]) for i in range(len(batch))])
    np.testing.assert_allclose(scores, singles, rtol=1e-5, atol=1e-4)
    np.testing.assert_array_equal(scores, np.asarray(score(crit, batch)))  # bit-identical again
    assert np.all(np.isfinite(scores))
    low, high = cnniqa.VALUE_RANGE
    assert np.all((scores >= low) & (scores <= high))
    # Black and white are both constant: every patch normalises to 0, so they score alike.
    assert scores[3] == pytest.approx(scores[4], abs=1e-4)

    broken = batch.copy()
    broken[0, 5, 5, 1] = np.nan
    broken[1, 0, 0, 0] = np.inf
    scores = np.asarray(score(crit, broken))
    assert scores[0] == scores[1] == low and np.all(np.isfinite(scores[2:])) and np.all(scores[2:] > low)


@pytest.mark.slow
def test_small_images_are_resized_up(params):
    rng = np.random.default_rng(4)
    small = rng.random((20, 40, 3)).astype(np.float32)  # 20 px high: resized to 32 x 40, one patch
    assert cnniqa.image_patches(jnp.asarray(small)).shape == (1, 32, 32, 1)
    dmos = jax.jit(cnniqa.cnniqa_dmos)
    assert np.isfinite(float(dmos(params, jnp.asarray(small))))
    tiny = rng.random((8, 8, 3)).astype(np.float32)
    assert np.isfinite(float(dmos(params, jnp.asarray(tiny))))


def test_missing_weights_error(tmp_path):
    with pytest.raises(DataNotFoundError, match="weights file not found.*cnniqa"):
        make_criterion("iqa_cnn", CriterionContext(weights_dir=str(tmp_path)))

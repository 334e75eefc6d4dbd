"""`waldo_jax.metrics`: one PSNR for training, fitting, the demo and the benchmarks."""

import jax
import jax.numpy as jnp
import numpy as np

from waldo_jax.metrics import MSE_FLOOR, image_psnr, psnr_from_mse


def test_psnr_known_values_and_floor():
    np.testing.assert_allclose(psnr_from_mse(np.array([1.0, 0.01, 1e-4])), [0.0, 20.0, 40.0], atol=1e-9)
    assert psnr_from_mse(np.float64(0.0)) == -10.0 * np.log10(MSE_FLOOR)  # identical images: finite, 120 dB


def test_psnr_same_in_numpy_jax_and_under_jit():
    mse = np.array([0.25, 3e-3, 0.0], np.float32)
    host = psnr_from_mse(mse)
    np.testing.assert_allclose(np.asarray(psnr_from_mse(jnp.asarray(mse))), host, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(jax.jit(psnr_from_mse)(jnp.asarray(mse))), host, rtol=1e-6)


def test_image_psnr_per_image():
    truth = np.zeros((2, 4, 4, 3))
    rendered = truth.copy()
    rendered[0] += 0.1  # MSE 0.01: 20 dB
    np.testing.assert_allclose(image_psnr(rendered, truth), [20.0, 120.0], atol=1e-9)

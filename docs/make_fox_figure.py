"""The README's fox figure: a held-out fox view rendered by a trained run, next to the real photo
and a training view.

  waldo train ../shared/scenes/fox --downscale 8 --out runs/fox
  python docs/make_fox_figure.py runs/fox
"""

import sys
from pathlib import Path

import waldo_jax  # noqa: F401  (XLA flags first)
import jax
import numpy as np

from waldo_jax.io import contact_sheet, save_png
from waldo_jax.nerf.checkpoint import load_checkpoint
from waldo_jax.nerf.trained import TrainedField, render_trained
from waldo_jax.paths import scene_path
from waldo_jax.scenes import load_scene

OUT = Path(__file__).resolve().parent / "images" / "fox_heldout_vs_train.png"


def main(run_dir: str, test_index: int = 1) -> None:
    checkpoint = load_checkpoint(run_dir)
    fox = scene_path("fox")
    train = load_scene(fox, downscale=8, split="train")
    test = load_scene(fox, downscale=8, split="test")
    out = render_trained(
        TrainedField.from_checkpoint(checkpoint), test.c2w[test_index : test_index + 1], test.intrinsics
    )
    render = np.asarray(jax.device_get(out.rgb))[0]
    mse = float(np.mean((render - test.images[test_index]) ** 2))
    psnr = -10 * np.log10(mse)
    sheet = contact_sheet(
        [train.images[0], test.images[test_index], render],
        columns=3,
        labels=["training view", "held-out photo", f"render {psnr:.1f} dB"],
        min_cell=135,
    )
    save_png(OUT, sheet)
    print(f"wrote {OUT} (held-out view {test.file_names[test_index]}, PSNR {psnr:.2f} dB)")


if __name__ == "__main__":
    main(sys.argv[1])

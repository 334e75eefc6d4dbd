"""Writing results: PNG images, labelled contact sheets, run folders that never overwrite, JSON.

Everything here runs on the host (NumPy / Pillow / imageio), at the edges of the program.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any, Optional, Sequence

import imageio.v3 as iio
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from waldo_jax.errors import WaldoError

__all__ = ["to_uint8", "save_png", "contact_sheet", "prepare_output_dir", "write_json", "write_transforms"]


def to_uint8(image: np.ndarray) -> np.ndarray:
    """float [H, W, 3] in [0, 1] (NaN as 0) -> uint8 [H, W, 3]."""
    image = np.nan_to_num(np.asarray(image, np.float32), nan=0.0, posinf=1.0, neginf=0.0)
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def save_png(path: str | os.PathLike, image: np.ndarray) -> None:
    """Writes a float [H, W, 3] image in [0, 1] (or uint8) as PNG."""
    image = np.asarray(image)
    iio.imwrite(path, image if image.dtype == np.uint8 else to_uint8(image))


def _font(size: int):
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow < 10.1 has a single fixed-size bitmap font
        return ImageFont.load_default()


def contact_sheet(
    images: Sequence[np.ndarray],
    columns: Optional[int] = None,
    labels: Optional[Sequence[Optional[str]]] = None,
    pad: int = 2,
    min_cell: int = 96,
    row_titles: Optional[Sequence[str]] = None,
) -> np.ndarray:
    """Tiles images into one uint8 picture, with an optional label written on each tile.

    Args:
      images: N images [H, W, 3] (float in [0, 1] or uint8) of one size; `None` leaves a cell empty.
      columns: tiles per row (default: about square).
      labels: N strings (or None) written in the tile's top-left corner on a dark band.
      pad: pixels between tiles.
      min_cell: small images are enlarged (nearest neighbour) so that a tile is at least this wide,
        keeping labels readable.
      row_titles: optional title per row, drawn in a band left of the row.

    Returns:
      uint8 [H_sheet, W_sheet, 3].
    """
    present = [im for im in images if im is not None]
    if not present:
        raise ValueError("contact_sheet needs at least one image")
    h, w = np.asarray(present[0]).shape[:2]
    scale = max(1, int(np.ceil(min_cell / w)))
    th, tw = h * scale, w * scale
    n = len(images)
    columns = columns or int(np.ceil(np.sqrt(n)))
    rows = int(np.ceil(n / columns))
    title_w = 0
    font = _font(max(10, min(16, tw // 8)))
    if row_titles:
        title_w = 12 + max(int(ImageDraw.Draw(Image.new("RGB", (1, 1))).textlength(t, font=font)) for t in row_titles)
    sheet = Image.new("RGB", (title_w + columns * tw + (columns + 1) * pad, rows * th + (rows + 1) * pad), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    for i, image in enumerate(images):
        r, c = divmod(i, columns)
        x0, y0 = title_w + pad + c * (tw + pad), pad + r * (th + pad)
        if image is None:
            continue
        tile = to_uint8(image) if np.asarray(image).dtype != np.uint8 else np.asarray(image)
        if tile.shape[:2] != (h, w):
            raise ValueError(f"contact_sheet: image {i} is {tile.shape[1]}x{tile.shape[0]}, expected {w}x{h}")
        tile = np.repeat(np.repeat(tile, scale, 0), scale, 1)
        sheet.paste(Image.fromarray(tile), (x0, y0))
        if labels is not None and labels[i]:
            box = draw.textbbox((x0 + 3, y0 + 2), labels[i], font=font)
            draw.rectangle((box[0] - 2, box[1] - 1, box[2] + 2, box[3] + 1), fill=(0, 0, 0))
            draw.text((x0 + 3, y0 + 2), labels[i], fill=(255, 255, 255), font=font)
    for r, title in enumerate(row_titles or []):
        draw.text((6, pad + r * (th + pad) + th // 2 - 6), title, fill=(0, 0, 0), font=font)
    return np.asarray(sheet)


def prepare_output_dir(path: str | os.PathLike, force: bool = False, can_force: bool = True) -> Path:
    """Creates an output folder, refusing to reuse a non-empty one unless `force`.

    `can_force` False: the command has no `--force`, and the error does not suggest one.

    Raises:
      WaldoError: the folder exists and is not empty (and `force` is False), or it is a file.
    """
    path = check_output_dir(path, force, can_force)
    path.mkdir(parents=True, exist_ok=True)
    return path


def check_output_dir(path: str | os.PathLike, force: bool = False, can_force: bool = True) -> Path:
    """`prepare_output_dir`'s checks without creating anything: call it before slow or fallible work,
    and `prepare_output_dir` once everything is validated, so a bad argument leaves no empty folder."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise WaldoError(f"{path}: exists and is not a directory")
    if path.is_dir() and any(path.iterdir()) and not force:
        advice = "choose another --out or pass --force" if can_force else "choose another --out"
        raise WaldoError(f"{path}: output directory exists and is not empty ({advice})")
    return path


def write_json(path: str | os.PathLike, obj: Any) -> None:
    """Writes JSON atomically (temp file + rename), NumPy values converted."""

    def default(o):
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
        raise TypeError(f"not JSON serialisable: {type(o).__name__}")

    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(obj, indent=2, default=default) + "\n")
    os.replace(tmp, path)


def write_transforms(path: str | os.PathLike, c2w: np.ndarray, intrinsics, file_names: Sequence[str],
                     extra: Optional[dict] = None) -> None:
    """Writes cameras as an instant-ngp/nerfstudio-style `transforms.json` (OpenGL c2w).

    Args:
      path: output file.
      c2w: [N, 4, 4] camera-to-world matrices.
      intrinsics: a `waldo_jax.types.Intrinsics`.
      file_names: N image paths relative to the file's folder.
      extra: more top-level keys.
    """
    d = intrinsics.to_dict()
    meta = {
        "w": d["width"], "h": d["height"], "fl_x": d["fx"], "fl_y": d["fy"], "cx": d["cx"], "cy": d["cy"],
        "k1": d["k1"], "k2": d["k2"], "p1": d["p1"], "p2": d["p2"],
        "camera_angle_x": float(2 * np.arctan(0.5 * d["width"] / d["fx"])),
        "camera_angle_y": float(2 * np.arctan(0.5 * d["height"] / d["fy"])),
    }
    meta.update(extra or {})
    c2w = np.asarray(c2w, np.float64)
    meta["frames"] = [
        {"file_path": name, "transform_matrix": np.round(m, 8).tolist()} for name, m in zip(file_names, c2w)
    ]
    write_json(path, meta)

"""Bad input through the real CLI entry point: a one-line error naming the value, exit status 1, no
traceback, and nothing written or changed (issues [2/6] and [3/5]: one case per kind of number that
reaches a division, a float32 / int32 cast or a shape, per kind of broken checkpoint, per image
outside its range).

Each case runs `waldo_jax.cli.main(argv)` in-process with `{tmp}` in argv replaced by a fresh folder
that holds an earlier run (`{tmp}/run/keep.txt`) and the inputs of `_inputs` (a small scene, scenes
with broken cameras, a tiny trained run and one with NaN parameters, images), and checks that the
folder is byte-identical afterwards and that no other file appeared.
"""

import errno
import hashlib
import json
import os

import numpy as np
import pytest
from conftest import within

from waldo_jax.cli import main
from waldo_jax.errors import MAX_RESOLUTION, MAX_SEED, WaldoError, check_seed

BIG = "100000000000000000000"  # 1e20 as an integer: overflows int64
LONG = "a" * 300  # a file name past every common file system's 255-byte limit

CASES = [
    # (id, argv, text the one-line message must contain)
    ("train-seed-overflow", ["train", "{tmp}/scene", "--out", "{tmp}/new", "--seed", BIG], BIG),
    ("train-seed-negative", ["train", "{tmp}/scene", "--out", "{tmp}/new", "--seed", "-1"], "--seed"),
    ("render-seed-overflow", ["render", "procedural", "--out", "{tmp}/new", "--seed", BIG], BIG),
    ("explore-seed-overflow", ["explore", "procedural", "--out", "{tmp}/new", "--seed", BIG], BIG),
    (
        "explore-seeds-past-the-limit",
        ["explore", "procedural", "--out", "{tmp}/new", "--seed", str(MAX_SEED), "--seeds", "2"],
        str(MAX_SEED),
    ),
    ("demo-seed-overflow", ["demo", "--out", "{tmp}/new", "--seed", BIG], BIG),
    ("procedural-negative-seed", ["explore", "procedural:-1", "--out", "{tmp}/new"], "procedural:-1"),
    # Seeds and sources by their text: int() took "", "1_0", "+1" and Arabic-Indic digits; an empty or
    # mis-cased SOURCE was blamed on a checkpoint inside it, or on the flags.
    # Numbers on the command line in ASCII digits: int() and float() read "1_0" as 10 and Arabic-Indic digits.
    ("views-underscore", ["render", "procedural", "--views", "1_0", "--out", "{tmp}/new"], "--views must be a number"),
    ("seed-arabic-indic", ["render", "procedural", "--seed", "١", "--out", "{tmp}/new"], "--seed must be a number"),
    ("grid-arabic-indic", ["explore", "procedural", "--grid", "٨x٤", "--out", "{tmp}/new"], "--grid must be AZxEL"),
    (
        "distance-edges-arabic-indic",
        ["explore", "procedural", "--distance-edges", "١,٢", "--out", "{tmp}/new"],
        "--distance-edges must be comma-separated numbers",
    ),
    ("procedural-seed-underscore", ["render", "procedural:1_0", "--out", "{tmp}/new"], "SEED a whole number in digits"),
    ("procedural-seed-empty", ["render", "procedural:", "--out", "{tmp}/new"], "SEED a whole number in digits"),
    ("explore-empty-source", ["explore", "", "--out", "{tmp}/new"], "SOURCE is empty"),
    ("render-miscased-source", ["render", "Procedural", "--views", "1", "--out", "{tmp}/new"], "spelt procedural"),
    ("procedural-seed-overflow", ["render", f"procedural:{BIG}", "--out", "{tmp}/new"], BIG),
    ("demo-into-an-earlier-run", ["demo", "--out", "{tmp}/run"], "{tmp}/run"),
    ("demo-zero-train-steps", ["demo", "--out", "{tmp}/new", "--train-steps", "0"], "--train-steps"),
    # Scenes whose cameras cannot be used.
    ("scene-info-translation-overflow", ["scene", "info", "{tmp}/far", "--json"], "1e+308"),
    ("train-translation-overflow", ["train", "{tmp}/far", "--out", "{tmp}/new"], "far/transforms.json"),
    ("scene-negative-aabb-scale", ["scene", "info", "{tmp}/negative_aabb"], "'aabb_scale'"),
    (
        "train-downscale-to-1px",
        ["train", "{tmp}/scene", "--out", "{tmp}/new", "--downscale", "1000"],
        "--downscale 1000 leaves 1x1",
    ),
    # Output folders that cannot be written, checked before any work.
    (
        "train-out-under-a-file",
        ["train", "{tmp}/scene", "--out", "{tmp}/run/keep.txt/new"],
        "keep.txt is not a directory",
    ),
    ("train-out-name-too-long", ["train", "{tmp}/scene", "--out", "{tmp}/" + LONG], "300 bytes"),
    ("explore-out-name-too-long", ["explore", "procedural", "--out", "{tmp}/" + LONG], "300 bytes"),
    # A path whose names each fit but whose whole (with the files written inside) passes PATH_MAX: a training
    # once ran to its end and then failed to write its checkpoint, leaving 17 empty folders.
    (
        "train-out-path-too-long",
        ["train", "{tmp}/scene", "--out", "{tmp}/" + "/".join(["d" * 250] * 16)],
        "passes this system's limit of",
    ),
    ("render-out-empty", ["render", "procedural", "--out", ""], "the output folder is empty text"),
    # Floats that leave float32 (where they are used) only in a product or below its smallest number: a
    # guard of 1e-300 passed every view, edges of 1e39 and speeds of 1e38 overflowed into a wrong verdict,
    # a render step of 1e-40 was accepted after the run folder was made.
    (
        "train-render-step-scale-tiny",
        ["train", "{tmp}/scene", "--out", "{tmp}/new", "--render-step-scale=1e-40"],
        "--render-step-scale must be between 0.01 and 100",
    ),
    (
        "explore-guard-underflows",
        ["explore", "procedural", "--out", "{tmp}/new", "--criterion", "colorfulness", "--guard", "opacity:1e-300"],
        "must be 0 or a number float32 holds",
    ),
    (
        "explore-distance-edge-overflows",
        ["explore", "procedural", "--out", "{tmp}/new", "--method", "map-elites", "--distance-edges=1e38,1e39"],
        "--distance-edges must be a finite number",
    ),
    (
        "path-speed-times-frames-overflows",
        ["path", "procedural", "--out", "{tmp}/new", "--frames", "4", "--max-speed=1e38", "--min-travel=1e38"],
        "--frames x --max-speed must be a finite number",
    ),
    ("weights-dst-empty", ["weights", "convert", "{tmp}/run", ""], "the output folder is empty text"),
    ("render-into-an-earlier-run", ["render", "{tmp}/tiny_run", "--poses", "train", "--out", "{tmp}/run"], "not empty"),
    # Sizes a user can ask for: each with its limit.
    (
        "render-resolution-huge",
        ["render", "procedural", "--out", "{tmp}/new", "--resolution", "100000"],
        f"between 8 and {MAX_RESOLUTION}",
    ),
    (
        "render-run-resolution-huge",
        ["render", "{tmp}/tiny_run", "--poses", "train", "--out", "{tmp}/new", "--resolution", "100000"],
        f"between 8 and {MAX_RESOLUTION}",
    ),
    (
        "render-poses-file-width-huge",
        ["render", "{tmp}/tiny_run", "--poses", "{tmp}/wide_poses.json", "--out", "{tmp}/new"],
        "wide_poses.json: camera of 100000x100",
    ),
    (
        "explore-resolution-huge",
        ["explore", "procedural", "--out", "{tmp}/new", "--resolution", "100000"],
        f"between 8 and {MAX_RESOLUTION}",
    ),
    (
        "explore-top-k-past-capacity",
        ["explore", "procedural", "--out", "{tmp}/new", "--top-k", "1000"],
        "--top-k) 1000 exceeds the 274 views",
    ),
    (
        "explore-seeds-past-memory",
        # Seeds render one after another: what grows with them is what each keeps (about 100 KiB here).
        ["explore", "procedural", "--criterion", "colorfulness", "--out", "{tmp}/new", "--seeds", "10000000"],
        "each seed keeps",
    ),
    (
        "explore-views-too-many",
        ["explore", "procedural", "--out", "{tmp}/new", "--views", "100000"],
        "--views must be an integer between 1 and 1000",
    ),
    (
        "explore-target-too-large",
        ["explore", "procedural", "--criterion", "waldo", "--target", "{tmp}/huge.png", "--out", "{tmp}/new"],
        f"huge.png: the image is 4100x8; sides must lie between 2 and {MAX_RESOLUTION}",
    ),
    ("score-1x1-image", ["score", "--criterion", "brisque", "{tmp}/dot.png"], "dot.png: the image is 1x1"),
    # Arguments that were accepted without a word.
    (
        "guard-fails-every-view",
        ["explore", "procedural", "--criterion", "colorfulness", "--guard", "opacity:2", "--out", "{tmp}/new"],
        "fails every view",
    ),
    (
        "guard-passes-every-view",
        ["explore", "procedural", "--criterion", "colorfulness", "--guard", "opacity:-1", "--out", "{tmp}/new"],
        "passes every view",
    ),
    (
        "weighted-one-criterion-no-weight",
        ["explore", "procedural", "--criterion", "weighted:composition", "--out", "{tmp}/new"],
        "bad weight",
    ),
    (
        "weighted-duplicate",
        ["explore", "procedural", "--criterion", "weighted:opacity=1,opacity=2", "--out", "{tmp}/new"],
        "names 'opacity' twice",
    ),
    (
        "explore-views-on-a-run",
        ["explore", "{tmp}/tiny_run", "--views", "5", "--criterion", "colorfulness", "--out", "{tmp}/new"],
        "--views is for procedural sources",
    ),
    (
        "render-views-on-a-run",
        ["render", "{tmp}/tiny_run", "--poses", "train", "--views", "5", "--out", "{tmp}/new"],
        "--views: for procedural sources only",
    ),
    # Non-finite data: refused naming the file.
    (
        "render-nan-checkpoint",
        ["render", "{tmp}/nan_run", "--poses", "train", "--out", "{tmp}/new"],
        "nan_run/checkpoint.ckpt: the field's parameters hold NaN",
    ),
    (
        "explore-nan-checkpoint",
        ["explore", "{tmp}/nan_run", "--criterion", "colorfulness", "--out", "{tmp}/new"],
        "nan_run/checkpoint.ckpt: the field's parameters hold NaN",
    ),
    ("score-nan-pixel", ["score", "--criterion", "colorfulness", "{tmp}/nan.tiff"], "nan.tiff: the image has 1 NaN"),
    # Numbers that reach a division, a float32 / int32 cast or a shape: checked where they enter
    # (errors.check_float32 / check_int, scenes.common.focal_from_angle / intrinsics_problem).
    ("scene-negative-w", ["scene", "info", "{tmp}/negative_w"], "negative_w/transforms.json: 'w' must be a positive"),
    (
        "scene-zero-fov",
        ["scene", "info", "{tmp}/zero_fov"],
        "zero_fov/transforms.json: 'camera_angle_x' must be a field of view between 0 and 3.14159 radians",
    ),
    ("train-zero-fov", ["train", "{tmp}/zero_fov", "--out", "{tmp}/new"], "'camera_angle_x' must be a field of view"),
    (
        "render-poses-zero-fov",
        ["render", "{tmp}/tiny_run", "--poses", "{tmp}/zero_fov_poses.json", "--out", "{tmp}/new"],
        "zero_fov_poses.json: 'camera_angle_x' must be a field of view",
    ),
    (
        "render-camera-path-zero-fov",
        ["render", "{tmp}/tiny_run", "--poses", "{tmp}/zero_fov_path.json", "--out", "{tmp}/new"],
        "zero_fov_path.json: 'fov' must be a field of view between 0 and 180",
    ),
    ("scene-fov-of-180-degrees", ["scene", "info", "{tmp}/flat_fov"], "a pinhole camera needs 0.001 to 179"),
    (
        "scene-focal-zero-in-float32",
        ["scene", "info", "{tmp}/tiny_focal"],
        "'fl_x' must be a positive number that float32",
    ),
    (
        "render-poses-focal-zero-in-float32",
        ["render", "{tmp}/tiny_run", "--poses", "{tmp}/tiny_focal_poses.json", "--out", "{tmp}/new"],
        "tiny_focal_poses.json: 'fl_x' must be a positive",
    ),
    (
        "render-poses-focal-inf-in-float32",
        ["render", "{tmp}/tiny_run", "--poses", "{tmp}/huge_focal_poses.json", "--out", "{tmp}/new"],
        "huge_focal_poses.json: 'fl_x' must be a finite number",
    ),
    (
        "train-steps-past-int32",
        ["train", "{tmp}/scene", "--out", "{tmp}/new", "--steps", "1000000000000"],
        "--steps must be a positive integer of at most 10000000",
    ),
    # Steps within int32 but past any training: 2e9 started a 170,000-hour run whose history alone would be 30 GB.
    (
        "train-steps-past-any-training",
        ["train", "{tmp}/scene", "--out", "{tmp}/new", "--steps", "2000000000"],
        "--steps must be a positive integer of at most 10000000",
    ),
    (
        "splat-fit-steps-past-any-training",
        ["train", "{tmp}/scene", "--model", "splat", "--out", "{tmp}/new", "--steps", "2000000000"],
        "--steps must be an integer between 1 and 10000000",
    ),
    (
        "demo-train-steps-past-any-training",
        ["demo", "--out", "{tmp}/new", "--train-steps", "100000000"],
        "--train-steps must be an integer between 1 and 10000000",
    ),
    (
        "explore-children-past-int32",
        ["explore", "procedural", "--children-per-epoch", "3000000000", "--out", "{tmp}/new"],
        "--children-per-epoch must be an integer between 1 and 2147483647",
    ),
    (
        "explore-refine-step-zero-in-float32",
        ["explore", "procedural", "--method", "egps+refine", "--refine-step-size", "1e-300", "--out", "{tmp}/new"],
        "--refine-step-size must be a positive",
    ),
    (
        "path-fps-zero-in-float32",
        ["path", "procedural", "--criterion", "colorfulness", "--fps", "1e-300", "--out", "{tmp}/new"],
        "--fps must be a positive number that float32 holds",
    ),
    (
        "train-render-step-scale-zero-in-float32",
        ["train", "{tmp}/scene", "--out", "{tmp}/new", "--render-step-scale", "1e-300"],
        "--render-step-scale must be a positive number that float32",
    ),
    # Checkpoints checked as a whole when opened: camera, box, near/far, poses, background.
    (
        "render-checkpoint-near-beyond-far",
        ["render", "{tmp}/near_far_run", "--poses", "train", "--out", "{tmp}/new"],
        "near_far_run/checkpoint.ckpt: near/far bounds 5 / 1 do not satisfy 0 < near < far",
    ),
    (
        "explore-checkpoint-nan-pose",
        ["explore", "{tmp}/nan_pose_run", "--criterion", "colorfulness", "--out", "{tmp}/new"],
        "nan_pose_run/checkpoint.ckpt: training pose 3: pose has non-finite",
    ),
    (
        "render-checkpoint-sheared-pose",
        ["render", "{tmp}/sheared_pose_run", "--poses", "train", "--out", "{tmp}/new"],
        "sheared_pose_run/checkpoint.ckpt: training pose 0: pose is not rigid",
    ),
    (
        "render-checkpoint-nan-background",
        ["render", "{tmp}/nan_background_run", "--poses", "train", "--out", "{tmp}/new"],
        "the background colour [nan, 0.5, 0.5] is not 3 numbers in [0, 1]",
    ),
    (
        "explore-checkpoint-nan-background",
        ["explore", "{tmp}/nan_background_run", "--criterion", "colorfulness", "--out", "{tmp}/new"],
        "nan_background_run/checkpoint.ckpt: the background",
    ),
    (
        "render-checkpoint-zero-focal",
        ["render", "{tmp}/zero_focal_run", "--poses", "train", "--out", "{tmp}/new"],
        "zero_focal_run/checkpoint.ckpt: the training camera: focal length fx = 0 px",
    ),
    (
        "render-checkpoint-huge-camera",
        ["render", "{tmp}/huge_camera_run", "--poses", "train", "--out", "{tmp}/new"],
        "huge_camera_run/checkpoint.ckpt: the training camera: camera of 100000x100000 pixels",
    ),
    (
        "render-checkpoint-flipped-box",
        ["render", "{tmp}/flipped_box_run", "--poses", "train", "--out", "{tmp}/new"],
        "flipped_box_run/checkpoint.ckpt: scene box",
    ),
    # Images outside the range they are read in: refused in one line, not clipped or misread.
    (
        "score-float-tiff-beyond-1",
        ["score", "--criterion", "colorfulness", "{tmp}/hdr.tiff"],
        "hdr.tiff: a float32 image with values in [0",
    ),
    (
        "explore-target-float-tiff-beyond-1",
        ["explore", "procedural", "--criterion", "waldo", "--target", "{tmp}/hdr.tiff", "--out", "{tmp}/new"],
        "hdr.tiff: a float32 image",
    ),
    (
        "train-float-image-beyond-1",
        ["train", "{tmp}/float_scene", "--out", "{tmp}/new"],
        "float_scene/images/1.tiff: a F-mode image with values in [0, 255], outside [0, 1]",
    ),
    # Files that are not what they should be: said as they are, not "not found".
    ("score-a-directory", ["score", "--criterion", "colorfulness", "{tmp}/run"], "run: a directory"),
    ("score-a-fifo", ["score", "--criterion", "colorfulness", "{tmp}/fifo"], "fifo: a FIFO"),
    ("score-a-symlink-loop", ["score", "--criterion", "colorfulness", "{tmp}/loop"], "loop: a symbolic link loop"),
    (
        "score-not-an-image",
        ["score", "--criterion", "colorfulness", "{tmp}/junk.png"],
        "junk.png: not a readable image",
    ),
    ("score-an-empty-image", ["score", "--criterion", "colorfulness", "{tmp}/empty.png"], "empty.png: an empty file"),
    (  # a 900-megapixel PNG header: Pillow's own decompression-bomb text, now the size rule's
        "score-a-bomb-sized-image",
        ["score", "--criterion", "colorfulness", "{tmp}/bomb.png"],
        "bomb.png: the image is too large (Image size (900000000 pixels)); sides must lie between 8 and "
        f"{MAX_RESOLUTION}",
    ),
    (
        "render-poses-a-directory",
        ["render", "{tmp}/tiny_run", "--poses", "{tmp}/run", "--out", "{tmp}/new"],
        "run: a directory",
    ),
    ("scene-a-symlink-loop", ["scene", "info", "{tmp}/loop"], "loop: a symbolic link that leads nowhere"),
    ("train-scene-a-fifo", ["train", "{tmp}/fifo", "--out", "{tmp}/new"], "fifo: a FIFO, socket or device"),
    (
        "render-checkpoint-a-fifo",
        ["render", "{tmp}/fifo_run", "--poses", "train", "--out", "{tmp}/new"],
        "checkpoint.ckpt: a FIFO",
    ),
]


def _write_scene(folder, translation=None, float_images=False, **meta):
    """A small instant-ngp scene: 8 cameras on a circle looking at the origin, 16x16 images (8-bit PNGs,
    or with `float_images` 32-bit float grey TIFFs with values up to 255)."""
    import imageio.v3 as iio

    from waldo_jax.cameras import look_at

    (folder / "images").mkdir(parents=True)
    frames = []
    for i in range(8):
        angle = 2 * np.pi * i / 8
        c2w = np.asarray(
            look_at(
                np.array([3 * np.cos(angle), 0.5, 3 * np.sin(angle)], np.float32),
                np.zeros(3),
                np.array([0.0, 1.0, 0.0]),
            ),
            np.float64,
        )
        c2w = np.concatenate([c2w[:3], [[0, 0, 0, 1]]])
        if translation is not None:
            c2w[0, 3] = translation
        pixels = np.random.default_rng(i).integers(0, 256, (16, 16, 3), np.uint8)
        name = f"images/{i}.tiff" if float_images else f"images/{i}.png"
        iio.imwrite(folder / name, pixels[..., 0].astype(np.float32) if float_images else pixels)
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
    (folder / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.8, **meta, "frames": frames}))


def _write_run(folder, nan=False, **record):
    """A run folder with an untrained tiny field (rendering it is cheap); NaN parameters if `nan`;
    `record` replaces fields of the checkpoint's scene record (a broken camera, box, pose...)."""
    import dataclasses

    import jax

    from waldo_jax.nerf import HashGridConfig, NGPFieldConfig, init_field
    from waldo_jax.nerf.checkpoint import CHECKPOINT_NAME, SceneRecord, save_checkpoint
    from waldo_jax.nerf.config import TrainConfig
    from waldo_jax.scenes import load_scene

    scene = load_scene(folder.parent / "scene")
    field = NGPFieldConfig(
        aabb=tuple(map(tuple, scene.aabb.tolist())),
        hashgrid=HashGridConfig(L=2, T=2**8, F=2, N_min=4, N_max=8),
        density_hidden=(8,),
        color_hidden=(8,),
    )
    config = TrainConfig(field=field, steps=1, sampler="dense", num_samples=8, samples_per_batch=256, eval_samples=8)
    params = init_field(jax.random.key(0), field)
    if nan:
        params = jax.tree.map(lambda a: np.full_like(a, np.nan), params)
    folder.mkdir()
    save_checkpoint(
        folder / CHECKPOINT_NAME,
        params,
        config,
        dataclasses.replace(SceneRecord.from_scene(scene), **record) if record else scene,
    )


def _write_png_header(path, width, height):
    """A PNG whose header says width x height over a few bytes of pixel data (a decompression bomb's size)."""
    import struct
    import zlib

    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    path.write_bytes(
        b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")
    )


def _inputs(tmp):
    """The files the cases read, written once per test into `tmp`."""
    import imageio.v3 as iio

    _write_scene(tmp / "scene")
    _write_scene(tmp / "far", translation=1e308)  # finite in JSON, infinite in float32
    _write_scene(tmp / "negative_aabb", aabb_scale=-4)
    _write_run(tmp / "tiny_run")
    _write_run(tmp / "nan_run", nan=True)
    (tmp / "fifo_run").mkdir()
    os.mkfifo(tmp / "fifo_run" / "checkpoint.ckpt")
    os.mkfifo(tmp / "fifo")
    os.symlink(tmp / "loop", tmp / "loop")
    (tmp / "junk.png").write_text("not an image")
    (tmp / "empty.png").write_bytes(b"")
    _write_png_header(tmp / "bomb.png", 30000, 30000)
    iio.imwrite(tmp / "huge.png", np.zeros((8, 4100, 3), np.uint8))
    iio.imwrite(tmp / "dot.png", np.zeros((1, 1, 3), np.uint8))
    nan = np.random.default_rng(0).random((16, 16, 3)).astype(np.float32)
    nan[3, 3, 0] = np.nan
    iio.imwrite(tmp / "nan.tiff", nan)
    c2w = json.loads((tmp / "scene" / "transforms.json").read_text())["frames"][0]["transform_matrix"]
    (tmp / "wide_poses.json").write_text(
        json.dumps({"fl_x": 100, "w": 100000, "h": 100, "frames": [{"transform_matrix": c2w}]})
    )
    _broken_camera_inputs(tmp, c2w)


def _broken_camera_inputs(tmp, c2w):
    """Scenes, poses files, camera paths, runs and images whose numbers cannot be used as they are."""
    import imageio.v3 as iio

    from waldo_jax.types import Intrinsics

    _write_scene(tmp / "negative_w", w=-16, h=16, fl_x=20.0)
    _write_scene(tmp / "zero_fov", camera_angle_x=0)
    _write_scene(tmp / "flat_fov", camera_angle_x=3.14159265)  # a focal length of ~4e-8 px: all rays sideways
    _write_scene(tmp / "tiny_focal", fl_x=1e-300)  # > 0 in float64, 0 in float32
    _write_scene(tmp / "float_scene", float_images=True)
    frames = [{"transform_matrix": c2w}]
    for name, camera in (
        ("zero_fov_poses", {"camera_angle_x": 0}),
        ("tiny_focal_poses", {"fl_x": 1e-300}),
        ("huge_focal_poses", {"fl_x": 1e300}),
    ):
        (tmp / f"{name}.json").write_text(json.dumps({**camera, "w": 16, "h": 16, "frames": frames}))
    flat = np.asarray(c2w, np.float64).reshape(-1).tolist()
    (tmp / "zero_fov_path.json").write_text(
        json.dumps(
            {  # a camera path as `waldo path` writes one, fov 0
                "render_width": 16,
                "render_height": 16,
                "camera_path": [{"camera_to_world": flat, "fov": 0, "aspect": 1}],
                "waldo": {"world": "scene"},
            }
        )
    )
    c2w_nan = np.stack([np.asarray(c2w, np.float32)] * 8)
    c2w_nan[3, 0, 3] = np.nan
    c2w_sheared = np.stack([np.asarray(c2w, np.float32)] * 8)
    c2w_sheared[0, :3, :3] *= 2.0
    _write_run(tmp / "near_far_run", near=5.0, far=1.0)
    _write_run(tmp / "nan_pose_run", c2w=c2w_nan)
    _write_run(tmp / "sheared_pose_run", c2w=c2w_sheared)
    _write_run(tmp / "nan_background_run", background=np.array([np.nan, 0.5, 0.5], np.float32))
    _write_run(tmp / "zero_focal_run", intrinsics=Intrinsics.create(16, 16, 0.0))
    _write_run(tmp / "huge_camera_run", intrinsics=Intrinsics.create(100000, 100000, 50000.0))
    _write_run(tmp / "flipped_box_run", aabb=np.array([[1.0, 1.0, 1.0], [-1.0, -1.0, -1.0]], np.float32))
    hdr = np.random.default_rng(1).random((16, 16, 3)).astype(np.float32) * 252  # linear HDR values, not [0, 1]
    iio.imwrite(tmp / "hdr.tiff", hdr)


def _snapshot(folder):
    """{relative path: sha256} of every regular file under folder (FIFOs and links by kind only)."""
    import stat

    out = {}
    for root, dirs, files in os.walk(folder):
        for name in files + dirs:
            path = os.path.join(root, name)
            mode = os.lstat(path).st_mode
            if stat.S_ISREG(mode):
                with open(path, "rb") as f:
                    out[os.path.relpath(path, folder)] = hashlib.sha256(f.read()).hexdigest()
            elif not stat.S_ISDIR(mode):
                out[os.path.relpath(path, folder)] = stat.S_IFMT(mode)
    return out


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    """One folder of inputs for every case (each case checks it leaves the folder byte-identical)."""
    tmp = tmp_path_factory.mktemp("bad_input")
    (tmp / "run").mkdir()
    (tmp / "run" / "keep.txt").write_text("an earlier run")
    _inputs(tmp)
    return tmp


@pytest.mark.parametrize("argv, expected", [pytest.param(a, e, id=i) for i, a, e in CASES])
def test_bad_input_is_one_line_and_changes_nothing(inputs, capsys, argv, expected):
    tmp_path = inputs
    listing = sorted(os.listdir(tmp_path))
    before = _snapshot(tmp_path)
    status = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err.strip()
    assert status == 1, err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("waldo: error: "), err
    assert "Traceback" not in err
    assert expected.replace("{tmp}", str(tmp_path)) in lines[0], lines[0]
    assert _snapshot(tmp_path) == before
    assert sorted(os.listdir(tmp_path)) == listing  # nothing created


def test_a_backend_the_machine_lacks_is_one_line_before_anything_is_created(tmp_path):
    """JAX_PLATFORMS naming a backend this machine cannot start (gpu on a CPU machine) is refused in
    one line, exit 1, before the output folder exists (JAX would raise at its first computation). A
    subprocess: this process's backend has started already."""
    import subprocess
    import sys

    import jax

    missing = "tpu" if jax.default_backend() == "gpu" else "gpu"
    out = tmp_path / "new"
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "waldo_jax",
            "render",
            "procedural",
            "--views",
            "2",
            "--resolution",
            "8",
            "--out",
            str(out),
        ],
        env={**os.environ, "JAX_PLATFORMS": missing},
        capture_output=True,
        text=True,
        timeout=300,
    )
    lines = result.stderr.strip().splitlines()
    assert result.returncode == 1, result.stderr
    assert len(lines) == 1 and lines[0].startswith(
        f"waldo: error: JAX_PLATFORMS={missing}: this machine cannot start that backend"
    ), result.stderr
    assert not out.exists() and os.listdir(tmp_path) == []


def test_demo_refusal_does_not_suggest_a_flag_it_lacks(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("an earlier run")
    assert main(["demo", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "not empty" in err and "--force" not in err


def test_check_seed_bounds():
    assert check_seed(0) == 0 and check_seed(MAX_SEED) == MAX_SEED
    assert check_seed(MAX_SEED - 3, count=4) == MAX_SEED - 3
    for bad, count in ((-1, 1), (MAX_SEED + 1, 1), (MAX_SEED - 2, 4), (True, 1), (1.5, 1)):
        with pytest.raises(WaldoError, match="--seed"):
            check_seed(bad, count=count)


def _one_warning_line(capsys, argv):
    """Runs argv, expects success, returns the stderr lines that are waldo warnings."""
    status = main(argv)
    err = capsys.readouterr().err
    assert status == 0, err
    assert "Traceback" not in err
    return [line for line in err.splitlines() if line.startswith("waldo: warning: ")]


def test_legal_but_surely_wrong_cameras_load_with_a_one_line_warning(tmp_path, capsys):
    """Repeated camera poses and a principal point outside the image load (the files are valid) but
    each says what is wrong in one line."""
    _write_scene(tmp_path / "pp", cx=5000.0)
    warned = _one_warning_line(capsys, ["scene", "info", str(tmp_path / "pp")])
    assert len(warned) == 1 and "principal point (cx, cy) = (5000, 8) lies outside the 16x16 image" in warned[0]

    _write_scene(tmp_path / "same")
    meta = json.loads((tmp_path / "same" / "transforms.json").read_text())
    for frame in meta["frames"]:
        frame["transform_matrix"] = meta["frames"][0]["transform_matrix"]
    (tmp_path / "same" / "transforms.json").write_text(json.dumps(meta))
    warned = _one_warning_line(capsys, ["scene", "info", str(tmp_path / "same")])
    assert len(warned) == 1 and "7 of 8 cameras repeat another camera's pose (1 distinct)" in warned[0]


def test_an_output_folder_that_cannot_be_written_is_refused_before_training(tmp_path, capsys, monkeypatch):
    """A read-only --out is refused before the scene is loaded or anything trained (the suite may run
    as root, where permissions do not bind: the check's os.access answer is simulated)."""
    _write_scene(tmp_path / "scene")
    (tmp_path / "ro").mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode: False if str(p) == str(tmp_path / "ro") else real_access(p, mode))
    import waldo_jax.nerf.runs as runs

    monkeypatch.setattr(runs, "load_splits", lambda *a, **k: pytest.fail("loaded the scene for an unwritable folder"))
    monkeypatch.setattr(runs, "train", lambda *a, **k: pytest.fail("trained into an unwritable folder"))
    for out in (tmp_path / "ro", tmp_path / "ro" / "new"):
        assert main(["train", str(tmp_path / "scene"), "--out", str(out), "--quiet"]) == 1
        err = capsys.readouterr().err.strip()
        assert err == f"waldo: error: {out}: cannot write there: {tmp_path / 'ro'} is not writable (permission denied)"
    assert os.listdir(tmp_path / "ro") == []


@pytest.mark.parametrize("command", ["explore", "path"])
def test_a_bad_criterion_is_refused_before_the_source_loads(tmp_path, capsys, monkeypatch, command):
    """The criterion's text, its guards' ranges, the target image and a method that needs gradients are
    checked before the source (a room to render, a NeRF run to read) is loaded; the room's oracles,
    which need the source, are still built after it."""
    import waldo_jax.cli.explore as cli_explore
    import waldo_jax.cli.path as cli_path

    module = cli_explore if command == "explore" else cli_path
    real_load = module.load_source
    monkeypatch.setattr(module, "load_source", lambda *a, **k: pytest.fail("loaded the source before the criterion"))
    bad = [
        (["--criterion", "weighted:composition"], "bad weight"),
        (["--criterion", "weighted:opacity=1,opacity=2"], "names 'opacity' twice"),
        (["--criterion", "colourfulness"], "unknown criterion 'colourfulness'"),
        (["--criterion", "colorfulness", "--guard", "opacty:0.5"], "unknown criterion 'opacty'"),
        (["--criterion", "colorfulness", "--guard", "opacity:2"], "fails every view"),
        (["--criterion", "waldo", "--target", str(tmp_path / "missing.png")], "missing.png"),
    ]
    if command == "explore":
        bad.append((["--criterion", "niqe", "--method", "egps+refine"], "'niqe' is not differentiable"))
    for flags, message in bad:
        out = tmp_path / "new"
        assert main([command, "procedural", "--out", str(out), *flags]) == 1
        err = capsys.readouterr().err.strip()
        assert message in err and len(err.splitlines()) == 1, (flags, err)
        assert not out.exists()
    # An oracle needs the room: the source loads first and the oracle is built from it (here it is then
    # refused, as its guard's threshold lies outside the guard's range), before any output exists.
    calls = []
    monkeypatch.setattr(module, "load_source", lambda *a, **k: calls.append(a) or real_load(*a, **k))
    assert (
        main(
            [
                command,
                "procedural:1",
                "--out",
                str(tmp_path / "oracle"),
                "--criterion",
                "waldo_oracle",
                "--guard",
                "waldo_visible:2",
            ]
        )
        == 1
    )
    assert calls and "fails every view" in capsys.readouterr().err
    assert not (tmp_path / "oracle").exists()


def test_a_full_disk_leaves_no_half_written_file_and_one_line(tmp_path, capsys, monkeypatch):
    """Every file goes through io.atomic_file: when the disk fills up mid-write, the file being written
    is absent (no 0-byte PNG), earlier files are whole, and the error is one line naming the file."""
    import waldo_jax.io as io_module

    real_open_temp = io_module._open_temp
    written = []

    class FullDisk:
        def __init__(self, f):
            self.f = f

        def write(self, data):
            raise OSError(errno.ENOSPC, "No space left on device", self.f.name)

        def __getattr__(self, name):
            return getattr(self.f, name)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

    def open_temp(path):
        name, f = real_open_temp(path)
        written.append(path.name)
        return (name, FullDisk(f)) if len(written) == 2 else (name, f)  # the second file hits a full disk

    monkeypatch.setattr(io_module, "_open_temp", open_temp)
    out = tmp_path / "views"
    args = ["render", "procedural", "--views", "3", "--resolution", "16", "--samples", "16", "--quiet"]
    status = main([*args, "--out", str(out)])  # --quiet: stderr holds the error alone
    err = capsys.readouterr().err.strip()
    assert status == 1 and len(err.splitlines()) == 1 and "No space left on device" in err, err
    assert "Traceback" not in err
    files = sorted(os.listdir(out))
    assert files == ["view_000.png"], files  # the first view whole; no temporary file, no empty PNG
    assert os.path.getsize(out / "view_000.png") > 0


def test_atomic_file_keeps_the_old_file_when_the_write_fails(tmp_path):
    from waldo_jax import io

    target = tmp_path / "results.json"
    io.write_json(target, {"a": 1})
    with pytest.raises(RuntimeError):
        with io.atomic_file(target) as f:
            f.write(b"half")
            raise RuntimeError("interrupted")
    assert json.loads(target.read_text()) == {"a": 1} and os.listdir(tmp_path) == ["results.json"]
    io.write_json(target, {"nan": float("nan"), "inf": np.float32(np.inf), "x": np.arange(2)})
    assert json.loads(target.read_text()) == {"nan": None, "inf": None, "x": [0, 1]}  # strict JSON


def test_render_force_replaces_an_earlier_render_without_stale_files(tmp_path, capsys):
    out = tmp_path / "views"
    assert main(["render", "procedural", "--views", "3", "--resolution", "8", "--samples", "8", "--out", str(out)]) == 0
    (out / "notes.txt").write_text("mine")
    assert (
        main(
            [
                "render",
                "procedural",
                "--views",
                "2",
                "--resolution",
                "8",
                "--samples",
                "8",
                "--out",
                str(out),
                "--force",
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert sorted(os.listdir(out)) == [
        "contact_sheet.png",
        "notes.txt",
        "room.json",
        "transforms.json",
        "view_000.png",
        "view_001.png",
    ]


def test_a_training_that_diverges_saves_no_run_and_leaves_no_folder(tmp_path, capsys, monkeypatch):
    """A field whose parameters end NaN (a scene's finite but absurd distortion did it) is not saved as a
    run: one line naming the scene, exit status 1, and the output folder the command made is removed (it
    had exited 0 with a checkpoint that every later command refused)."""
    import jax
    import jax.numpy as jnp

    import waldo_jax.nerf.runs as runs

    _write_scene(tmp_path / "scene")
    real_train = runs.train

    def diverging(*args, **kwargs):
        result = real_train(*args, **kwargs)
        return result._replace(params=jax.tree.map(lambda x: x * jnp.nan, result.params))

    monkeypatch.setattr(runs, "train", diverging)
    out = tmp_path / "new"
    argv = ["train", str(tmp_path / "scene"), "--out", str(out), "--steps", "2", "--quiet"]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"waldo: error: {tmp_path / 'scene'}: the training diverged") and "\n" not in err
    assert f"removed the unfinished output folder {out}" in err
    assert not out.exists()


def test_only_waldos_own_warnings_reach_the_user(capsys):
    """The command prints its own warnings, one line each; a library's (matplotlib's "identical low and
    high zlims" on cameras at one height) and NumPy's arithmetic ones (an overflow in a cast, before the
    input check names the input) are left out: they leaked as `waldo: warning:` lines."""
    import matplotlib

    from waldo_jax.cli import _show_warning
    from waldo_jax.scenes import loader

    _show_warning(UserWarning("a waldo note"), UserWarning, loader.__file__, 1)
    _show_warning(UserWarning("identical low and high zlims"), UserWarning, matplotlib.__file__, 1)
    _show_warning(RuntimeWarning("overflow encountered in cast"), RuntimeWarning, loader.__file__, 1)
    assert capsys.readouterr().err == "waldo: warning: a waldo note\n"


def test_a_name_with_control_characters_stays_one_line(tmp_path, capsys):
    """A message quoting a path with a newline or a terminal escape is one line with them escaped, from
    any reader (the CLI writes every error through `errors.one_line`)."""
    odd = tmp_path / "scene\nwith\x1b[31mcolour"
    assert main(["scene", "info", str(odd)]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "\x1b" not in err
    assert "scene\\nwith\\x1b[31mcolour" in err


@pytest.mark.parametrize("name", ["JAX_PLATFORM_NAME", "JAX_DEFAULT_DEVICE"])
def test_a_backend_named_by_any_of_jaxs_variables_is_checked(monkeypatch, name):
    """`JAX_PLATFORM_NAME` / `JAX_DEFAULT_DEVICE=gpu` raised a RuntimeError at the first key: one line
    naming its variable (`JAX_PLATFORMS=cuda`, an AssertionError inside JAX, in tests/test_environment.py)."""
    from waldo_jax.cli import check_jax_platforms

    monkeypatch.setenv(name, "gpu")
    with pytest.raises(WaldoError, match=f"^{name}=gpu: this machine cannot start that backend"):
        check_jax_platforms()


@pytest.mark.parametrize("method, size", [("evosax:Open_ES", 3), ("evosax:DifferentialEvolution", 2)])
def test_an_evosax_population_the_strategy_refuses_is_one_line(tmp_path, capsys, method, size):
    """Mirrored strategies need an even population and DE four: evosax's AssertionError was a traceback."""
    argv = ["explore", "procedural", "--criterion", "colorfulness", "--method", method, "--views", "2"]
    argv += ["--children-per-epoch", str(size), "--epochs", "1", "--top-k", "1", "--resolution", "8"]
    assert main([*argv, "--out", str(tmp_path / "new")]) == 1
    err = capsys.readouterr().err.strip()
    assert f"cannot take a population of {size}" in err and "\n" not in err
    assert not (tmp_path / "new").exists()


def test_a_flag_with_no_effect_says_so_in_one_warning_line(tmp_path):
    """`--target` without the finder, `--weights` without a weighted criterion, a method option with a method
    that has none, `view --force` without `--export`: each was dropped without a word."""
    import warnings

    from waldo_jax.cli import build_parser
    from waldo_jax.cli.explore import explore_config_from_args
    from waldo_jax.cli.flags import criterion_before_source
    from waldo_jax.cli.view import _check

    parser = build_parser()
    target = tmp_path / "t.png"
    io_write = __import__("imageio.v2", fromlist=["imwrite"]).imwrite
    io_write(target, np.zeros((4, 4, 3), np.uint8))

    def said(action):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            action()
        return [str(w.message) for w in caught]

    args = parser.parse_args(
        ["explore", "procedural", "--out", "x", "--criterion", "colorfulness", "--target", str(target)]
    )
    assert said(lambda: criterion_before_source(args)) == [
        "--target has no effect: no criterion named here uses it (it is for waldo)"
    ]
    args = parser.parse_args(["score", "a.png", "--criterion", "opacity", "--weights", "w"])
    (line,) = said(lambda: criterion_before_source(args))
    assert line.startswith("--weights has no effect") and "brisque" in line and "saliency" in line
    args = parser.parse_args(["explore", "procedural", "--out", "x", "--method", "egps", "--top-c", "8"])
    assert said(lambda: explore_config_from_args(args)) == [
        "--top-c 8 has no effect with --method egps (it is for pibs, pibs+refine)"
    ]
    args = parser.parse_args(["explore", "procedural", "--out", "x", "--method", "grs", "--refine-steps", "9"])
    (line,) = said(lambda: explore_config_from_args(args))
    assert line.startswith("--refine-steps 9 has no effect with --method grs (it is for grs+refine, ")
    args = parser.parse_args(["view", "procedural", "--force", "--port", "0"])
    assert said(lambda: _check(args)) == [
        "--force has no effect without --export (it overwrites an existing FILE.html)"
    ]
    # The flags a method does take, and the finder's target, say nothing.
    for argv in (
        ["explore", "procedural", "--out", "x", "--method", "pibs", "--top-c", "8"],
        ["explore", "procedural", "--out", "x", "--method", "egps+refine", "--refine-steps", "9"],
    ):
        assert said(lambda: explore_config_from_args(parser.parse_args(argv))) == []


@pytest.mark.parametrize(
    "kind, says",
    [("folder", "a directory"), ("fifo", "a FIFO, socket or device")],
)
def test_every_json_reader_says_a_file_that_is_no_regular_file_before_reading_it(tmp_path, kind, says):
    """`io.read_json_file`, under every JSON reader (poses files, results.json, summary.json, camera paths):
    a FIFO blocked the read for ever (and /dev/zero, size 0 by its stat, read until memory ran out: not tried
    here, as without the check it would take the machine's memory). Each now ends at the stat, in the
    reader's own error type."""
    from waldo_jax.io import read_json_file

    path = tmp_path / "poses.json"
    path.mkdir() if kind == "folder" else os.mkfifo(path)
    with within(10):
        with pytest.raises(WaldoError, match=f"{path}: {says}, where a poses file was expected"):
            read_json_file(path, "poses file")
        with pytest.raises(ValueError, match=f"^{says}, where an output JSON was expected$"):
            read_json_file(path, "output JSON", error=ValueError)


def test_json_that_could_not_be_held_parsed_is_refused_before_parsing(tmp_path, monkeypatch):
    """A JSON file's objects take up to 24 bytes per byte of text (`[[0],[0],...]`): a 512 MiB file, within
    the size bound, could need 12 GiB, and Linux ends such a process without a MemoryError. Its worst case
    is checked against the free memory first, in the reader's own error type."""
    import waldo_jax.io as wio

    path = tmp_path / "poses.json"
    path.write_text("[" + ",".join(["[0]"] * 100_000) + "]")  # 400 kB: up to 10 MB parsed
    monkeypatch.setattr(wio, "host_memory_bytes", lambda: 4 * 2**20)
    says = r"poses.json: poses file of 0.4 MiB may take up to 0.01 GiB parsed, more than the 0.0 GiB"
    with pytest.raises(WaldoError, match=says):
        wio.read_json_file(path, "poses file")
    monkeypatch.setattr(wio, "host_memory_bytes", lambda: 64 * 2**20)
    assert len(wio.read_json_file(path, "poses file")) == 100_000


@pytest.mark.parametrize(
    "item",
    ["[]", "{}", "[0]", '{"a":1}', '{"a":0.5,"b":[0.5,0.5]}', "0.5", '"abcdefgh"', "[0.5,0.5,0.5,0.5]", "[[[]]]"],
)
def test_the_parsed_json_estimate_is_at_least_what_parsing_takes(item):
    """`io._parsed_bytes`, the bound the memory check uses, against what `json.loads` really allocates
    (tracemalloc) for a list of 20,000 copies of each kind of item."""
    import tracemalloc

    from waldo_jax.io import _parsed_bytes

    text = "[" + ",".join([item] * 20_000) + "]"
    tracemalloc.start()
    try:
        parsed = json.loads(text)
        taken = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert len(parsed) == 20_000
    assert taken <= _parsed_bytes(text.encode()) <= 4 * taken + 2**16

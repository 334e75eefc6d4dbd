"""The sizes the device check's steps use: the GPU's (`FULL`) and the tiny ones of `--smoke` (`SMOKE`).

Plain Python (static, shape-setting); the report records them under `settings`. A new step adds its
sizes here, a `--smoke` value included.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

# The test files that failed on a GPU before (one H100, before the packed renderer): run first.
FAILED_BEFORE = (
    "test_csnet.py",
    "test_cnniqa.py",
    "test_nerf_field.py",
    "test_cameras.py",
    "test_sharding.py",
    "test_train.py",
    "test_occupancy.py",
    "test_scenes.py",
    "test_explore_cli.py",
)


@dataclasses.dataclass(frozen=True)
class Settings:
    """Every size the steps use (plain Python: static, shape-setting)."""

    fox: str = "scenes/fox"
    fox_downscale: float = 4.0  # 270x480 training images: the GPU's; the CPU runs used 8
    train_preset: str = "quality"
    train_steps: int = 1000
    train_overrides: tuple = ()  # (name, value) pairs given to TrainConfig.preset
    pytest_first: tuple = tuple(f"tests/{name}" for name in FAILED_BEFORE)
    pytest_rest: Optional[tuple] = None  # None: every other test file
    pytest_workers: int = 8
    determinism_args: tuple = ("procedural:0", "--resolution", "64", "--criterion", "saliency", "--budget", "low")
    render_poses: int = 16
    render_size: str = "144x256"
    render_repeats: int = 3
    population_poses: int = 256
    population_resolutions: tuple = (64, 128, 256)
    population_samples: int = 64
    population_repeats: int = 3
    explore_resolutions: tuple = (256, 455)  # the fox is portrait: 144x256 and 256x455 (shorter side 256)
    explore_args: tuple = ("--criterion", "saliency", "--method", "egps", "--budget", "low")
    gradient_cases: tuple = ("procedural:waldo_oracle", "procedural:saliency", "RUN:saliency")
    gradient_resolution: int = 64
    gradient_poses: int = 4
    gradient_repeats: int = 5
    # The splat renderer (issue [2/5]): the GPU targets' cells, then the donut explored.
    splats_args: tuple = (
        "--counts",
        "100000,1000000",
        "--sizes",
        "128,256",
        "--populations",
        "256",
        "--repeats",
        "3",
        "--max-seconds-per-cell",
        "60",
    )
    splats_explore_args: tuple = (
        "--resolution",
        "128",
        "--criterion",
        "saliency",
        "--method",
        "egps+refine",
        "--budget",
        "low",
    )


FULL = Settings()
SMOKE = Settings(
    fox_downscale=16.0,
    train_steps=48,
    train_overrides=(
        ("samples_per_batch", 2**12),
        ("rays_per_batch", 2**10),
        ("chunk", 16),
        ("occupancy_resolution", 32),
        ("occupancy_warmup", 16),
        ("eval_samples", 128),
        ("render_step_scale", 1.0),
        ("hashgrid", {"L": 8, "T": 2**14}),
    ),
    pytest_first=("tests/test_cameras.py::test_look_at_identity_frame",),
    pytest_rest=("tests/test_device_check.py::test_time_left_by_a_step_goes_to_the_later_ones",),
    pytest_workers=0,
    determinism_args=(
        "procedural:0",
        "--resolution",
        "16",
        "--views",
        "8",
        "--epochs",
        "2",
        "--children-per-epoch",
        "6",
        "--criterion",
        "colorfulness",
    ),
    render_poses=2,
    render_size="24x32",
    render_repeats=1,
    population_poses=2,
    population_resolutions=(16,),
    population_samples=16,
    population_repeats=1,
    explore_resolutions=(32,),
    explore_args=("--criterion", "colorfulness", "--method", "egps", "--epochs", "2", "--children-per-epoch", "4"),
    gradient_cases=("RUN:colorfulness",),
    gradient_resolution=16,
    gradient_poses=2,
    gradient_repeats=1,
    splats_args=("--quick", "--populations", "2"),
    splats_explore_args=(
        "--resolution",
        "16",
        "--criterion",
        "colorfulness",
        "--method",
        "egps+refine",
        "--epochs",
        "2",
        "--children-per-epoch",
        "6",
        "--refine-poses",
        "2",
        "--refine-steps",
        "1",
    ),
)

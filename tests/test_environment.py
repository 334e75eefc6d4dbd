"""Environment variables read by waldo_jax, JAX and XLA: a bad value is one line naming it, before JAX
starts (`waldo_jax.environment`), through the `waldo` command and the library's import."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from waldo_jax.environment import (
    EnvironmentVariableError,
    VARIABLES,
    check_environment,
    COMPILE_CACHE_MAX_BYTES,
    compile_cache_folder,
    environment_problems,
    prune_compile_cache,
    xla_flag_known,
    xla_flags_refused,
)

# One bad value per kind of check, each named by the error (the JAX_* ones refused by JAX's own import).
BAD = [
    ("JAX_DEFAULT_MATMUL_PRECISION", "banana"),
    ("JAX_ENABLE_X64", "banana"),
    ("JAX_TRACEBACK_FILTERING", "banana"),
    ("XLA_FLAGS", "--banana"),
    ("XLA_FLAGS", "banana"),
    ("XLA_FLAGS", "--xla_force_host_platform_device_count=banana"),  # a known flag, a value XLA cannot read
    ("XLA_FLAGS", "--xla_cpu_disable_loop_unrolling=true"),  # a string in jaxlib's library, not a flag
    ("XLA_PYTHON_CLIENT_MEM_FRACTION", "2"),
    ("XLA_PYTHON_CLIENT_ALLOCATOR", "banana"),
    ("XLA_PYTHON_CLIENT_PREALLOCATE", "banana"),
    ("TF_CPP_MIN_LOG_LEVEL", "9"),
    ("TF_CPP_MAX_VLOG_LEVEL", "x"),
    ("CUDA_VISIBLE_DEVICES", "banana"),
    ("JAX_PLATFORMS", "banana"),
    ("WALDO_DATA", "/no/such/folder/for/waldo"),
    ("WALDO_WEIGHTS", "/no/such/folder/for/waldo"),
    ("WALDO_REQUIRE_DATA", "banana"),
    ("WALDO_DETERMINISTIC", "banana"),
    ("WALDO_FAST_COMPILE", "banana"),
    ("WALDO_CPU_DEVICES", "0"),
    ("WALDO_COMPILE_CACHE", "/etc/passwd"),  # a file: not a folder for the cache
    ("JAX_COMPILATION_CACHE_DIR", "/etc/passwd"),
    # Kinds the names alone let through: digits int() refuses, blank values, JAX modes waldo_jax cannot run
    # under, values XLA reads as the right type but cannot use, folders whose permission bits lie (root, /proc).
    ("TF_CPP_MIN_LOG_LEVEL", "--1"),
    ("WALDO_CPU_DEVICES", "²"),
    ("JAX_PLATFORMS", " "),
    ("JAX_PLATFORM_NAME", "banana"),
    ("JAX_DEFAULT_DEVICE", "banana"),  # had been refused in JAX's words, after it had started
    ("MPLBACKEND", "banana"),  # Matplotlib refused it at the first figure: a traceback after the whole search
    ("JAX_NUM_CPU_DEVICES", "-5"),
    ("JAX_ENABLE_X64", "1"),
    ("JAX_ENABLE_X64", "t"),  # JAX's own other words for on: "t" and "y" (they got past, and crashed a search)
    ("JAX_DEBUG_INFS", "y"),
    ("JAX_DEBUG_INFS", "1"),
    ("JAX_DEBUG_NANS", "1"),  # a training chunk's scan and a splat search's finish ended in FloatingPointError
    ("JAX_DISABLE_JIT", "1"),  # a 1-view render of 8x8 pixels took 18 s
    ("JAX_DEFAULT_PRNG_IMPL", "rbg"),  # procedural:0 became another room, exit 0
    ("JAX_THREEFRY_PARTITIONABLE", "0"),
    ("JAX_NUMPY_RANK_PROMOTION", "raise"),  # JAX's own broadcasting error from inside a search, no variable named
    ("XLA_FLAGS", "--xla_force_host_platform_device_count=0"),
    ("XLA_FLAGS", "--xla_backend_optimization_level=99"),
    # Values XLA reads and then cannot compile with: aborts (a check failure, an LLVM option) or an internal error.
    ("XLA_FLAGS", "--xla_disable_all_hlo_passes=true"),
    ("XLA_FLAGS", "--xla_backend_extra_options=--bogus"),
    ("XLA_FLAGS", "--xla_dump_to=/proc/waldo_dump"),
    ("JAX_COMPILATION_CACHE_DIR", "/proc/waldo_cache"),
]


def _run(env_update, *args):
    env = {**os.environ, **env_update}
    return subprocess.run(
        [sys.executable, "-m", "waldo_jax", *args], env=env, capture_output=True, text=True, timeout=300
    )


@pytest.mark.slow
def test_a_backend_jax_fails_to_start_by_an_assertion_is_one_line(tmp_path):
    """`JAX_PLATFORMS=cuda` on a machine without one: JAX fails with a bare AssertionError, which was a traceback."""
    result = _run({"JAX_PLATFORMS": "cuda"}, "render", "procedural", "--views", "1", "--out", str(tmp_path / "new"))
    assert result.returncode == 1, result.stderr[-2000:]
    assert result.stderr.strip().splitlines()[-1].startswith("waldo: error: JAX_PLATFORMS=cuda: this machine cannot")
    assert "Traceback" not in result.stderr and not (tmp_path / "new").exists()


@pytest.mark.slow
@pytest.mark.parametrize("name,value", BAD, ids=[f"{n}={v}" for n, v in BAD])
def test_a_bad_value_is_one_line_naming_it_from_the_command(name, value):
    result = _run({name: value}, "--help")
    assert result.returncode == 1, (result.returncode, result.stderr[-2000:])
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("waldo: error: environment variable "), result.stderr[-2000:]
    assert f"{name}=" in lines[0], lines[0]
    assert "Traceback" not in result.stderr


# JAX's strict modes, refused in-process (one of them, rank promotion, from the command in BAD too).
STRICT_MODES = [
    ("JAX_NUMPY_RANK_PROMOTION", "raise"),
    ("JAX_NUMPY_DTYPE_PROMOTION", "Strict"),
    ("JAX_TRANSFER_GUARD", "disallow"),
    ("JAX_TRANSFER_GUARD_HOST_TO_DEVICE", "disallow_explicit"),
    ("JAX_TRANSFER_GUARD_DEVICE_TO_HOST", "disallow"),
    ("JAX_TRANSFER_GUARD_DEVICE_TO_DEVICE", "disallow"),
]


def test_jax_strict_modes_waldo_jax_does_not_meet_are_refused_by_name():
    """Rank and dtype strictness and the transfer guard each ended a search in JAX's own error or a traceback."""
    for name, value in STRICT_MODES:
        (problem,) = environment_problems({name: value})
        assert problem.startswith(f"{name}={value}"), problem
    for name, value in (("JAX_NUMPY_RANK_PROMOTION", "allow"), ("JAX_TRANSFER_GUARD", "log")):
        assert environment_problems({name: value}) == []


@pytest.mark.slow
def test_good_values_pass_and_the_command_runs():
    good = {
        "XLA_FLAGS": "--xla_force_host_platform_device_count=2 --xla_cpu_use_fusion_emitters=false",
        "JAX_PLATFORMS": "cpu",
        "TF_CPP_MIN_LOG_LEVEL": "2",
        "XLA_PYTHON_CLIENT_MEM_FRACTION": ".5",
        "WALDO_DETERMINISTIC": "1",
        "CUDA_VISIBLE_DEVICES": "",
        "JAX_NUMPY_RANK_PROMOTION": "warn",
        "JAX_NUMPY_DTYPE_PROMOTION": "standard",
    }
    assert environment_problems(good) == []
    result = _run(good, "--help")
    assert result.returncode == 0, result.stderr[-2000:]


def test_every_variable_in_the_table_is_checked():
    for name, _ in VARIABLES.items():
        assert name in {n for n, _ in BAD + STRICT_MODES} or name in ("CUDA_VISIBLE_DEVICES",), name


def test_check_environment_names_each_problem():
    with pytest.raises(EnvironmentVariableError, match=r"and 1 more") as raised:
        check_environment({"XLA_FLAGS": "--banana", "WALDO_FAST_COMPILE": "x"})
    assert "XLA_FLAGS=--banana" in str(raised.value) and "WALDO_FAST_COMPILE=x" in str(raised.value)
    check_environment({})  # nothing set: nothing to refuse


def test_xla_itself_refuses_what_the_names_let_through_and_the_answer_is_cached(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    good, unknown, unreadable = (
        "--xla_cpu_use_fusion_emitters=false --xla_force_host_platform_device_count=2",
        "--xla_cpu_disable_loop_unrolling=true",
        "--xla_force_host_platform_device_count=banana",
    )
    assert xla_flags_refused(good) is None
    assert "is no flag this jaxlib knows" in xla_flags_refused(unknown)
    assert "cannot read the value 'banana'" in xla_flags_refused(unreadable)
    import subprocess

    def no_child(*args, **kwargs):
        raise AssertionError("asked XLA again")

    monkeypatch.setattr(subprocess, "run", no_child)  # cached: no child process the second time
    assert xla_flags_refused(good) is None and xla_flags_refused(unreadable).startswith("--xla_force_host")


def test_xla_flags_are_read_from_jaxlib_itself(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert xla_flag_known("xla_dump_to")  # not in waldo_jax's own list: found in the library
    assert not xla_flag_known("xla_no_such_flag_at_all")
    assert (tmp_path / "waldo_jax" / "xla_flags.json").is_file()  # the answers are cached
    assert not xla_flag_known("xla_no_such_flag_at_all")


# ----------------------------------------------------------------------------------------------
# The `waldo` command's persistent compilation cache (`WALDO_COMPILE_CACHE`).


def test_compile_cache_folder_default_off_path_and_jaxs_own(tmp_path):
    default = tmp_path / "xdg" / "waldo_jax" / "jax_cache"
    assert compile_cache_folder({"XDG_CACHE_HOME": str(tmp_path / "xdg")}) == default
    assert compile_cache_folder({"XDG_CACHE_HOME": str(tmp_path / "xdg"), "WALDO_COMPILE_CACHE": "on"}) == default
    assert compile_cache_folder({"WALDO_COMPILE_CACHE": "off"}) is None
    assert compile_cache_folder({"WALDO_COMPILE_CACHE": str(tmp_path / "c")}) == tmp_path / "c"
    # JAX's own variable set: JAX caches there, waldo_jax adds nothing.
    assert compile_cache_folder({"JAX_COMPILATION_CACHE_DIR": str(tmp_path), "WALDO_COMPILE_CACHE": "on"}) is None
    # A folder to be made is fine where its nearest existing parent is a folder; under a file it is not.
    assert environment_problems({"WALDO_COMPILE_CACHE": str(tmp_path / "new" / "deeper")}) == []
    (tmp_path / "file").write_text("x")
    (problem,) = environment_problems({"WALDO_COMPILE_CACHE": str(tmp_path / "file" / "below")})
    assert problem.startswith("WALDO_COMPILE_CACHE=") and "not a writable folder" in problem


def test_prune_compile_cache_removes_the_oldest_programs_past_the_bound(tmp_path):
    sizes = {"a": 300, "b": 200, "c": 100, "d": 50}  # oldest first
    for age, (key, size) in enumerate(sizes.items()):
        (tmp_path / f"{key}-cache").write_bytes(b"x" * size)
        os.utime(tmp_path / f"{key}-cache", (1000 + age, 1000 + age))
    (tmp_path / "a-atime").write_bytes((5000 * 10**9).to_bytes(8, "little"))  # read last (JAX's own record)
    (tmp_path / "b-atime").write_bytes(b"")  # unreadable record: the file's times decide
    (tmp_path / ".lockfile").write_text("")  # not a program: kept, not counted
    assert prune_compile_cache(tmp_path, 10_000) == 0  # under the bound: nothing goes
    assert prune_compile_cache(tmp_path, 400) == 2  # b, then c (a was read last): 650 -> 350 bytes
    assert sorted(p.name for p in tmp_path.iterdir()) == [".lockfile", "a-atime", "a-cache", "d-cache"]
    assert prune_compile_cache(tmp_path / "missing", 0) == 0  # no folder: nothing to do, no error


def _score(tmp_path, env_update, image):
    # Without the suite's own cache and its 0.2 s threshold (tests/conftest.py): the command's defaults.
    unset = ("JAX_COMPILATION_CACHE_DIR", "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS")
    env = {k: v for k, v in os.environ.items() if k not in unset}
    env.update({"XDG_CACHE_HOME": str(tmp_path / "xdg"), **env_update})
    argv = [sys.executable, "-m", "waldo_jax", "score", "--criterion", "colorfulness", str(image), "--json"]
    result = subprocess.run(argv, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


@pytest.mark.slow
def test_a_command_fills_the_cache_and_a_rerun_loads_it_with_the_same_result(tmp_path):
    import imageio.v3 as iio
    import numpy as np

    image = tmp_path / "view.png"
    iio.imwrite(image, (np.random.default_rng(0).uniform(size=(24, 32, 3)) * 255).astype(np.uint8))
    cache = tmp_path / "cache"
    first = _score(tmp_path, {"WALDO_COMPILE_CACHE": str(cache)}, image)
    entries = sorted(p.name for p in cache.iterdir())
    assert any(name.endswith("-cache") for name in entries), f"the first run cached no program: {entries}"
    # An old program past the folder's bound (a sparse file: its size, not the disk's) goes at the next start.
    with open(cache / "stale-cache", "wb") as f:
        f.truncate(COMPILE_CACHE_MAX_BYTES + 1)
    os.utime(cache / "stale-cache", (1, 1))
    again = _score(tmp_path, {"WALDO_COMPILE_CACHE": str(cache)}, image)
    assert again == first  # the same scores from the loaded programs
    assert sorted(p.name for p in cache.iterdir()) == entries  # every program found, nothing new; the stale one gone
    # Off: nothing cached, not even in the default folder; on (unset): the default folder.
    _score(tmp_path, {"WALDO_COMPILE_CACHE": "off"}, image)
    assert not (tmp_path / "xdg" / "waldo_jax" / "jax_cache").exists()
    _score(tmp_path, {}, image)
    assert any((tmp_path / "xdg" / "waldo_jax" / "jax_cache").iterdir())

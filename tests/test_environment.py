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
    environment_problems,
    xla_flag_known,
)

# One bad value per kind of check, each named by the error (the JAX_* ones refused by JAX's own import).
BAD = [
    ("JAX_DEFAULT_MATMUL_PRECISION", "banana"),
    ("JAX_ENABLE_X64", "banana"),
    ("JAX_TRACEBACK_FILTERING", "banana"),
    ("XLA_FLAGS", "--banana"),
    ("XLA_FLAGS", "banana"),
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
]


def _run(env_update, *args):
    env = {**os.environ, **env_update}
    return subprocess.run(
        [sys.executable, "-m", "waldo_jax", *args], env=env, capture_output=True, text=True, timeout=300
    )


@pytest.mark.slow
@pytest.mark.parametrize("name,value", BAD, ids=[f"{n}={v}" for n, v in BAD])
def test_a_bad_value_is_one_line_naming_it_from_the_command(name, value):
    result = _run({name: value}, "--help")
    assert result.returncode == 1, (result.returncode, result.stderr[-2000:])
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("waldo: error: environment variable "), result.stderr[-2000:]
    assert f"{name}=" in lines[0], lines[0]
    assert "Traceback" not in result.stderr


@pytest.mark.slow
def test_good_values_pass_and_the_command_runs():
    good = {
        "XLA_FLAGS": "--xla_force_host_platform_device_count=2 --xla_cpu_use_fusion_emitters=false",
        "JAX_PLATFORMS": "cpu",
        "TF_CPP_MIN_LOG_LEVEL": "2",
        "XLA_PYTHON_CLIENT_MEM_FRACTION": ".5",
        "WALDO_DETERMINISTIC": "1",
        "CUDA_VISIBLE_DEVICES": "",
    }
    assert environment_problems(good) == []
    result = _run(good, "--help")
    assert result.returncode == 0, result.stderr[-2000:]


def test_every_variable_in_the_table_is_checked():
    for name, _ in VARIABLES.items():
        assert name in {n for n, _ in BAD} or name in ("CUDA_VISIBLE_DEVICES",), name


def test_check_environment_names_each_problem():
    with pytest.raises(EnvironmentVariableError, match=r"and 1 more") as raised:
        check_environment({"XLA_FLAGS": "--banana", "WALDO_FAST_COMPILE": "x"})
    assert "XLA_FLAGS=--banana" in str(raised.value) and "WALDO_FAST_COMPILE=x" in str(raised.value)
    check_environment({})  # nothing set: nothing to refuse


def test_xla_flags_are_read_from_jaxlib_itself(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert xla_flag_known("xla_dump_to")  # not in waldo_jax's own list: found in the library
    assert not xla_flag_known("xla_no_such_flag_at_all")
    assert (tmp_path / "waldo_jax" / "xla_flags.json").is_file()  # the answers are cached
    assert not xla_flag_known("xla_no_such_flag_at_all")

"""The environment variables that waldo_jax, JAX and XLA read, checked before JAX starts.

A bad value of one of them otherwise ends a run far from its cause: JAX raises a ValueError while it is
imported (`JAX_DEFAULT_MATMUL_PRECISION=banana`, `JAX_ENABLE_X64=banana`), XLA aborts the process with
no Python error at all when `XLA_FLAGS` names a flag it does not know, and a bad
`XLA_PYTHON_CLIENT_MEM_FRACTION` is read only when a GPU starts. `check_environment` reads them all
first and raises `EnvironmentVariableError`, one line naming the variable, its value and what it takes:

  * waldo_jax's own: `WALDO_DATA`, `WALDO_WEIGHTS` (existing folders when set), `WALDO_REQUIRE_DATA`,
    `WALDO_DETERMINISTIC`, `WALDO_FAST_COMPILE` (on / off words), `WALDO_CPU_DEVICES` (1..256),
    `WALDO_COMPILE_CACHE` (on / off or a folder that can be made: `enable_compile_cache`, which the
    `waldo` command runs);
  * XLA's: `XLA_FLAGS` (each `--name` or `--name=value`, every name one this jaxlib knows: the flag
    names are read from its shared library, `xla_flag_known`; then XLA itself parses the whole value in
    a child process, `xla_flags_refused`, which finds the rest: a name the library holds as a string but
    XLA does not take as a flag, a value it cannot read), `XLA_PYTHON_CLIENT_PREALLOCATE`,
    `XLA_PYTHON_CLIENT_MEM_FRACTION`, `XLA_PYTHON_CLIENT_ALLOCATOR`, `TF_CPP_MIN_LOG_LEVEL`,
    `TF_CPP_MAX_VLOG_LEVEL`, `CUDA_VISIBLE_DEVICES`; Matplotlib's `MPLBACKEND` (a backend it knows,
    asked of Matplotlib: it refuses a bad one only at a run's first figure);
  * JAX's: `JAX_PLATFORMS` and `JAX_PLATFORM_NAME` (names from the known platforms), `JAX_DEFAULT_DEVICE`
    (one of them), `JAX_NUM_CPU_DEVICES`, `JAX_COMPILATION_CACHE_DIR` (a folder that exists or can be
    made, tried by making one there; JAX itself only warns at each program it cannot cache),
    `JAX_ENABLE_X64`, `JAX_DEBUG_INFS` and `JAX_DEBUG_NANS`
    (off only: waldo_jax computes in 32 bits and uses infinities and NaNs on purpose), `JAX_DISABLE_JIT` (off only),
    `JAX_DEFAULT_PRNG_IMPL` and `JAX_THREEFRY_PARTITIONABLE` (JAX's defaults only: a seed's draws),
    `JAX_NUMPY_RANK_PROMOTION`, `JAX_NUMPY_DTYPE_PROMOTION` and `JAX_TRANSFER_GUARD*` (not their strict
    modes, which waldo_jax's own programs do not meet) and every `JAX_*` configuration
    variable, which JAX itself checks when it is imported: `import_jax` turns its refusal into the same
    one line.

A value of blanks is refused (JAX and XLA would read it as a name); an empty one is unset. XLA flags
whose values XLA reads by type only are checked for range too (`_XLA_VALUES`: the host device count,
the optimisation level, the dump folder).

`waldo_jax/__init__.py` runs `check_environment` and `import_jax` first of all; the `waldo` command
prints the error as one line and exits 1 (`install_excepthook`).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import mmap
import os
import re
import sys
from pathlib import Path
from typing import Callable, Dict, List, Mapping, Optional, Tuple

from waldo_jax.errors import WaldoError

__all__ = [
    "EnvironmentVariableError",
    "VARIABLES",
    "environment_problems",
    "check_environment",
    "import_jax",
    "COMPILE_CACHE_MAX_BYTES",
    "compile_cache_folder",
    "enable_compile_cache",
    "prune_compile_cache",
    "xla_flag_known",
    "xla_flags_refused",
    "install_excepthook",
]

# JAX's own words for a switch (`jax._src.config.bool_env`): "t" and "y" turn JAX_ENABLE_X64 on as well.
_ON = ("1", "true", "yes", "on", "t", "y")
_OFF = ("0", "false", "no", "off", "f", "n")
# JAX's platform names (`JAX_PLATFORMS`, comma-separated, tried in order).
_PLATFORMS = ("cpu", "gpu", "cuda", "rocm", "tpu", "metal", "neuron", "interpreter")
_ALLOCATORS = ("default", "platform", "bfc", "cuda_async")
_XLA_TOKEN = re.compile(r"--([A-Za-z0-9_]+)(=.*)?")
_CUDA_DEVICE = re.compile(r"(-?\d+|GPU-[0-9A-Fa-f-]+|MIG-[0-9A-Za-z/-]+)")
# Flags known without reading jaxlib: those waldo_jax adds itself (`waldo_jax._xla_flags`).
_KNOWN_XLA_FLAGS = {
    "xla_cpu_experimental_ynn_fusion_type",
    "xla_gpu_deterministic_ops",
    "xla_gpu_exclude_nondeterministic_ops",
    "xla_cpu_use_fusion_emitters",
    "xla_force_host_platform_device_count",
}


class EnvironmentVariableError(WaldoError, ValueError):
    """An environment variable with a value waldo_jax, JAX or XLA cannot use (named in the message)."""


def _switch(value: str) -> Optional[str]:
    if value.strip().lower() in _ON + _OFF:
        return None
    return f"expected one of {', '.join(_ON + _OFF)}"


def _folder(value: str) -> Optional[str]:
    path = Path(value).expanduser()
    if not path.exists():
        return "no such folder"
    return None if path.is_dir() else "not a folder"


def _fraction(value: str) -> Optional[str]:
    try:
        x = float(value)
    except ValueError:
        return "expected a number in (0, 1]"
    return None if 0.0 < x <= 1.0 else "expected a number in (0, 1]"


_INTEGER = re.compile(r"[+-]?[0-9]+")  # ASCII digits only: str.isdigit() also takes '²' and '٣', int() not all


def _integer(value: str, low: int, high: int, also: Tuple[int, ...] = ()) -> Optional[str]:
    """None for a whole number in [low, high] (or one of `also`), else what it takes."""
    v = value.strip()
    if _INTEGER.fullmatch(v) and (low <= int(v) <= high or int(v) in also):
        return None
    return f"expected an integer {low}..{high}" + "".join(f" or {a}" for a in also)


def _level(value: str, top: int) -> Optional[str]:
    return _integer(value, 0, top)


def _off_only(why: str) -> Callable[[str], Optional[str]]:
    """A JAX switch waldo_jax cannot run under: an off word (or JAX's own check of the rest) only."""

    def check(value: str) -> Optional[str]:
        v = value.strip().lower()
        return None if v in _OFF or v not in _ON else why

    return check


def _refuse(*values: str, why: str) -> Callable[[str], Optional[str]]:
    """A JAX setting whose `values` waldo_jax cannot run under (JAX itself checks that the rest are its words)."""

    def check(value: str) -> Optional[str]:
        return why if value.strip().lower() in values else None

    return check


def _platforms(value: str) -> Optional[str]:
    names = [p.strip().lower() for p in value.split(",") if p.strip()]
    unknown = [p for p in names if p not in _PLATFORMS]
    if not names or unknown:
        return f"unknown platform {', '.join(unknown) or repr(value)} (known: {', '.join(_PLATFORMS)})"
    return None


def _platform(value: str) -> Optional[str]:
    """One platform name (`JAX_DEFAULT_DEVICE`: JAX takes a name there, not a list)."""
    name = value.strip().lower()
    return None if name in _PLATFORMS else f"unknown platform {value!r} (known: {', '.join(_PLATFORMS)})"


def _mpl_backend(value: str) -> Optional[str]:
    """A backend Matplotlib takes (it reads `MPLBACKEND` when imported, and refuses a bad one only then:
    after a search, at its first figure). Asked of Matplotlib itself, which is imported only to ask."""
    try:
        from matplotlib import rcsetup  # importing matplotlib reads MPLBACKEND: a bad one raises here

        rcsetup.validate_backend(value)
    except ImportError:  # pragma: no cover - matplotlib is a dependency
        return None
    except ValueError:
        return "not a backend Matplotlib knows (agg draws without a display; unset it for Matplotlib's choice)"
    return None


def _cuda_devices(value: str) -> Optional[str]:
    items = [v.strip() for v in value.split(",")]
    if value.strip() == "" or all(_CUDA_DEVICE.fullmatch(v) for v in items):
        return None
    return "expected comma-separated device indices or GPU-/MIG- UUIDs"


def _xla_flags(value: str) -> Optional[str]:
    tokens = value.split()
    bad = [t for t in tokens if not _XLA_TOKEN.fullmatch(t)]
    if bad:
        return f"{bad[0]!r} is not --name or --name=value"
    unknown = [t for t in tokens if not xla_flag_known(_XLA_TOKEN.fullmatch(t).group(1))]
    if unknown:
        return f"{unknown[0]} is no flag this jaxlib knows: XLA would abort the process"
    for token in tokens:
        name, given = _XLA_TOKEN.fullmatch(token).groups()
        if name in _XLA_VALUES and given is not None:
            why = _XLA_VALUES[name](given[1:])
            if why:
                return f"--{name}={given[1:]}: {why}"
    return xla_flags_refused(value) if tokens else None


def _compile_cache(value: str) -> Optional[str]:
    """An on / off word, or a folder that exists or can be made (`_writable_folder`)."""
    return None if value.strip().lower() in _ON + _OFF else _writable_folder(value)


def _writable_folder(value: str) -> Optional[str]:
    """A writable folder, or one that can be made (its nearest existing parent a writable folder). Tried by
    making and removing a folder there: permission bits alone pass /proc and /sys for root."""
    import tempfile

    path = Path(value).expanduser()
    if path.exists() and not path.is_dir():
        return "not a writable folder"
    parent = path
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        return f"cannot be made ({parent} is not a writable folder)"
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".waldo_probe_", dir=parent))
    except OSError as e:
        return "not a writable folder" if parent == path else f"cannot be made in {parent} ({e.strerror or e})"
    return None


# Values of XLA flags that XLA takes but the process cannot run with (XLA itself parses only their type).
_XLA_VALUES: Dict[str, Callable[[str], Optional[str]]] = {
    "xla_force_host_platform_device_count": lambda v: _integer(v, 1, 256),
    "xla_backend_optimization_level": lambda v: _integer(v, 0, 3),
    "xla_dump_to": lambda v: None if v in ("-", "sponge") else _writable_folder(v),
}


# name -> (check of a set value: None or the problem, what it takes)
VARIABLES: Dict[str, Tuple[Callable[[str], Optional[str]], str]] = {
    "WALDO_DATA": (_folder, "the data folder, ../shared's layout"),
    "WALDO_WEIGHTS": (_folder, "the weights folder"),
    "WALDO_REQUIRE_DATA": (_switch, "a missing data file fails instead of skipping"),
    "WALDO_DETERMINISTIC": (_switch, "deterministic GPU kernels, default on"),
    "WALDO_FAST_COMPILE": (_switch, "faster XLA:CPU compiles, default off"),
    "WALDO_CPU_DEVICES": (
        lambda v: _integer(v, 1, 256),
        "the CPU devices XLA makes, default the usable cores up to 8",
    ),
    "WALDO_COMPILE_CACHE": (_compile_cache, "the `waldo` command's compilation cache: on, off or a folder"),
    "XLA_FLAGS": (_xla_flags, "XLA's flags"),
    "XLA_PYTHON_CLIENT_PREALLOCATE": (_switch, "preallocate GPU memory"),
    "XLA_PYTHON_CLIENT_MEM_FRACTION": (_fraction, "the share of GPU memory to preallocate"),
    "XLA_PYTHON_CLIENT_ALLOCATOR": (
        lambda v: None if v.strip() in _ALLOCATORS else f"expected one of {', '.join(_ALLOCATORS)}",
        "the GPU allocator",
    ),
    "TF_CPP_MIN_LOG_LEVEL": (lambda v: _level(v, 3), "XLA's log level"),
    "TF_CPP_MAX_VLOG_LEVEL": (lambda v: _level(v, 10), "XLA's verbose log level"),
    "CUDA_VISIBLE_DEVICES": (_cuda_devices, "the GPUs JAX may use"),
    "MPLBACKEND": (_mpl_backend, "the backend Matplotlib draws the figures with"),
    "JAX_PLATFORMS": (_platforms, "the backends JAX may start"),
    "JAX_PLATFORM_NAME": (_platforms, "the backend JAX starts (deprecated for JAX_PLATFORMS)"),
    "JAX_DEFAULT_DEVICE": (_platform, "the backend JAX puts arrays on by default"),
    "JAX_NUM_CPU_DEVICES": (lambda v: _integer(v, 1, 256, also=(-1,)), "the CPU devices JAX makes"),
    "JAX_COMPILATION_CACHE_DIR": (_writable_folder, "JAX's persistent compilation cache"),
    "JAX_ENABLE_X64": (
        _off_only("waldo_jax computes in 32 bits (indices and results assume it): unset it or set it to 0"),
        "64-bit types by default",
    ),
    "JAX_DEBUG_INFS": (
        _off_only("the searches use infinities on purpose (the fitness of unusable slots): unset it"),
        "stop at the first infinity",
    ),
    "JAX_DEBUG_NANS": (
        _off_only(
            "waldo_jax keeps failures as NaN inside its compiled programs on purpose (a failed view's score, "
            "a ray that hits nothing): unset it"
        ),
        "stop at the first NaN",
    ),
    "JAX_DISABLE_JIT": (
        _off_only("every search, render and training step is one compiled program: without jit a run takes hours"),
        "run without compiling",
    ),
    # JAX's strict modes for user code: waldo_jax's own programs broadcast ranks, promote int32 with float32 and
    # move arrays between host and device, so these end a run in JAX's error far from the variable.
    "JAX_NUMPY_RANK_PROMOTION": (
        _refuse("raise", why="waldo_jax broadcasts arrays of different ranks: unset it or set it to allow"),
        "NumPy-style rank promotion",
    ),
    "JAX_NUMPY_DTYPE_PROMOTION": (
        _refuse("strict", why="waldo_jax mixes integer and float arrays: unset it or set it to standard"),
        "implicit dtype promotion",
    ),
    **{
        name: (
            _refuse("disallow", "disallow_explicit", why="waldo_jax moves arrays to and from the device: unset it"),
            "JAX's transfer guard",
        )
        for name in (
            "JAX_TRANSFER_GUARD",
            "JAX_TRANSFER_GUARD_HOST_TO_DEVICE",
            "JAX_TRANSFER_GUARD_DEVICE_TO_HOST",
            "JAX_TRANSFER_GUARD_DEVICE_TO_DEVICE",
        )
    },
    # JAX modes that change what a seed draws: the same seed would build another room and search otherwise.
    "JAX_DEFAULT_PRNG_IMPL": (
        lambda v: (
            None
            if v.strip().lower() == "threefry2x32"
            else "a seed fixes a run bit for bit with threefry2x32, JAX's default, only: unset it"
        ),
        "JAX's random number generator",
    ),
    "JAX_THREEFRY_PARTITIONABLE": (
        lambda v: (
            None
            if v.strip().lower() in _ON
            else "a seed's draws are waldo_jax's with JAX's default (on) only: unset it"
        ),
        "JAX's sharding-invariant threefry",
    ),
}


def environment_problems(environ: Optional[Mapping[str, str]] = None) -> List[str]:
    """One line per variable of `VARIABLES` set to a value it cannot take (`NAME=VALUE: why`)."""
    environ = os.environ if environ is None else environ
    problems = []
    for name, (check, what) in VARIABLES.items():
        value = environ.get(name)
        if value is None or value == "" or name == "CUDA_VISIBLE_DEVICES" and value.strip() == "":
            continue  # empty is unset for these (as JAX and XLA read them); CUDA's blank hides every GPU
        why = check(value) if value.strip() else "blank (unset it, or give a value)"
        if why:
            shown = value if len(value) <= 80 else value[:77] + "..."
            problems.append(f"{name}={shown} ({what}): {why}")
    return problems


def check_environment(environ: Optional[Mapping[str, str]] = None) -> None:
    """Raises `EnvironmentVariableError` naming the first bad variable (see the module docstring)."""
    problems = environment_problems(environ)
    if problems:
        more = f" (and {len(problems) - 1} more: {'; '.join(problems[1:])})" if len(problems) > 1 else ""
        raise EnvironmentVariableError(f"environment variable {problems[0]}{more}")


def import_jax():
    """Imports JAX; a refusal of one of its `JAX_*` variables becomes an `EnvironmentVariableError`
    naming that variable (JAX reads and checks them all on import)."""
    try:
        import jax
    except (ValueError, TypeError) as e:
        message = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        named = [
            n for n in sorted(os.environ) if n.startswith("JAX_") and (n in message or n.lower() in message.lower())
        ]
        where = f"environment variable {named[0]}={os.environ[named[0]]}: " if named else ""
        set_ = ", ".join(n for n in sorted(os.environ) if n.startswith("JAX_"))
        raise EnvironmentVariableError(
            f"{where}JAX refuses it ({message[:200]})" + ("" if named else f"; JAX variables set: {set_ or 'none'}")
        ) from None
    return jax


# The compilation cache's size bound (the oldest programs are removed past it, once per process:
# `prune_compile_cache`): the demo writes about 4 MB, an explore of a NeRF tens of MB.
COMPILE_CACHE_MAX_BYTES = 2**30
# JAX's cache files: the program, and the time it was last read (JAX writes it while it evicts itself).
_CACHE_SUFFIX, _ATIME_SUFFIX = "-cache", "-atime"


def compile_cache_folder(environ: Optional[Mapping[str, str]] = None) -> Optional[Path]:
    """The folder of the `waldo` command's persistent compilation cache, or None for none.

    `WALDO_COMPILE_CACHE`: unset or an on word, `$XDG_CACHE_HOME/waldo_jax/jax_cache` (default
    `~/.cache/...`); an off word, none; anything else, that folder. None as well when JAX's own
    `JAX_COMPILATION_CACHE_DIR` is set: JAX then caches there itself.
    """
    environ = os.environ if environ is None else environ
    value = environ.get("WALDO_COMPILE_CACHE", "").strip()
    if environ.get("JAX_COMPILATION_CACHE_DIR", "").strip() or value.lower() in _OFF:
        return None
    if value and value.lower() not in _ON:
        return Path(value).expanduser()
    base = environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "waldo_jax" / "jax_cache"


def enable_compile_cache(environ: Optional[Mapping[str, str]] = None) -> Optional[Path]:
    """Turns on JAX's persistent compilation cache in `compile_cache_folder` for this process; returns the
    folder (None: off, or left to JAX_COMPILATION_CACHE_DIR).

    A command run again, or another with programs of the same shapes, loads XLA's compiled programs
    instead of compiling them again (the results are the same: the cache key covers the program, the
    XLA flags, the jaxlib version and the device). Every program is cached, however short its compile
    (`JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS`, when set, decides instead), and the folder is bounded
    by `COMPILE_CACHE_MAX_BYTES`, pruned here once (`prune_compile_cache`): JAX's own bound lists the
    folder and reads every program's last-read record before each program it writes (a small program
    took 84-95 ms into a folder of 1,200 that way, 28-33 ms pruned once: `benchmarks/compile_cache_writes.py`
    on the 2-core CPU). Where `JAX_COMPILATION_CACHE_MAX_SIZE` is set, JAX bounds the folder itself, as it
    says. Call it before the process's first compilation (JAX decides once whether it caches). A
    default folder that cannot be made is a warning (the command runs without the cache); a folder
    named in `WALDO_COMPILE_CACHE` that cannot be, an `EnvironmentVariableError`.
    """
    environ = os.environ if environ is None else environ
    folder = compile_cache_folder(environ)
    if folder is None:
        return None
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        why = f"cannot make {folder} ({e.strerror or e})"
        if environ.get("WALDO_COMPILE_CACHE", "").strip().lower() not in ("",) + _ON:
            raise EnvironmentVariableError(f"environment variable WALDO_COMPILE_CACHE: {why}") from None
        import warnings

        warnings.warn(f"no compilation cache: {why}; set WALDO_COMPILE_CACHE to a writable folder, or to off")
        return None
    jax = import_jax()
    jax.config.update("jax_compilation_cache_dir", str(folder))
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    if "JAX_COMPILATION_CACHE_MAX_SIZE" not in environ:
        prune_compile_cache(folder, COMPILE_CACHE_MAX_BYTES)
        jax.config.update("jax_compilation_cache_max_size", -1)  # no bound of JAX's: pruned above
    return folder


def prune_compile_cache(folder: Path, max_bytes: int) -> int:
    """Removes the oldest programs from the compilation cache `folder` until its programs take at most
    `max_bytes`; returns how many were removed.

    A program's age is the later of its file's modification and access times and the read time JAX
    records beside it (`<key>-atime`, where JAX evicted itself before), so programs still loaded stay
    longest. Files that vanish meanwhile (another process pruning) or cannot be removed are skipped:
    the cache is an optimisation, never a reason to fail.
    """
    entries, total = [], 0
    try:
        paths = list(Path(folder).glob(f"*{_CACHE_SUFFIX}"))
    except OSError:
        return 0
    for path in paths:
        try:
            st = path.stat()
        except OSError:
            continue
        entries.append((max(st.st_mtime_ns, st.st_atime_ns), path, st.st_size))
        total += st.st_size
    if total <= max_bytes:  # the usual case: the read records are not opened
        return 0
    aged = []
    for used, path, size in entries:
        atime_path = path.with_name(path.name[: -len(_CACHE_SUFFIX)] + _ATIME_SUFFIX)
        try:
            used = max(used, int.from_bytes(atime_path.read_bytes()[:8], "little"))
        except (OSError, ValueError):
            pass
        aged.append((used, path, atime_path, size))
    removed = 0
    for _, path, atime_path, size in sorted(aged, key=lambda e: (e[0], e[1].name)):
        if total <= max_bytes:
            break
        try:
            path.unlink()
        except OSError:
            continue
        try:
            atime_path.unlink(missing_ok=True)
        except OSError:
            pass
        total -= size
        removed += 1
    return removed


def _jaxlib_libraries() -> List[Path]:
    """jaxlib's shared libraries and those of installed JAX plugins (CUDA, ROCm)."""
    found = []
    for package in ("jaxlib", "jax_plugins"):
        spec = importlib.util.find_spec(package)
        for folder in (spec.submodule_search_locations or []) if spec else []:
            found += [p for p in Path(folder).rglob("*.so") if p.stat().st_size > 10_000_000]
    return sorted(found)


def _cache_file() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "waldo_jax" / "xla_flags.json"


# A child process that starts XLA's CPU client with the XLA_FLAGS to check: XLA parses every flag there
# and aborts on one it does not know or a value it cannot read (jaxlib's own client, else JAX's).
# It then compiles and runs a small program: flags XLA reads but cannot work with (no HLO passes at all, a
# code-generation split count of 0, options LLVM does not know) fail only there, aborting the process.
_PROBE = """
import jax
import jax.numpy as jnp
jax.jit(lambda x: jnp.sum(x * 2.0 + 1.0))(jnp.arange(8.0)).block_until_ready()
jax.random.uniform(jax.random.key(0), (4,)).block_until_ready()  # constant arrays, as every random draw has
"""
# The line of a failed probe that says why: XLA's check failures, LLVM's and its flag parser's errors,
# else the last line (a Python exception's).
_FAILURE_LINE = re.compile(
    r"(Check failed[^\n]*|Unknown command line argument[^\n]*|Flag parsing failed[^\n]*|[A-Za-z]*Error: [^\n]*|"
    r"terminate called[^\n]*|what\(\):[^\n]*)"
)
_UNKNOWN_FLAG = re.compile(r"Unknown flag in XLA_FLAGS: (\S+)")
_BAD_VALUE = re.compile(r"Couldn't interpret value (.*) for flag (\w+)")


def _read_cache() -> dict:
    """The answers cached for the installed jaxlib libraries (under their "key"; none for others)."""
    libraries = _jaxlib_libraries()
    stamp = hashlib.sha1(
        repr([(str(p), p.stat().st_size, p.stat().st_mtime_ns) for p in libraries] + [_PROBE]).encode()
    )
    key = stamp.hexdigest()[:16]
    cache = _cache_file()
    try:
        known = json.loads(cache.read_text()) if cache.is_file() and cache.stat().st_size < 1_000_000 else {}
        known = known if isinstance(known, dict) and known.get("key") == key else {"key": key}
    except (OSError, ValueError):
        known = {"key": key}
    return known


def _write_cache(known: dict) -> None:
    """Writes the answers whole (a temporary file renamed over the cache: a reader never sees half)."""
    cache = _cache_file()
    try:
        cache.parent.mkdir(parents=True, exist_ok=True)
        partial = cache.with_name(f"{cache.name}.{os.getpid()}.tmp")
        partial.write_text(json.dumps(known))
        os.replace(partial, cache)
    except OSError:
        pass


def xla_flags_refused(value: str) -> Optional[str]:
    """Why XLA would refuse XLA_FLAGS=`value` (it aborts the process on an unknown flag or a value it
    cannot read), or None. XLA itself is asked, in a child process (about half a second; the answer is
    cached per value and jaxlib install); None where the child fails for another reason."""
    import subprocess

    known = _read_cache()
    probed = known.get("probed") if isinstance(known.get("probed"), dict) else {}
    if value in probed and isinstance(probed[value], str):
        return probed[value] or None
    env = {k: v for k, v in os.environ.items() if not k.startswith(("JAX_", "XLA_", "TF_CPP_"))}
    env.update(XLA_FLAGS=value, JAX_PLATFORMS="cpu", TF_CPP_MIN_LOG_LEVEL="0")
    try:
        child = subprocess.run(
            [sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True, timeout=120, errors="replace"
        )
    except (OSError, subprocess.SubprocessError):
        return None
    answer = ""
    if child.returncode != 0:
        unknown, bad = _UNKNOWN_FLAG.search(child.stderr), _BAD_VALUE.search(child.stderr)
        if unknown:
            answer = f"{unknown.group(1)} is no flag this jaxlib knows: XLA would abort the process"
        elif bad:
            answer = f"--{bad.group(2)}: XLA cannot read the value {bad.group(1)[:40]!r} and would abort the process"
        elif _probe_fails(env, without_flags=True):
            return None  # the probe fails without these flags too: nothing learnt about them
        else:
            lines = _FAILURE_LINE.findall(child.stderr)
            why = (lines[-1] if lines else (child.stderr.strip().splitlines() or ["no message"])[-1]).strip()
            answer = f"XLA fails to compile a small program with these flags ({why[:160]}) and would stop the command"
    known = _read_cache()  # again: another process may have written meanwhile
    probed = known.get("probed") if isinstance(known.get("probed"), dict) else {}
    if len(probed) < 256:
        known["probed"] = {**probed, value: answer}
        _write_cache(known)
    return answer or None


def _probe_fails(env: dict, without_flags: bool) -> bool:
    """Whether the probe program fails (in a child process), with `env`'s XLA_FLAGS or without any."""
    import subprocess

    env = {k: v for k, v in env.items() if not (without_flags and k == "XLA_FLAGS")}
    try:
        child = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, timeout=120)
    except (OSError, subprocess.SubprocessError):
        return True
    return child.returncode != 0


def xla_flag_known(name: str) -> bool:
    """Whether `name` (without `--`) is an XLA flag of the installed jaxlib: its name is a string in
    one of jaxlib's shared libraries (where XLA registers its flags). Answers are cached per library
    set; True where no library can be read (nothing to check against)."""
    if name in _KNOWN_XLA_FLAGS:
        return True
    libraries = _jaxlib_libraries()
    if not libraries:
        return True
    known = _read_cache()
    if isinstance(known.get(name), bool):
        return known[name]
    needle = name.encode() + b"\x00"
    answer = False
    try:
        for library in libraries:
            with open(library, "rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
                if m.find(needle) >= 0:
                    answer = True
                    break
    except (OSError, ValueError):
        return True
    known[name] = answer
    _write_cache(known)
    return answer


def install_excepthook() -> None:
    """Uncaught `EnvironmentVariableError`s print as one line (`waldo: error: ...`), exit status 1."""
    previous = sys.excepthook

    def hook(kind, value, traceback):
        if isinstance(value, EnvironmentVariableError):
            print(f"waldo: error: {value}", file=sys.stderr)
            return
        previous(kind, value, traceback)

    if getattr(sys.excepthook, "__name__", "") != "hook" or sys.excepthook.__module__ != __name__:
        sys.excepthook = hook

"""The fields `waldo view` reads from an output folder's JSON, checked by key before anything is drawn.

An output folder is the user's to edit, and a damaged one (a hand-edited results.json, a copy cut short,
a NaN written by another tool) must end in one line naming the file, the key and the value, not in a
TypeError inside the drawing or a frustum silently drawn at NaN. Every reader of `scene`, `demo` and `paths`
takes its values through these functions: a key may be absent where the reader has a default (older
outputs lack some), but a key that is present must hold what its writer writes: a pose a finite rigid
4x4 camera-to-world (`scenes.common`'s rule: orthonormal within `RIGID_TOL`, det +1, origin within
`MAX_COORDINATE`), a score a finite number or null, a rank or slot a whole number, a name text, and
lists that describe the same views the same length.
"""

from __future__ import annotations

import math
from pathlib import Path, PurePosixPath
from typing import Any, Callable, List, Optional

import numpy as np

from waldo_jax.errors import MAX_RESOLUTION, WaldoError, check_input_file, is_finite_number, one_line

__all__ = ["MAX_FRUSTUMS", "Fields", "ViewerError", "check_image_file", "check_poses", "read_json", "relative_file"]

# The most cameras one page draws: viser adds a frustum in about a millisecond and the exported page grows
# by some 250 bytes with each, so 20,000 are 25 s and 5 MB; a results.json of 10^6 poses (some 100 MB) took
# 20 minutes. The search's views past it are left out, the worst first (a `waldo: warning:` line says so).
MAX_FRUSTUMS = 20_000

_MISSING = object()
# The smallest side of a view the viewer shows: a run's views keep their scene's aspect under `--resolution`
# (`Intrinsics.with_max_side`), so a 4:3 scene at `--resolution 8` writes 8x6 shots, which are waldo's own.
MIN_SIDE = 1


class ViewerError(WaldoError, ValueError):
    """A PATH `waldo view` cannot show (the message names it and says why)."""


def _shown(value: Any) -> str:
    """`repr(value)` on one line, cut to 60 characters (a list of 10^6 poses is not a message)."""
    text = one_line(repr(value))
    return text if len(text) <= 60 else text[:57] + "..."


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


class Fields:
    """A JSON object read from `path`, its values taken by key and checked (`ViewerError` naming the file,
    the key and the value).

    Args:
      data: the parsed JSON object (anything: a list or a number is refused as "not an object").
      path: the file it was read from (for the messages).
      where: the key path of `data` inside the file ("" for the file's top level, "topk[2]" for an entry).
    """

    def __init__(self, data: Any, path: Path, where: str = ""):
        self.path = Path(path)
        self.where = where
        if not isinstance(data, dict):
            raise self.error(f"expected a JSON object, got {_shown(data)}")
        self.data = data

    def key(self, name: str) -> str:
        """The full key path of `name` in the file (`topk[2].c2w`)."""
        return f"{self.where}.{name}" if self.where else name

    def error(self, problem: str, name: Optional[str] = None) -> ViewerError:
        """A `ViewerError` "FILE: KEY: problem" (the key left out for the object itself at the top level)."""
        where = self.key(name) if name is not None else self.where
        return ViewerError(f"{self.path}: {where + ': ' if where else ''}{problem}")

    def has(self, name: str) -> bool:
        """Whether `name` is present and not null."""
        return self.data.get(name) is not None

    def _get(self, name: str, default: Any) -> Any:
        value = self.data.get(name, _MISSING)
        if value is _MISSING or value is None:
            if default is _MISSING:
                raise self.error("missing", name)
            return default
        return value

    def text(self, name: str, default: Any = _MISSING, choices: Optional[tuple] = None) -> Any:
        """A string value (one of `choices` where given)."""
        value = self._get(name, default)
        if value is default and default is not _MISSING:
            return value
        if not isinstance(value, str):
            raise self.error(f"expected text, got {_shown(value)}", name)
        if choices is not None and value not in choices:
            raise self.error(f"expected one of {', '.join(map(repr, choices))}, got {_shown(value)}", name)
        return value

    def flag(self, name: str, default: Any = _MISSING) -> Any:
        """A true / false value."""
        value = self._get(name, default)
        if value is default and default is not _MISSING:
            return value
        if not isinstance(value, bool):
            raise self.error(f"expected true or false, got {_shown(value)}", name)
        return value

    def integer(self, name: str, default: Any = _MISSING, minimum: int = 0, maximum: int = 2**31 - 1) -> Any:
        """A whole number in [minimum, maximum] (a float such as 1.5, a bool or text refused)."""
        value = self._get(name, default)
        if value is default and default is not _MISSING:
            return value
        return _integer(value, minimum, maximum, lambda p: self.error(p, name))

    def number(self, name: str, default: Any = _MISSING, positive: bool = False) -> Any:
        """A finite number that float32 holds (> 0 with `positive`)."""
        value = self._get(name, default)
        if value is default and default is not _MISSING:
            return value
        return _number(value, positive, lambda p: self.error(p, name))

    def object(self, name: str, default: Any = _MISSING) -> Optional["Fields"]:
        """The JSON object under `name` as `Fields` (`default` where absent)."""
        value = self._get(name, default)
        if value is default and default is not _MISSING:
            return value
        if not isinstance(value, dict):
            raise self.error(f"expected a JSON object, got {_shown(value)}", name)
        return Fields(value, self.path, self.key(name))

    def items(self, name: str, default: Any = _MISSING) -> Any:
        """The list under `name` as `Fields` per entry (each must be an object)."""
        values = self.array(name, default)
        if values is default and default is not _MISSING:
            return values
        return [Fields(v, self.path, f"{self.key(name)}[{i}]") for i, v in enumerate(values)]

    def array(self, name: str, default: Any = _MISSING) -> Any:
        """A JSON list (`default` where absent)."""
        value = self._get(name, default)
        if value is default and default is not _MISSING:
            return value
        if not isinstance(value, list):
            raise self.error(f"expected a list, got {_shown(value)}", name)
        return value

    def scores(self, name: str, count: Optional[int] = None, default: Any = _MISSING, of: str = "views") -> Any:
        """A list of scores: finite numbers, or null for a view not scored (its render failed); `count`
        entries where given (the views, or what `of` names, that they score)."""
        values = self.array(name, default)
        if values is default and default is not _MISSING:
            return values
        if count is not None and len(values) != count:
            raise self.error(f"{len(values)} scores for {count} {of}", name)
        out: List[Optional[float]] = []
        for i, value in enumerate(values):
            out.append(None if value is None else _number(value, False, lambda p: self.error(p, f"{name}[{i}]")))
        return out

    def score(self, name: str) -> Optional[float]:
        """One score: a finite number, or None where absent or null."""
        return self.number(name, None)

    def integers(self, name: str, count: Optional[int] = None, minimum: int = 0, default: Any = _MISSING) -> Any:
        """A list of whole numbers >= `minimum` (`count` of them where given)."""
        values = self.array(name, default)
        if values is default and default is not _MISSING:
            return values
        if count is not None and len(values) != count:
            raise self.error(f"{len(values)} entries for {count} views", name)
        return [
            _integer(v, minimum, 2**31 - 1, lambda p, i=i: self.error(p, f"{name}[{i}]")) for i, v in enumerate(values)
        ]

    def poses(self, name: str, default: Any = _MISSING) -> Any:
        """A list of camera-to-world matrices, float64 [N, 4, 4], each finite and rigid (`check_poses`)."""
        value = self._get(name, default)
        if value is default and default is not _MISSING:
            return value
        return check_poses(value, lambda p: self._indexed(p, name))

    def _indexed(self, problem: str, name: str) -> ViewerError:
        """`check_poses`'s "[i]: problem" as the error of key `name[i]`."""
        index, _, rest = problem.partition(": ")
        return self.error(rest, name + index) if problem.startswith("[") else self.error(problem, name)

    def pose(self, name: str) -> np.ndarray:
        """One camera-to-world matrix, float64 [4, 4], finite and rigid."""
        value = self._get(name, _MISSING)
        return check_poses([value], lambda p: self.error(p.removeprefix("[0]: "), name))[0]

    def resolution(self, name: str, default: Any = _MISSING) -> Any:
        """An image size [width, height], each side MIN_SIDE .. MAX_RESOLUTION pixels."""
        values = self.array(name, default)
        if values is default and default is not _MISSING:
            return values
        if len(values) != 2:
            raise self.error(f"expected [width, height], got {_shown(values)}", name)
        side = f"expected [width, height] of {MIN_SIDE} .. {MAX_RESOLUTION} pixels each, got {_shown(values)}"
        return tuple(_integer(v, MIN_SIDE, MAX_RESOLUTION, lambda _: self.error(side, name)) for v in values)


def _integer(value: Any, minimum: int, maximum: int, error: Callable[[str], Exception]) -> int:
    # A JSON integer past 64 bits reads as a float (`io.parse_json`): refused here as not a whole number.
    if isinstance(value, bool) or not isinstance(value, int) or not minimum <= value <= maximum:
        raise error(f"expected a whole number between {minimum} and {maximum}, got {_shown(value)}")
    return int(value)


def _as_float(value: Any) -> float:
    """A number as a float: an integer past float64's range is infinite (waldo's JSON reader makes such
    integers floats already; a caller's own Python numbers need not be)."""
    try:
        return float(value)
    except OverflowError:
        return math.inf


def _number(value: Any, positive: bool, error: Callable[[str], Exception]) -> float:
    # NaN and Infinity are not JSON, but Python's parser reads them: a file that holds one is damaged.
    if not is_finite_number(value) or abs(value) > float(np.finfo(np.float32).max):
        raise error(f"expected a finite number, got {_shown(value)}")
    if positive and not np.float32(value) > 0:
        raise error(f"expected a positive number, got {_shown(value)}")
    return float(value)


def check_poses(value: Any, error: Callable[[str], Exception]) -> np.ndarray:
    """`value` (a list of 4x4 lists of numbers) as float64 [N, 4, 4] if every matrix is a finite rigid
    camera-to-world with its origin within `MAX_COORDINATE` (`scenes.common.rigid_problem`, the scenes'
    rule, checked for all N at once); else `error(problem)` naming the first bad pose by its index."""
    from waldo_jax.scenes.common import rigid_problem

    if not isinstance(value, list):
        raise error(f"expected a list of 4x4 camera-to-world matrices, got {_shown(value)}")
    for i, m in enumerate(value):  # the shape and the types first: np.asarray reads "1" and true as numbers
        if not (
            isinstance(m, list)
            and len(m) == 4
            and all(isinstance(row, list) and len(row) == 4 and all(map(_is_number, row)) for row in m)
        ):
            raise error(f"[{i}]: expected a 4x4 matrix of numbers, got {_shown(m)}")
    try:
        m = np.asarray(value, np.float64).reshape(-1, 4, 4)
    except OverflowError:  # an integer past float64 (waldo's JSON reader makes them inf; a caller's need not)
        m = np.array([[[_as_float(v) for v in row] for row in pose] for pose in value], np.float64)
    found = rigid_problem(m)
    if found is not None:
        raise error(f"[{found[0]}]: {found[1]}")
    return m


def read_json(path: Path, what: str) -> Any:
    """The JSON of the file at `path` (`io.read_json_file`: size and depth bounded), once it is known to be a
    regular file: a FIFO named summary.json or results.json had blocked its read for ever, and a folder was
    said to be missing (`errors.check_input_file` says which it is)."""
    from waldo_jax.io import read_json_file

    try:
        check_input_file(path, what)
    except WaldoError as e:
        raise ViewerError(str(e)) from None
    return read_json_file(path, what, lambda problem: ViewerError(f"{path}: {problem}"))


def relative_file(fields: Fields, name: str, folder: Path) -> Optional[Path]:
    """The file that `fields[name]` names relative to `folder` (None where absent or null): a relative path
    that stays inside the folder (an output's images are its own; `../` or an absolute name would put any
    image of the machine into an exported page)."""
    text = fields.text(name, None)
    if text is None:
        return None
    parts = PurePosixPath(text.replace("\\", "/")).parts
    if not text or text.startswith(("/", "\\")) or Path(text).is_absolute() or ".." in parts or "\x00" in text:
        raise fields.error(f"expected a file name inside {folder}, got {_shown(text)}", name)
    return folder / text


def check_image_file(path: Path, what: str) -> Path:
    """`path` if it is a regular file whose header an image reader knows, of sides MIN_SIDE ..
    MAX_RESOLUTION pixels (read from the header before the page is built);
    else a `ViewerError` naming `what` and the file (a directory, a FIFO, a link loop said as such)."""
    from PIL import Image

    try:
        check_input_file(path, "image file")
    except WaldoError as e:
        raise ViewerError(f"{what}: {e}") from None
    try:
        with Image.open(path) as header:
            width, height = header.size
    except Exception as e:  # Pillow raises many types (a truncated header, a decompression bomb, not an image)
        first = (str(e).strip().splitlines() or [type(e).__name__])[0]
        raise ViewerError(f"{what}: {path}: not a readable image ({one_line(first)[:160]})") from None
    if not (MIN_SIDE <= min(width, height) and max(width, height) <= MAX_RESOLUTION):
        raise ViewerError(
            f"{what}: {path}: the image is {width}x{height}; sides must lie between {MIN_SIDE} and "
            f"{MAX_RESOLUTION} pixels"
        )
    return path

"""OpenCV FileStorage YAML (`%YAML:1.0`, the subset OpenCV writes) read without OpenCV.

`read_opencv_storage(path)` returns the file's top-level mapping: mappings, sequences, flow
lists/maps, numbers, and `!!opencv-matrix` nodes as NumPy arrays of their `dt`. BRISQUE's SVR and
feature ranges (OpenCV contrib's `quality` module) are stored this way.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Dict, List, Tuple

import numpy as np

from waldo_jax.errors import DataNotFoundError, WaldoError, check_input_file
from waldo_jax.weights.store import WeightsError

__all__ = ["read_opencv_storage"]


class _StorageError(Exception):
    def __init__(self, line: int, problem: str):
        super().__init__(f"line {line}: {problem}")


# The largest file read (BRISQUE's and NIQE's models are under 1 MiB).
MAX_YAML_BYTES = 64 << 20
_NUMBER = re.compile(r"[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$")
_INTEGER = re.compile(r"[-+]?\d+$")
_SPECIAL = {".inf": np.inf, "+.inf": np.inf, "-.inf": -np.inf, ".nan": np.nan}
_KEY = re.compile(r"([A-Za-z_][\w\-]*)\s*:(\s+|$)(.*)$")
_DTYPES = {"u": np.uint8, "c": np.int8, "w": np.uint16, "s": np.int16, "i": np.int32, "f": np.float32, "d": np.float64}


def _scalar(token: str) -> Any:
    token = token.strip()
    if _INTEGER.match(token):
        return int(token)
    if _NUMBER.match(token):
        return float(token)
    if token.lower() in _SPECIAL:
        return _SPECIAL[token.lower()]
    if len(token) >= 2 and token[0] == token[-1] and token[0] in "\"'":
        return token[1:-1]
    return token


def _flow(text: str, line: int) -> Any:
    """A flow collection `[ ... ]` / `{ k: v, ... }` (nested allowed) or a scalar."""
    pos = 0

    def skip() -> None:
        nonlocal pos
        while pos < len(text) and text[pos] in " \t":
            pos += 1

    def value() -> Any:
        nonlocal pos
        skip()
        if pos >= len(text):
            raise _StorageError(line, "a value is missing")
        if text[pos] in "[{":
            closing = "]" if text[pos] == "[" else "}"
            is_map = text[pos] == "{"
            pos += 1
            items: Any = {} if is_map else []
            while True:
                skip()
                if pos < len(text) and text[pos] == closing:
                    pos += 1
                    return items
                if is_map:
                    match = re.compile(r"([A-Za-z_][\w\-]*)\s*:").match(text, pos)
                    if not match:
                        raise _StorageError(line, f"expected 'key:' in a flow mapping at {text[pos : pos + 20]!r}")
                    pos = match.end()
                    items[match.group(1)] = value()
                else:
                    items.append(value())
                skip()
                if pos < len(text) and text[pos] == ",":
                    pos += 1
                elif pos < len(text) and text[pos] == closing:
                    continue
                else:
                    raise _StorageError(line, f"expected ',' or {closing!r} at {text[pos : pos + 20]!r}")
        start = pos
        while pos < len(text) and text[pos] not in ",]}":
            pos += 1
        return _scalar(text[start:pos])

    result = value()
    skip()
    if pos != len(text):
        raise _StorageError(line, f"unexpected text after a value: {text[pos : pos + 20]!r}")
    return result


def _logical_lines(text: str) -> List[Tuple[int, int, str]]:
    """(line number, indent, content) with flow collections spanning lines joined into one."""
    lines = text.splitlines()
    out: List[Tuple[int, int, str]] = []
    i = 0
    while i < len(lines):
        raw = lines[i]
        number = i + 1
        i += 1
        content = raw.strip()
        if not content or content.startswith("#") or content == "---" or content.startswith("%"):
            continue
        indent = len(raw) - len(raw.lstrip(" "))
        depth = content.count("[") + content.count("{") - content.count("]") - content.count("}")
        while depth > 0:
            if i >= len(lines):
                raise _StorageError(number, "a '[' or '{' is never closed")
            more = lines[i].strip()
            i += 1
            content += " " + more
            depth += more.count("[") + more.count("{") - more.count("]") - more.count("}")
        out.append((number, indent, content))
    return out


def _matrix(node: Any, line: int) -> np.ndarray:
    if not isinstance(node, dict) or not {"rows", "cols", "dt", "data"} <= set(node):
        raise _StorageError(line, "an opencv-matrix needs rows, cols, dt and data")
    rows, cols, dt, data = node["rows"], node["cols"], str(node["dt"]), node["data"]
    if dt not in _DTYPES:
        raise _StorageError(line, f"unsupported opencv-matrix dt {dt!r}")
    if not isinstance(data, list) or len(data) != rows * cols:
        size = len(data) if isinstance(data, list) else "no list of"
        raise _StorageError(line, f"opencv-matrix {rows}x{cols} has {size} data values")
    return np.asarray(data, dtype=_DTYPES[dt]).reshape(rows, cols)


def _block(lines: List[Tuple[int, int, str]], start: int, indent: int) -> Tuple[Any, int]:
    """Parses the block of lines at `indent` from `start`; returns (value, index after the block)."""
    number, _, content = lines[start]
    is_sequence = content == "-" or content.startswith("- ")
    result: Any = [] if is_sequence else {}
    i = start
    while i < len(lines) and lines[i][1] == indent:
        number, _, content = lines[i]
        if is_sequence:
            if not (content == "-" or content.startswith("- ")):
                raise _StorageError(number, f"expected a '- ' item, got {content[:30]!r}")
            rest = content[1:].strip()
            i += 1
            if rest:
                result.append(_flow(rest, number))
            elif i < len(lines) and lines[i][1] > indent:
                value, i = _block(lines, i, lines[i][1])
                result.append(value)
            else:
                result.append(None)
            continue
        match = _KEY.match(content)
        if not match:
            raise _StorageError(number, f"expected 'key: value', got {content[:30]!r}")
        key, rest = match.group(1), match.group(3).strip()
        i += 1
        tag = None
        if rest.startswith("!!"):
            tag, _, rest = rest.partition(" ")
            rest = rest.strip()
        if rest:
            value = _flow(rest, number)
        elif i < len(lines) and lines[i][1] > indent:
            value, i = _block(lines, i, lines[i][1])
        else:
            value = None
        if tag == "!!opencv-matrix":
            value = _matrix(value, number)
        elif tag is not None:
            raise _StorageError(number, f"unsupported tag {tag!r}")
        result[key] = value
    if i < len(lines) and lines[i][1] > indent:
        raise _StorageError(lines[i][0], "unexpected indentation")
    return result, i


def read_opencv_storage(path: str | Path) -> Dict[str, Any]:
    """The top-level mapping of an OpenCV FileStorage YAML file (`%YAML:1.0`).

    Mappings, sequences, flow lists/maps and `!!opencv-matrix` nodes (as NumPy arrays of their `dt`)
    are read; numbers become int or float.

    Raises:
      DataNotFoundError: no such file.
      WeightsError: not an OpenCV YAML file, or malformed (names the file and the line).
    """
    path = Path(path)
    if not os.path.lexists(path):  # anything there that is no readable file is said by check_input_file
        raise DataNotFoundError(f"file not found: {path}")
    try:
        check_input_file(path, "OpenCV YAML file")
        if path.stat().st_size > MAX_YAML_BYTES:
            raise WeightsError(
                f"{path}: an OpenCV YAML file of {path.stat().st_size / 2**20:,.0f} MiB (at most "
                f"{MAX_YAML_BYTES // 2**20} MiB: the models' files are under 1 MiB)"
            )
    except WaldoError as exc:
        raise WeightsError(str(exc)) from None
    try:
        text = path.read_text(encoding="utf-8")
    except (UnicodeDecodeError, OSError) as exc:
        raise WeightsError(f"{path}: not a readable OpenCV YAML file ({exc})") from None
    first = next((line.strip() for line in text.splitlines() if line.strip()), "")
    if not first.startswith("%YAML"):
        raise WeightsError(f"{path}: not an OpenCV FileStorage YAML file (no '%YAML' header)")
    try:
        lines = _logical_lines(text)
        if not lines:
            raise _StorageError(1, "the file holds no data")
        tree, end = _block(lines, 0, lines[0][1])
        if end != len(lines):
            raise _StorageError(lines[end][0], "unexpected dedent")
    except _StorageError as exc:
        raise WeightsError(f"{path}: malformed OpenCV YAML, {exc}") from None
    except (ValueError, TypeError, OverflowError) as exc:  # OverflowError: 300 as a uint8 'dt'
        raise WeightsError(f"{path}: malformed OpenCV YAML ({exc})") from None
    except RecursionError:  # flow lists or blocks nested thousands deep: the parser recurses per level
        raise WeightsError(f"{path}: malformed OpenCV YAML (nested too deep to read)") from None
    if not isinstance(tree, dict):
        raise WeightsError(f"{path}: the top level is not a mapping")
    return tree

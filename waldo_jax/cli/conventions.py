"""What every `waldo` command shares: its parser's one-line errors, "(default: X)" in help, `--quiet`, progress.

* `Parser`: an argparse parser whose bad arguments (an unknown choice, a missing value, a typo in a flag)
  raise `UsageError`, a `WaldoError` the CLI prints as one line `waldo: error: ...` with exit status 1,
  like every other bad input; a value outside a flag's `choices` reads `unknown --flag 'value': expected
  one of a, b`. Sub-commands' parsers are `Parser`s too (argparse makes them of the parent's class).
* `DefaultsHelpFormatter`: appends " (default: X)" to the help of each option with a default, unless
  the help already says "(default: ...)" in words (a default derived from other values).
* `add_quiet` / `Progress`: `--quiet` silences progress (bars, phase names, chatter on stderr), never
  errors, warnings nor the command's result. Progress bars (tqdm) go to stderr and only to a terminal,
  so a pipe, a log file or `--json` output stays clean.
"""

from __future__ import annotations

import argparse
import re
import sys
from typing import Optional, TextIO

from tqdm import tqdm

from waldo_jax.errors import WaldoError

__all__ = ["Parser", "UsageError", "is_ascii_number", "path_argument", "DefaultsHelpFormatter", "add_quiet", "Progress"]


# A decimal number in ASCII (a sign, digits with an optional point, an exponent) or a word float() reads for
# infinity and NaN (refused later by name, where the flag's range is checked).
_ASCII_NUMBER = re.compile(
    r"\s*[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?\s*|\s*[+-]?(inf|infinity|nan)\s*", re.ASCII | re.I
)


def path_argument(text: str) -> str:
    """An argparse `type` for a file or folder argument: empty text (or blanks) is refused, where Python's
    Path would read it as the current folder (`weights convert SRC ''` wrote into it)."""
    if not text.strip():
        raise argparse.ArgumentTypeError("empty: name a file or folder")
    return text


def is_ascii_number(text: str) -> bool:
    """Whether `text` is a number written in ASCII digits (no "1_0", no non-ASCII digits)."""
    return _ASCII_NUMBER.fullmatch(text) is not None


class UsageError(WaldoError):
    """Bad command-line arguments (as argparse finds them): printed as one line, exit status 1."""


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """Help text with " (default: X)" after every option that has a default (not None / False / [])."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        absent = action.default is None or action.default is False or action.default is argparse.SUPPRESS
        if "(default" in text or not action.option_strings or action.required or absent or action.default == []:
            return text
        return text + " (default: %(default)s)"


class Parser(argparse.ArgumentParser):
    """An `argparse.ArgumentParser` whose errors are one-line `UsageError`s and whose help states defaults."""

    def __init__(self, *args, formatter_class=DefaultsHelpFormatter, **kwargs):
        super().__init__(*args, formatter_class=formatter_class, **kwargs)

    def error(self, message: str):
        """Raises `UsageError(message)` (argparse would print the usage and exit with status 2)."""
        raise UsageError(" ".join(message.split()))

    def _get_value(self, action: argparse.Action, arg_string: str):
        # int() and float() read "1_0" as 10 and Arabic-Indic or full-width digits as digits: a number on the
        # command line is written in ASCII, as the environment's and procedural:SEED's are.
        # Text that is no number at all keeps argparse's own "invalid int value" message.
        readable_only_by_python = isinstance(arg_string, str) and (not arg_string.isascii() or "_" in arg_string)
        if action.type in (int, float) and readable_only_by_python and not is_ascii_number(arg_string):
            flag = max(action.option_strings, key=len) if action.option_strings else (action.metavar or action.dest)
            raise argparse.ArgumentError(None, f"{flag} must be a number in ASCII digits, got {arg_string!r}")
        return super()._get_value(action, arg_string)

    def _check_value(self, action: argparse.Action, value) -> None:
        # argparse's own hook for `choices`; the project's wording names the flag, the value and the choices.
        if action.choices is not None and value not in action.choices:
            flag = max(action.option_strings, key=len) if action.option_strings else (action.metavar or action.dest)
            raise argparse.ArgumentError(
                None, f"unknown {flag} {value!r}: expected one of {', '.join(map(str, action.choices))}"
            )


def add_quiet(parser: argparse.ArgumentParser, what: str = "progress bars nor progress lines") -> None:
    """`--quiet` on `parser`: no `what` (errors, warnings and the result are printed still)."""
    parser.add_argument("--quiet", action="store_true", help=f"no {what}; errors, warnings and the result still print")


class Progress:
    """A command's progress on stderr: named phases and counted steps on one tqdm bar, and lines.

    Silent with `quiet`; the bar shows only on a terminal (tqdm's `disable=None`), lines always
    (unless quiet). Use as a context manager, so the bar is cleared on success and on error.
    """

    def __init__(self, quiet: bool = False, stream: Optional[TextIO] = None):
        self.quiet = quiet
        self.stream = sys.stderr if stream is None else stream
        self._bar = None

    def say(self, message: str) -> None:
        """One progress line (e.g. "rendering 8 views at 64x64 ..."), unless quiet."""
        if not self.quiet:
            print(message, file=self.stream, flush=True)

    def phase(self, name: str, total: Optional[int] = None, unit: str = "it") -> None:
        """Starts phase `name` (e.g. "compiling and searching"); `total` steps counted by `advance`."""
        self.close()
        self._bar = tqdm(
            total=total,
            desc=name,
            unit=unit,
            disable=True if self.quiet else None,
            file=self.stream,
            leave=False,
            dynamic_ncols=True,
            bar_format=None if total else "{desc} ... {elapsed}",
        )

    def advance(self, steps: int = 1) -> None:
        """Counts `steps` done in the current phase."""
        if self._bar is not None:
            self._bar.update(steps)

    def close(self) -> None:
        """Ends the current phase (clears its bar)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None

    def __enter__(self) -> "Progress":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

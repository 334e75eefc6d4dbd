"""CLI conventions shared by every command (issue 35, item 5): `--version`, `--quiet`, progress on stderr,
`choices` refused in one line with exit 1, and every default stated as " (default: X)" in help."""

import argparse
import io
import json
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

import waldo_jax
from waldo_jax.cli import build_parser, main
from waldo_jax.cli.conventions import Progress
from waldo_jax.version import UNKNOWN_VERSION, package_version

ROOT = Path(__file__).resolve().parent.parent
# Commands that print progress or chatter (bars, phase names, "rendering N views ...", per-model lines).
QUIET_COMMANDS = [
    ("demo",),
    ("explore",),
    ("train",),
    ("path",),
    ("render",),
    ("score",),
    ("scene", "info"),
    ("weights", "convert"),
]


class _Terminal(io.StringIO):
    """A stderr that says it is a terminal, so progress bars draw (tqdm hides them from pipes and files)."""

    def isatty(self):
        return True


def _commands(parser=None, prefix=()):
    """{(command, subcommand...): parser} of every runnable command under `parser`."""
    parser = parser or build_parser()
    found = {}
    for action in parser._actions:  # argparse keeps its subcommands only there
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found.update(_commands(sub, prefix + (name,)) or {prefix + (name,): sub})
    return found


def _pyproject_version():
    text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    return text.split("[project]", 1)[1].split('version = "', 1)[1].split('"', 1)[0]


def test_version_flag_prints_the_package_version():
    result = subprocess.run(
        [sys.executable, "-m", "waldo_jax", "--version"], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout == f"waldo {_pyproject_version()}\n"
    assert waldo_jax.__version__ == _pyproject_version()


def test_version_falls_back_to_pyproject_then_to_unknown(tmp_path):
    pyproject = tmp_path / "pyproject.toml"
    pyproject.write_text(
        '[build-system]\nrequires = []\n\n[project]\nname = "x"\nversion = "9.8.7"\n[tool.other]\nversion = "1.0"\n'
    )
    assert package_version("waldo-jax-never-installed", pyproject) == "9.8.7"
    assert package_version("waldo-jax-never-installed", tmp_path / "missing.toml") == UNKNOWN_VERSION


def test_every_command_that_prints_progress_takes_quiet():
    commands = _commands()
    assert set(QUIET_COMMANDS) <= set(commands), sorted(commands)
    lacking = [
        " ".join(c)
        for c in QUIET_COMMANDS
        if "--quiet" not in {s for a in commands[c]._actions for s in a.option_strings}
    ]
    assert not lacking, f"without --quiet: {lacking}"


@pytest.mark.parametrize(
    "argv, flag, value",
    [
        (["explore", "procedural", "--out", "{tmp}/new", "--budget", "huge"], "--budget", "huge"),
        (["explore", "procedural", "--out", "{tmp}/new", "--pibs-fallback", "egps"], "--pibs-fallback", "egps"),
        (["explore", "procedural", "--out", "{tmp}/new", "--initial", "photos"], "--initial", "photos"),
        (["path", "procedural", "--out", "{tmp}/new", "--aggregate", "max"], "--aggregate", "max"),
        (["path", "procedural", "--out", "{tmp}/new", "--budget", "medium"], "--budget", "medium"),
        (["train", "{tmp}", "--out", "{tmp}/new", "--preset", "best"], "--preset", "best"),
        (["train", "{tmp}", "--out", "{tmp}/new", "--sampler", "grid"], "--sampler", "grid"),
        (["train", "{tmp}", "--out", "{tmp}/new", "--model", "mesh"], "--model", "mesh"),
        (["scene", "info", "{tmp}", "--split", "holdout"], "--split", "holdout"),
        (["sceen", "info", "{tmp}"], "COMMAND", "sceen"),
    ],
)
def test_a_value_outside_the_choices_is_one_line_and_exit_1(tmp_path, capsys, argv, flag, value):
    status = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 1 and len(err) == 1, err
    assert err[0].startswith(f"waldo: error: unknown {flag} '{value}': expected one of "), err[0]
    assert not (tmp_path / "new").exists()


def test_other_argument_errors_are_one_line_and_exit_1(capsys):
    for argv, message in (
        (["render", "procedural", "--out", "x", "--resolutoin", "8"], "unrecognized arguments"),
        (["render", "procedural", "--out", "x", "--views", "many"], "invalid int value: 'many'"),
        ([], "required: COMMAND"),
    ):
        assert main(argv) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("waldo: error: ") and message in err[0], err


def test_help_states_every_default_one_way():
    """Each option with a default shows " (default: X)"; none says "(default X)" or "X (default)"."""
    problems = []
    for name, parser in _commands().items():
        text = " ".join(parser.format_help().split())
        for action in parser._actions:
            help_text = action.help or ""
            if "default" in help_text and "(default: " not in help_text:
                problems.append(f"{' '.join(name)} {action.option_strings}: {help_text!r}")
            default = action.default
            has_default = not (default is None or default is False or default is argparse.SUPPRESS or default == [])
            if action.option_strings and not action.required and has_default and "(default: " not in help_text:
                shown = f"(default: {action.default})"
                if shown not in text:
                    problems.append(f"{' '.join(name)} {action.option_strings}: no {shown} in help")
    assert not problems, "\n".join(problems)


def test_progress_goes_to_a_terminal_and_quiet_silences_it():
    for quiet in (False, True):
        stream = _Terminal()
        with Progress(quiet, stream) as progress:
            progress.say("rendering 3 views ...")
            progress.phase("compiling", total=3, unit="view")
            progress.advance(3)
        assert ("rendering 3 views" in stream.getvalue() and "compiling" in stream.getvalue()) != quiet
        assert stream.getvalue() == "" or not quiet
    pipe = io.StringIO()  # not a terminal: lines, no bar
    with Progress(False, pipe) as progress:
        progress.say("a line")
        progress.phase("a bar", total=2)
        progress.advance(2)
    assert pipe.getvalue() == "a line\n"


def test_render_quiet_keeps_the_result_line_and_the_images(tmp_path, capsys, monkeypatch):
    """`waldo render procedural --poses FILE` shows its progress on a terminal, none with --quiet; the
    result line and the images are the same."""
    from waldo_jax.cameras import look_at

    c2w = [
        np.concatenate(
            [
                np.asarray(
                    look_at(
                        np.array([2.0 * np.cos(a), 0.4, 2.0 * np.sin(a)], np.float32),
                        np.zeros(3),
                        np.array([0.0, 1.0, 0.0]),
                    )
                )[:3],
                [[0, 0, 0, 1]],
            ]
        ).tolist()
        for a in (0.0, 2.0)
    ]
    poses = tmp_path / "poses.json"
    poses.write_text(
        json.dumps({"camera_angle_x": 1.0, "w": 8, "h": 8, "frames": [{"transform_matrix": m} for m in c2w]})
    )
    outputs = {}
    for quiet in (False, True):
        terminal = _Terminal()
        monkeypatch.setattr(sys, "stderr", terminal)
        out = tmp_path / f"quiet{quiet}"
        argv = ["render", "procedural", "--poses", str(poses), "--samples", "8", "--out", str(out)]
        assert main(argv + ["--quiet"] * quiet) == 0
        monkeypatch.undo()
        assert ("rendering" in terminal.getvalue()) != quiet, terminal.getvalue()
        stdout = capsys.readouterr().out.strip().splitlines()
        assert len(stdout) == 1 and stdout[0].startswith("wrote 2 PNGs of procedural:0 at 8x8")
        outputs[quiet] = [iio.imread(out / f"{i:04d}.png") for i in range(2)]
    assert all(np.array_equal(a, b) for a, b in zip(outputs[False], outputs[True]))


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # imageio-ffmpeg writes the MP4 in a subprocess
def test_path_shows_its_phases_on_a_terminal_and_quiet_hides_them(tmp_path, capsys, monkeypatch):
    """`waldo path` names its phases (loading, compiling and searching, rendering, writing) on a terminal's
    stderr; --quiet prints none of them, and the search finds the same path either way."""
    tiny = [
        "--criterion",
        "waldo_oracle",
        "--resolution",
        "16",
        "--views",
        "8",
        "--keyframes",
        "3",
        "--frames",
        "8",
        "--epochs",
        "1",
        "--initial-paths",
        "4",
        "--paths-per-epoch",
        "3",
        "--max-speed",
        "0.5",
        "--max-turn",
        "60",
    ]
    found = {}
    for quiet in (False, True):
        terminal = _Terminal()
        monkeypatch.setattr(sys, "stderr", terminal)
        out = tmp_path / f"quiet{quiet}"
        assert main(["path", "procedural:1", "--out", str(out), *tiny] + ["--quiet"] * quiet) == 0
        monkeypatch.undo()
        text = terminal.getvalue()
        phases = (
            "loading procedural:1",
            "compiling and searching (1 epoch, 1 seed)",
            "rendering the 8 video frames",
            "writing the exports",
        )
        assert all((phase in text) != quiet for phase in phases), text
        stdout = capsys.readouterr().out.strip().splitlines()
        assert len(stdout) == 1 and stdout[0].startswith("EGPS path on ") and str(out) in stdout[0]
        found[quiet] = json.loads((out / "results.json").read_text())["found"]["score"]
    assert found[False] == found[True]


@pytest.mark.parametrize(
    "argv, name",
    [
        (["scene", "info", ""], "path"),
        (["train", " ", "--out", "{tmp}/o"], "SCENE_PATH"),
        (["weights", "convert", "", "{tmp}/o"], "SRC"),  # had converted the current folder (DST: the --out rule)
        (["score", "--criterion", "colorfulness", ""], "IMAGE"),
    ],
)
def test_an_empty_file_or_folder_argument_is_refused_not_read_as_the_current_folder(tmp_path, capsys, argv, name):
    before = sorted(Path.cwd().iterdir())
    assert main([a.replace("{tmp}", str(tmp_path)) for a in argv]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"waldo: error: argument {name}: empty: name a file or folder"]
    assert sorted(Path.cwd().iterdir()) == before and not (tmp_path / "o").exists()

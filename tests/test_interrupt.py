"""Ctrl-C (SIGINT) and SIGTERM end `waldo` cleanly at every stage (issue [3/5], waldo_jax.cli.interrupt):
exit status 130 / 143, one line `waldo: interrupted`, no traceback (before the fix: a segmentation
fault, exit 139, after the line), no half-written file, no unfinished new output folder, earlier
output folders byte-identical.

The subprocess tests send the signal after the first progress line: a training interrupted while its
first chunk compiles (where the segfault was) and while it trains, a search interrupted while its
jitted epochs run (where the main thread waits inside XLA and Python runs no signal handler). The
in-process tests interrupt the writing of outputs.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import select
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from test_bad_input import _write_scene
from waldo_jax import io
from waldo_jax.cli import interrupt, main

# A process started in the background by a non-interactive shell inherits SIGINT as ignored, and
# waldo keeps an inherited "ignore" (as Python does): the child starts from Python's default handler.
_WALDO = (
    "import runpy, signal; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "runpy.run_module('waldo_jax', run_name='__main__')"
)


def _tree(folder):
    """{relative path: sha256} of every file under folder."""
    out = {}
    for root, _, files in os.walk(folder):
        for name in files:
            path = os.path.join(root, name)
            with open(path, "rb") as f:
                out[os.path.relpath(path, folder)] = hashlib.sha256(f.read()).hexdigest()
    return out


def _signal_after(argv, ready, signum, cwd, timeout=300.0, env=None):
    """Runs `waldo argv` (with the variables `env` added to the environment), sends `signum` once `ready` (text,
    or a compiled bytes pattern) has appeared in its output (stdout and stderr, progress bars included), and
    returns (exit status, output, seconds from the signal to the exit)."""
    proc = subprocess.Popen(
        [sys.executable, "-c", _WALDO, *argv],
        cwd=cwd,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        env=None if env is None else {**os.environ, **env},
    )
    output, sent, deadline = b"", None, time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            readable, _, _ = select.select([proc.stdout], [], [], 1.0)
            chunk = os.read(proc.stdout.fileno(), 65536) if readable else b""
            if readable and not chunk:
                break
            output += chunk
            seen = ready.search(output) if isinstance(ready, re.Pattern) else ready.encode() in output
            if sent is None and seen:
                proc.send_signal(signum)
                sent = time.monotonic()
        status = proc.wait(timeout=max(1.0, deadline - time.monotonic()))
    finally:
        if proc.poll() is None:
            proc.kill()
    text = output.decode(errors="replace")
    assert sent is not None, f"{ready!r} never appeared:\n{text[-3000:]}"
    return status, text, time.monotonic() - sent


def _assert_clean(status, text, signum):
    assert status == interrupt.EXIT_STATUS[signum], f"exit status {status}:\n{text[-3000:]}"
    lines = [line for line in text.replace("\r", "\n").splitlines() if line.startswith("waldo: ")]
    assert len(lines) == 1 and lines[0].startswith("waldo: interrupted"), text[-3000:]
    assert "Traceback" not in text and "Fatal Python error" not in text, text[-3000:]


@pytest.fixture
def scene_and_earlier_run(tmp_path):
    _write_scene(tmp_path / "scene")
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / "keep.txt").write_text("an earlier run")
    (earlier / "results.json").write_text('{"cvir": 1.0}')
    return tmp_path, _tree(earlier)


@pytest.mark.parametrize(
    "signum, ready",
    [
        (signal.SIGINT, "/2000"),  # the first bar: the first chunk compiles
        (signal.SIGTERM, "loss="),
    ],  # a chunk trained: training runs
    ids=["sigint-while-compiling", "sigterm-while-training"],
)
def test_an_interrupted_training_exits_cleanly_and_leaves_no_run_folder(scene_and_earlier_run, signum, ready):
    tmp, earlier = scene_and_earlier_run
    status, text, seconds = _signal_after(["train", "scene", "--out", "new", "--steps", "2000"], ready, signum, tmp)
    _assert_clean(status, text, signum)
    assert "removed the unfinished output folder" in text
    assert not (tmp / "new").exists()  # created before training (checked writable), removed on the interrupt
    assert _tree(tmp / "earlier") == earlier
    assert seconds < 60, seconds


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["sigint", "sigterm"])
def test_an_interrupted_search_exits_at_once_and_leaves_the_earlier_run_as_it_was(scene_and_earlier_run, signum):
    """Into the earlier run's folder with --force: the search stops before anything is written. The
    epochs run in one jitted call: the exit must not wait for the remaining epochs."""
    tmp, earlier = scene_and_earlier_run
    status, text, seconds = _signal_after(
        [
            "explore",
            "procedural",
            "--criterion",
            "colorfulness",
            "--resolution",
            "16",
            "--views",
            "8",
            "--epochs",
            "1000",
            "--children-per-epoch",
            "8",
            "--out",
            "earlier",
            "--force",
        ],
        "epoch 1/1000",
        signum,
        tmp,
    )
    _assert_clean(status, text, signum)
    assert "epoch 1000/1000" not in text
    assert _tree(tmp / "earlier") == earlier
    assert sorted(os.listdir(tmp)) == ["earlier", "scene"]
    assert seconds < 30, seconds


# `waldo path` shows its phases only on a terminal, and its epochs run in one jitted call that says nothing:
# JAX's own log line for the compiled search marks the moment the search itself runs ("Finished XLA
# compilation of jit(_search) in ..." in jax 0.10; matched loosely, as its wording has changed between
# versions). 100 epochs of 300 paths (the oracle scores poses, no render) take about 25 s on the 2-core CPU
# past that line.
PATH_SEARCH = ["path", "procedural", "--frames", "8", "--keyframes", "2", "--resolution", "16", "--views", "4"]
PATH_SEARCH += ["--initial-paths", "3", "--epochs", "100", "--paths-per-epoch", "300"]
SEARCH_RUNS = re.compile(rb"Finished [^\n]*compil[^\n]*\b_search\b")


@pytest.mark.parametrize(
    "signum, out",
    [(signal.SIGINT, ["new"]), (signal.SIGTERM, ["earlier", "--force"])],
    ids=["sigint-new-folder", "sigterm-earlier-folder"],
)
def test_an_interrupted_path_search_exits_at_once_and_leaves_no_folder(tmp_path, signum, out):
    """`waldo path` interrupted in its jitted search (never tried before): the exit does not wait for the
    remaining epochs, no output folder is made (it is made once the search is done), and an earlier
    folder given with --force is left as it was."""
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / "camera_path.json").write_text('{"an": "earlier path"}')
    before = _tree(earlier)
    status, text, seconds = _signal_after(
        [*PATH_SEARCH, "--out", *out], SEARCH_RUNS, signum, tmp_path, env={"JAX_LOG_COMPILES": "1"}
    )
    _assert_clean(status, text, signum)
    assert "removed the unfinished output folder" not in text and " path on procedural:0 " not in text
    assert sorted(os.listdir(tmp_path)) == ["earlier"]
    assert _tree(earlier) == before
    assert seconds < 15, seconds


def _interrupt_on_call(monkeypatch, module, name, call, exception):
    """Makes module.name raise `exception` on its `call`-th call (1-based)."""
    real, calls = getattr(module, name), []

    def wrapper(*args, **kwargs):
        calls.append(1)
        if len(calls) == call:
            raise exception
        return real(*args, **kwargs)

    monkeypatch.setattr(module, name, wrapper)


RENDER = ["render", "procedural", "--views", "3", "--resolution", "8", "--samples", "8"]


def test_an_interrupt_while_writing_removes_the_new_folder(tmp_path, capsys, monkeypatch):
    """Ctrl-C between two files of a new output folder: status 130, the folder (which holds a part of
    the run) removed, no temporary file anywhere; the caller's signal handlers as they were (they were
    left ignoring SIGINT and SIGTERM, which every process started afterwards inherited)."""
    _interrupt_on_call(monkeypatch, io, "write_bytes", 2, KeyboardInterrupt())
    out = tmp_path / "deep" / "views"
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    assert main([*RENDER, "--quiet", "--out", str(out)]) == 130  # stderr: the interruption alone
    assert {s: signal.getsignal(s) for s in handlers} == handlers
    err = capsys.readouterr().err.strip()
    assert err == f"waldo: interrupted (removed the unfinished output folder {tmp_path / 'deep'})", err
    assert os.listdir(tmp_path) == []


def test_sigterm_while_writing_into_an_earlier_folder_keeps_every_file_whole(tmp_path, capsys, monkeypatch):
    """SIGTERM (as `interrupt.Interrupted`) during a --force render into an earlier folder: status 143;
    the folder stays (it is not new): each file in it is whole, either the earlier one or the new one,
    and no temporary file is left."""
    out = tmp_path / "views"
    assert main([*RENDER, "--out", str(out)]) == 0
    before = _tree(out)
    _interrupt_on_call(monkeypatch, io, "_open_temp", 2, interrupt.Interrupted(signal.SIGTERM))
    assert main([*RENDER, "--out", str(out), "--force", "--seed", "1"]) == 143
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == "waldo: interrupted by SIGTERM", err
    after = _tree(out)
    assert sorted(after) == sorted(before)  # no temporary file
    assert after["view_000.png"] != before["view_000.png"] and after["view_001.png"] == before["view_001.png"]


def test_discard_unfinished_removes_the_temporary_file_of_a_write_in_progress(tmp_path):
    with pytest.raises(FileNotFoundError):  # the rename finds no temporary file: the cut write never lands
        with io.atomic_file(tmp_path / "results.json") as f:
            f.write(b"half")
            assert len(os.listdir(tmp_path)) == 1  # the temporary file
            assert io.discard_unfinished() == []
            assert os.listdir(tmp_path) == []
    assert os.listdir(tmp_path) == []


_DROPPED = """
import os, signal, sys, time
from waldo_jax.cli import interrupt

signal.signal(signal.SIGTERM, signal.SIG_DFL)  # as a shell starts it (the worker may ignore it)

class Dropper:  # the signal arrives while Python runs a __del__, where an exception is dropped
    def __del__(self):
        os.kill(os.getpid(), signal.SIGTERM)
        end = time.perf_counter() + 0.3
        while time.perf_counter() < end:
            pass

with interrupt.handled(exit_process=True) as guard:
    try:
        Dropper()
        end = time.perf_counter() + 5.0
        while time.perf_counter() < end:  # Python code, as a training loop between its chunks
            pass
        print("never interrupted", flush=True)
    except KeyboardInterrupt as e:
        print("the main thread unwound", flush=True)
        guard.finish(e.signum)
"""


@pytest.mark.slow
def test_a_signal_raised_where_python_drops_exceptions_is_raised_again():
    """SIGTERM handled inside a __del__ (as it was inside one of JAX's garbage-collection callbacks in a
    training run): no "Exception ignored" traceback, and the main thread itself unwinds and ends the
    process with 143 (before: the traceback, then the watcher thread ending it after its grace time)."""
    proc = subprocess.run([sys.executable, "-c", _DROPPED], capture_output=True, text=True, timeout=120)
    text = proc.stdout + proc.stderr
    assert proc.returncode == 143, text
    assert "Traceback" not in text and "Exception ignored" not in text, text
    assert "the main thread unwound" in text and "waldo: interrupted by SIGTERM" in text, text


@pytest.mark.slow
def test_an_interrupted_held_out_evaluation_keeps_the_trained_run(tmp_path, capsys, monkeypatch):
    """Ctrl-C after training, while the held-out views render: status 130, and the run folder stays with
    the trained field (loadable; train.json without a held-out PSNR), not removed as unfinished. Run
    again without the interrupt, the evaluation is at the pixel budget and says so."""
    from waldo_jax.nerf import runs
    from waldo_jax.nerf.checkpoint import load_checkpoint

    _write_scene(tmp_path / "scene")  # 16x16 images; one held-out view
    _interrupt_on_call(monkeypatch, runs, "evaluate_held_out", 1, KeyboardInterrupt())
    out = tmp_path / "run"
    argv = ["train", str(tmp_path / "scene"), "--out", str(out), "--steps", "2", "--quiet", "--eval-max-pixels", "64"]
    assert main(argv) == 130
    assert capsys.readouterr().err.strip() == "waldo: interrupted"
    assert sorted(os.listdir(out)) == ["checkpoint.ckpt", "train.json"]
    stats = json.loads((out / "train.json").read_text())
    assert stats["psnr_test"] is None and stats["eval_image_size"] is None and stats["eval_downscale"] is None
    assert stats["steps"] == 2
    assert load_checkpoint(out / "checkpoint.ckpt").config.render_step_scale is None
    monkeypatch.undo()
    assert main([*argv, "--force"]) == 0
    assert "(at 8x8, 1/2 size; renders march x" in capsys.readouterr().out
    stats = json.loads((out / "train.json").read_text())
    assert stats["eval_image_size"] == [8, 8] and stats["eval_downscale"] == 2 and stats["psnr_test"] is not None


def test_a_kept_output_folder_and_the_folders_made_for_it_are_left_by_an_interrupt(tmp_path):
    before = len(io.created_output_dirs())  # earlier in-process tests may have left some
    kept = io.prepare_output_dir(tmp_path / "deep" / "run")
    other = io.prepare_output_dir(tmp_path / "other")
    assert io.created_output_dirs()[before:] == [tmp_path / "deep", tmp_path / "other"]
    assert not io.keep_output_dir(tmp_path / "other" / "part")  # a part of an output folder is not kept alone
    assert io.keep_output_dir(kept)
    assert io.discard_unfinished(io.created_output_dirs()[before:]) == [other.absolute()]
    assert kept.is_dir() and sorted(os.listdir(tmp_path)) == ["deep"]


def _importing_jax(pid: int) -> bool:
    """Whether process `pid` has jaxlib's library mapped: it is importing JAX (or past it)."""
    try:
        return "jaxlib" in Path(f"/proc/{pid}/maps").read_text()
    except OSError:
        return False


@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="reads a process's libraries from /proc")
@pytest.mark.parametrize("delay", [0.0, 0.3])
def test_a_signal_while_the_command_starts_ends_it_cleanly(tmp_path, delay):
    """Ctrl-C while `python -m waldo_jax` imports JAX (before `main` installs its handlers) ends the command
    at once with status 130 and one line: it once printed a 30-line import traceback, or was dropped in a
    garbage-collection callback of JAX's and the command went on to write its output. The signal is sent
    `delay` seconds after jaxlib's library appears in the process (the import under way, whatever the
    machine's speed)."""
    out = tmp_path / "out"
    argv = ["render", "procedural", "--views", "1", "--resolution", "8", "--samples", "4", "--out", str(out)]
    proc = subprocess.Popen(
        [sys.executable, "-m", "waldo_jax", *argv], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )
    deadline = time.monotonic() + 60
    while not _importing_jax(proc.pid) and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.002)
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    output, _ = proc.communicate(timeout=120)
    _assert_clean(proc.returncode, output.decode(errors="replace"), signal.SIGINT)
    assert not out.exists()


def test_only_the_waldo_command_guards_its_start(monkeypatch):
    """A process that imports waldo_jax as a library (a notebook, pytest) keeps its own signal handlers."""
    from waldo_jax import _startup

    monkeypatch.setattr(sys, "argv", ["/usr/bin/python3", "script.py"])
    monkeypatch.setattr(sys, "orig_argv", ["/usr/bin/python3", "script.py"])
    assert not _startup.is_waldo_command()
    monkeypatch.setattr(sys, "argv", ["/venv/bin/waldo", "demo"])
    assert _startup.is_waldo_command()
    monkeypatch.setattr(sys, "argv", ["/x/waldo_jax/__main__.py"])
    monkeypatch.setattr(sys, "orig_argv", ["python", "-m", "waldo_jax", "demo"])
    assert _startup.is_waldo_command()

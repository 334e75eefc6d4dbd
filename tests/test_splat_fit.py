"""A splat fit's work is set by its images' size: the first step program is checked against the host's
free memory before anything is written, a large step is timed and the fit's time said, and a later
`max_pairs` that would not fit is capped and counted (`waldo_jax.splats.fit`)."""

import warnings

import jax
import pytest

from conftest import require_scene
from waldo_jax.cli import main
from waldo_jax.errors import MemoryBudgetError
from waldo_jax.scenes import load_scene
from waldo_jax.splats import fit

SHORT = fit.FitConfig(steps=30, capacity=2048, init_count=1024, densify_from=10, densify_every=10)


@pytest.fixture(scope="module")
def lego():
    return load_scene(require_scene("lego_tiny"), split="train", max_images=12)


def _fit(scene, config=SHORT, **kw):
    return fit.fit_splats(jax.random.key(0), scene, config, **kw)


@pytest.mark.slow  # compiles a step for XLA's memory analysis: 7.5-9.2 s on the 2-core CPU
def test_a_step_that_does_not_fit_is_refused_before_the_run_folder_is_made(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(fit, "host_memory_bytes", lambda: 1 << 20)  # 1 MiB free
    out = tmp_path / "run"
    code = main(["train", str(require_scene("lego_tiny")), "--model", "splat", "--steps", "20", "--out", str(out)])
    err = capsys.readouterr().err
    assert code != 0
    assert "100x100 a step" in err and "GiB" in err and "--downscale" in err and "--capacity" in err, err
    assert "Traceback" not in err
    assert not out.exists()


def test_a_capacity_whose_state_does_not_fit_is_refused_before_it_is_allocated(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(fit, "init_splats", None)  # never reached
    out = tmp_path / "run"
    args = ["train", str(require_scene("lego_tiny")), "--model", "splat", "--capacity", str(2**24), "--out", str(out)]
    monkeypatch.setattr("waldo_jax.errors.host_memory_bytes", lambda: 8 << 30)
    assert main(args) != 0
    err = capsys.readouterr().err
    assert "--capacity 16777216" in err and "GiB" in err and "Traceback" not in err, err
    assert not out.exists()
    assert fit.capacity_bytes(fit.FitConfig(capacity=2**24)) > 8 << 30 > fit.capacity_bytes(fit.FitConfig())


@pytest.mark.slow  # compiles a step (7 s), as the command's refusal above does
def test_the_refusal_names_the_image_size_and_the_memory(lego, monkeypatch):
    monkeypatch.setattr(fit, "host_memory_bytes", lambda: 1 << 20)
    called = []
    with pytest.raises(MemoryBudgetError, match=r"1 view of 100x100 a step, 2048 splats: a step needs"):
        _fit(lego, ready=lambda: called.append(1))
    assert not called  # nothing made before the check


@pytest.mark.slow
def test_a_large_step_is_timed_and_the_blocks_still_end_on_densifications(lego, monkeypatch):
    lines = []
    plain = _fit(lego, log=lines.append)
    assert not any("one step" in line for line in lines)
    monkeypatch.setattr(fit, "TIMED_STEP_PIXELS", 1)
    lines = []
    timed = _fit(lego, log=lines.append)
    said = [line for line in lines if "one step" in line]
    assert len(said) == 1 and "for 30 steps on this machine" in said[0], lines
    assert timed.history[0]["step_seconds"] > 0
    assert [row["step"] for row in timed.history] == [row["step"] for row in plain.history] == [0, 10, 20, 30]
    assert timed.steps == plain.steps == 30
    # The same steps with the same keys: the same fit up to the two programs' float rounding.
    assert abs(timed.history[-1]["loss"] - plain.history[-1]["loss"]) < 1e-3


@pytest.mark.slow
def test_a_max_pairs_that_would_not_fit_is_capped_and_counted(lego, monkeypatch):
    calls = []
    measured = fit._max_pairs

    def growing(*args):  # the real measure first, then a scene that needs 8 x more pairs a view
        calls.append(1)
        return measured(*args) * (1 if len(calls) == 1 else 8)

    monkeypatch.setattr(fit, "_max_pairs", growing)
    grown = _fit(lego)
    first = grown.history[0]["step_memory_bytes"]
    assert [row["max_pairs"] for row in grown.history[1:]] == [grown.history[1]["max_pairs"]] + [grown.max_pairs] * 2
    assert grown.max_pairs_capped == 0 and grown.step_memory > first
    calls.clear()
    monkeypatch.setattr(fit, "host_memory_bytes", lambda: first)  # the first program fits, no larger one
    with warnings.catch_warnings(record=True) as said:
        warnings.simplefilter("always")
        capped = _fit(lego, log=None)
    assert capped.max_pairs_capped == grown.max_pairs > capped.max_pairs == grown.history[1]["max_pairs"]
    assert [row.get("max_pairs_capped") for row in capped.history[1:]] == [grown.max_pairs, grown.max_pairs, None]
    assert sum("would not fit this machine's memory" in str(w.message) for w in said) == 2
    assert capped.steps == 30

"""The artefact guard (`opacity`), `constrained`, `weighted`, the CLI spec parser, and composition rules."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import waldo_jax  # noqa: F401
from waldo_jax.cli import main
from waldo_jax.criteria import (
    Criterion,
    CriterionContext,
    CriterionError,
    build_criterion,
    constrained,
    make_criterion,
    weighted,
)
from waldo_jax.criteria.combine import parse_guard, spec_names
from waldo_jax.criteria.composition import composition_from_map, composition_terms


def _rgba(colors, alphas, size=8):
    """Renders [P, size, size, 4] with flat colours [P, 3] and opacities [P]."""
    colors = np.asarray(colors, np.float32)[:, None, None, :] * np.ones((1, size, size, 1), np.float32)
    alphas = np.asarray(alphas, np.float32)[:, None, None, None] * np.ones((1, size, size, 1), np.float32)
    return np.concatenate([colors, alphas], axis=-1)


def _brightness(direction="max", value_range=(0.0, 1.0)):
    """A toy image criterion: the mean intensity."""
    return Criterion(
        params=(),
        name="bright",
        direction=direction,
        value_range=value_range,
        inputs="images",
        apply=lambda p, images: jnp.mean(images, axis=(1, 2, 3)),
        description="mean intensity",
    )


def test_opacity_is_the_mean_alpha_and_photographs_are_opaque():
    op = make_criterion("opacity")
    assert op.inputs == "renders" and op.direction == "max"
    renders = _rgba([[1, 0, 0], [0, 1, 0], [0, 0, 1]], [0.0, 0.5, 1.0])
    np.testing.assert_allclose(op.score_images(renders), [0.0, 0.5, 1.0], atol=1e-6)
    half = renders.copy()
    half[1, :4, :, 3] = 1.0
    half[1, 4:, :, 3] = 0.0
    assert float(op.score_images(half)[1]) == pytest.approx(0.5)
    np.testing.assert_array_equal(op.score_images(renders[..., :3]), [1.0, 1.0, 1.0])  # no alpha: a photograph
    nan = renders.copy()
    nan[2, 0, 0, 0] = np.nan
    assert float(op.score_images(nan)[2]) == 0.0


def test_constrained_gives_the_worst_score_where_the_guard_fails():
    guarded = constrained(_brightness(), make_criterion("opacity"), 0.9)
    assert guarded.name == "bright|opacity>=0.9" and guarded.inputs == "renders"
    renders = _rgba([[0.8] * 3, [0.6] * 3, [0.9] * 3], [1.0, 0.95, 0.2])
    tol = 1e-5  # a compiled float32 mean over 192 values (XLA's summation order): a few ulps of the sum
    np.testing.assert_allclose(guarded.score_images(renders), [0.8, 0.6, 0.0], atol=tol)
    # a "min" primary gets its upper bound; a "min" guard passes below the threshold
    low = constrained(_brightness("min"), make_criterion("opacity"), 0.9)
    np.testing.assert_allclose(low.score_images(renders), [0.8, 0.6, 1.0], atol=tol)
    dark_guard = constrained(_brightness(), _brightness("min"), 0.7)
    np.testing.assert_allclose(dark_guard.score_images(renders[..., :3]), [0.0, 0.6, 0.0], atol=tol)
    assert dark_guard.inputs == "images"
    with pytest.raises(CriterionError, match="no finite worst score"):
        constrained(_brightness(value_range=(-np.inf, 1.0)), make_criterion("opacity"), 0.5)


def test_weighted_normalises_by_value_range_and_direction():
    a = _brightness(value_range=(0.0, 1.0))
    b = _brightness("min", value_range=(0.0, 2.0))  # lower is better: 0 -> 1, 2 -> 0
    combined = weighted([a, b], [3.0, 1.0])
    assert combined.direction == "max" and combined.value_range == (0.0, 1.0)
    images = np.stack([np.full((4, 4, 3), v, np.float32) for v in (0.0, 0.5, 1.0)])
    expected = [0.75 * v + 0.25 * (1 - v / 2) for v in (0.0, 0.5, 1.0)]
    np.testing.assert_allclose(combined.score_images(images), expected, atol=1e-6)
    # the weights are leaves of the params: a sweep can vmap over them
    sweep = jax.vmap(lambda w: combined.apply((combined.params[0], w), jnp.asarray(_rgba([[0.5] * 3], [1.0]))))
    out = sweep(jnp.array([[1.0, 0.0], [0.0, 1.0]]))
    np.testing.assert_allclose(out[:, 0], [0.5, 0.75], atol=1e-6)
    with pytest.raises(CriterionError, match="not finite at both ends"):
        weighted([a, make_criterion("colorfulness")], [1, 1])
    with pytest.raises(CriterionError, match="one weight per criterion"):
        weighted([a], [1, 2])
    with pytest.raises(CriterionError, match="not all 0"):
        weighted([a, b], [0, 0])


@pytest.mark.slow
def test_combinations_take_pose_oracles():
    """Pose oracles combine (they were refused before): with each other into a pose criterion, with view
    criteria into a "posed" one; the values are checked in tests/test_waldo_found.py."""
    from waldo_jax.procedural import make_room

    context = CriterionContext(room=make_room(0))
    oracle = make_criterion("waldo_oracle", context)
    assert constrained(oracle, make_criterion("opacity"), 0.5).inputs == "posed"
    assert constrained(oracle, make_criterion("waldo_visible", context), 0.9).inputs == "poses"
    assert weighted([oracle, _brightness()], [1, 1]).inputs == "posed"
    assert build_criterion("weighted:waldo_oracle=1,opacity=1", context).inputs == "posed"
    with pytest.raises(CriterionError, match="needs the procedural Waldo room"):
        build_criterion("colorfulness", guards=["waldo_visible:0.9"])


def test_build_criterion_parses_the_command_line_forms():
    c = build_criterion("colorfulness", guards=["opacity:0.9"])
    assert c.name == "colorfulness|opacity>=0.9" and c.inputs == "renders"
    w = build_criterion("weighted:opacity=2,composition=1")
    assert w.name == "weighted:opacity=2,composition=1"
    assert parse_guard("opacity:0.25") == ("opacity", 0.25)
    # What a spec names, read from its text alone (a command checks it before it loads a scene).
    assert spec_names("weighted:opacity=2,composition=1", ["opacity:0.5"]) == ("opacity", "composition", "opacity")
    with pytest.raises(CriterionError, match="unknown criterion 'opacty'"):
        spec_names("colorfulness", ["opacty:0.5"])
    for bad in ("opacity", "opacity:x", ":0.5", "opacity:nan"):
        with pytest.raises(CriterionError, match="bad --guard"):
            parse_guard(bad)
    with pytest.raises(CriterionError, match="unknown criterion 'nope'"):
        build_criterion("weighted:nope=1")
    with pytest.raises(CriterionError, match="bad weight 'x'"):
        build_criterion("weighted:opacity=x,composition=1")
    with pytest.raises(CriterionError, match="bad weight ''"):  # every criterion states its weight
        build_criterion("weighted:opacity,composition=1")
    with pytest.raises(CriterionError, match="at least two criteria"):
        build_criterion("weighted:composition=1")
    with pytest.raises(CriterionError, match="names 'opacity' twice"):
        build_criterion("weighted:opacity=1,opacity=2")
    for stray in ("weighted:opacity=1,,composition=1", "weighted:opacity=1,composition=1,", "weighted:,opacity=1"):
        with pytest.raises(CriterionError, match="an empty item between commas"):  # was dropped in silence
            build_criterion(stray)
    with pytest.raises(CriterionError, match="at least two criteria"):
        build_criterion("weighted:")
    # Weights near float64's largest summed to infinity and normalised to 0 each: now as 1 : 1.
    huge = build_criterion("weighted:opacity=1e308,composition=1e308")
    np.testing.assert_array_equal(np.asarray(huge.params[1]), [0.5, 0.5])
    # A guard threshold that fails every view, or passes every view, is refused with the guard's range.
    for bad, verdict in (("opacity:2", "fails"), ("opacity:-1", "passes"), ("opacity:0", "passes")):
        with pytest.raises(CriterionError, match=f"lies in \\[0, 1\\], so the threshold {verdict} every view"):
            build_criterion("colorfulness", guards=[bad])
    assert build_criterion("colorfulness", guards=["opacity:1"]).name == "colorfulness|opacity>=1"


def test_guarded_criterion_runs_inside_a_jitted_search_step():
    """The combined criterion is a pytree whose static side hashes: one trace for two calls."""
    guarded = constrained(_brightness(), make_criterion("opacity"), 0.9)
    traces = []

    @jax.jit
    def step(criterion, rgba):
        traces.append(1)
        return criterion.apply(criterion.params, rgba)

    renders = jnp.asarray(_rgba([[0.5] * 3, [0.7] * 3], [1.0, 0.1]))
    step(guarded, renders)
    again = constrained(_brightness(), make_criterion("opacity"), 0.5)  # new threshold: a traced leaf
    np.testing.assert_allclose(step(again, renders), [0.5, 0.0], atol=1e-6)
    assert len(traces) <= 2  # toy criteria are new lambdas; the guard machinery adds no retrace
    np.testing.assert_allclose(step(guarded, renders), [0.5, 0.0], atol=1e-6)


@pytest.mark.slow
def test_score_cli_prints_json_in_input_order(tmp_path, capsys):
    import imageio.v3 as iio

    paths = []
    for i, (rgb, alpha) in enumerate([((255, 0, 0), 255), ((0, 0, 0), 0), ((40, 40, 40), 255)]):
        image = np.zeros((8, 8 + i, 4), np.uint8)  # three sizes: three batched calls
        image[..., :3] = rgb
        image[..., 3] = alpha
        paths.append(tmp_path / f"{i}.png")
        iio.imwrite(paths[-1], image)
    assert main(["score", "--criterion", "opacity", *map(str, paths), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out == {"criterion": "opacity", "direction": "max", "scores": [1.0, 0.0, 1.0]}
    assert main(["score", "--criterion", "colorfulness", str(paths[0]), str(paths[2])]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("# colorfulness (higher is better)")
    assert (
        float(lines[1].split()[0]) == pytest.approx(0.3 * np.hypot(255, 127.5), rel=1e-5)
        and abs(float(lines[2].split()[0])) < 1e-3
    )  # red vs grey
    assert main(["score", "--criterion", "colorfulness", str(tmp_path / "missing.png")]) == 1
    assert "no such image file" in capsys.readouterr().err
    (tmp_path / "junk.png").write_bytes(b"not an image")
    assert main(["score", "--criterion", "colorfulness", str(tmp_path / "junk.png")]) == 1
    assert "junk.png: not a readable image" in capsys.readouterr().err
    assert main(["score", "--criterion", "waldo_oracle", str(paths[0])]) == 1
    assert "'waldo_oracle' scores camera poses of the procedural room, not image files" in capsys.readouterr().err


def test_score_cli_decodes_a_bounded_batch_at_a_time(tmp_path, capsys, monkeypatch):
    """`waldo score` decodes at most SCORE_BATCH_BYTES of images at once (all of them were held at once, 0.8 GB
    a 4096x4096 photo): in batches of one the scores are those of one batch, up to float32 rounding (XLA
    vectorises a batch of 5 differently)."""
    import imageio.v3 as iio

    import waldo_jax.cli.score as score_cli

    rng = np.random.default_rng(0)
    paths = [tmp_path / f"{i}.png" for i in range(5)]
    for path in paths:
        iio.imwrite(path, rng.integers(0, 256, (16, 16, 3), dtype=np.uint8))
    argv = ["score", "--criterion", "colorfulness", *map(str, paths), "--json"]
    assert main(argv) == 0
    whole = json.loads(capsys.readouterr().out)["scores"]
    monkeypatch.setattr(score_cli, "SCORE_BATCH_BYTES", 16 * 16 * 16)  # one 16x16 image a batch
    assert main(argv) == 0
    assert json.loads(capsys.readouterr().out)["scores"] == pytest.approx(whole, rel=1e-6)


def _blob_map(cx, cy, radius=0.15, size=96):
    ys, xs = (np.mgrid[0:size, 0:size] + 0.5) / size
    return ((xs - cx) ** 2 + (ys - cy) ** 2 <= radius**2).astype(np.float32)


@pytest.mark.slow
def test_composition_prefers_power_points_to_corners_and_edges():
    power = float(composition_from_map(_blob_map(1 / 3, 1 / 3)))
    corner = float(composition_from_map(_blob_map(0.15, 0.15)))
    edge = float(composition_from_map(_blob_map(0.5, 0.15)))
    centre = float(composition_from_map(_blob_map(0.5, 0.5)))
    assert 1.0 <= corner < edge < power <= 5.0
    assert corner < centre < power
    for cx, cy in [(1 / 3, 2 / 3), (2 / 3, 1 / 3), (2 / 3, 2 / 3)]:  # the four power points are equivalent
        assert float(composition_from_map(_blob_map(cx, cy))) == pytest.approx(power, abs=1e-5)


@pytest.mark.slow
def test_composition_terms_on_analytic_maps():
    terms = {k: float(v) for k, v in composition_terms(_blob_map(1 / 3, 1 / 3)).items()}
    assert terms["thirds"] == pytest.approx(1.0, abs=1e-3)
    assert terms["balance"] == pytest.approx(np.exp(-(2 * (1 / 6) ** 2) / (2 * 0.25**2)), abs=2e-3)
    assert terms["emphasis"] == 1.0  # area pi 0.15^2 = 0.07, inside [0.05, 0.5]
    assert float(composition_terms(_blob_map(0.5, 0.5))["symmetry"]) == pytest.approx(1.0, abs=1e-6)
    empty = {k: float(v) for k, v in composition_terms(np.zeros((32, 32), np.float32)).items()}
    assert empty["emphasis"] == 0.0 and empty["symmetry"] == 0.0
    full = composition_terms(np.ones((32, 32), np.float32))
    assert float(full["emphasis"]) == 0.0  # a view that is all "subject" has no subject
    assert float(composition_from_map(np.zeros((32, 32), np.float32))) < float(
        composition_from_map(_blob_map(0.5, 0.5))
    )


@pytest.mark.parametrize(
    "flags, said",
    [
        (["--poses", "train"], "--poses has no effect on IMAGE files (it is for --source)"),
        (["--resolution", "16"], "--resolution has no effect on IMAGE files (it is for --source)"),
        (["--poses", "p.json", "--resolution", "16"], "--poses and --resolution have no effect on IMAGE files"),
        ([], None),
    ],
)
def test_render_flags_beside_image_files_say_they_change_nothing(tmp_path, capsys, flags, said):
    """--poses and --resolution set what `--source` renders: beside image files they were ignored in silence."""
    import imageio.v3 as iio

    iio.imwrite(tmp_path / "a.png", np.full((8, 8, 3), 90, np.uint8))
    assert main(["score", "--criterion", "colorfulness", str(tmp_path / "a.png"), *flags]) == 0
    warned = [line for line in capsys.readouterr().err.splitlines() if line.startswith("waldo: warning:")]
    assert warned == ([] if said is None else [next(w for w in warned if said in w)])

"""Camera paths (`waldo_jax.search.path`, `path_search`, `scenes.camera_paths`, `waldo path`): the spline,
the limits, the search (determinism, scan == loop, limits kept, failures never selected, better than
the straight path on the room), the exports' round trips and the command line."""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from waldo_jax.cameras import look_at
from waldo_jax.cli import main
from waldo_jax.criteria import CriterionContext, make_criterion
from waldo_jax.errors import SceneFormatError
from waldo_jax.pipeline import initial_scores, load_source
from waldo_jax.pipeline.experiment import seed_keys
from waldo_jax.scenes import read_poses_file
from waldo_jax.scenes.camera_paths import from_ngp, instant_ngp_camera_path, nerfstudio_camera_path, to_ngp
from waldo_jax.search import ExploreConfig, Initial, explore
from waldo_jax.search.path import catmull_rom, path_c2w, path_motion, sample_path, straight_path
from waldo_jax.search.path_search import (
    EVOSAX_STD_INIT,
    PathConfig,
    aggregate_scores,
    default_params,
    path_limits,
    path_method,
    search_path,
    search_path_loop,
    search_path_seeds,
)
from waldo_jax.types import Intrinsics, Pose

TINY = PathConfig(keyframes=3, frames=8, epochs=2, initial_paths=6, paths_per_epoch=6)


@pytest.fixture(scope="module", autouse=True)
def _release_compilations():
    """Drops this module's many compiled search programs at its end, so that the xdist worker that ran
    it does not carry them into the tests it runs next (a fresh-clone run twice saw that worker's XLA
    compile crash in test_train, right after this module was added; cause not established)."""
    yield
    jax.clear_caches()


def _keyframes(key, k=4):
    a, b = jax.random.split(key)
    return Pose(
        origin=jax.random.normal(a, (k, 3)),
        target=jax.random.normal(b, (k, 3)) + 5.0,
        up=jnp.tile(jnp.array([0.0, 1.0, 0.0]), (k, 1)),
    )


def test_catmull_rom_passes_through_its_points_and_frames_are_evenly_spaced():
    kf = _keyframes(jax.random.key(0), 5)
    np.testing.assert_allclose(catmull_rom(kf.origin, jnp.arange(5.0)), kf.origin, atol=1e-5)
    frames = sample_path(kf, 40)
    np.testing.assert_allclose(frames.origin[0], kf.origin[0], atol=1e-5)
    np.testing.assert_allclose(frames.origin[-1], kf.origin[-1], atol=1e-5)
    step = np.linalg.norm(np.diff(frames.origin, axis=0), axis=1) + np.linalg.norm(
        np.diff(frames.target, axis=0), axis=1
    )
    assert step.std() / step.mean() < 0.05  # arc-length spacing (a uniform parameter gives ~0.3 here)


def test_straight_path_moves_at_constant_speed_on_a_line():
    start = Pose(origin=jnp.zeros(3), target=jnp.array([0.0, 0.0, -1.0]), up=jnp.array([0.0, 1.0, 0.0]))
    end = Pose(origin=jnp.array([1.0, 0.0, 0.0]), target=jnp.array([1.0, 0.0, -1.0]), up=jnp.array([0.0, 1.0, 0.0]))
    c2w = path_c2w(straight_path(start, end, 4), 11)
    motion = path_motion(c2w, jnp.float32(1.0))
    np.testing.assert_allclose(motion.speed, 0.1, atol=1e-5)
    np.testing.assert_allclose(motion.turn, 0.0, atol=0.05)
    np.testing.assert_allclose(c2w[:, 1:3, 3], 0.0, atol=1e-6)


def test_limits_are_zero_exactly_when_kept():
    train = np.stack(
        [
            np.asarray(look_at(jnp.array([x, 0.0, 0.0]), jnp.array([x, 0.0, -1.0]), jnp.array([0, 1.0, 0])))
            for x in (0.0, 1.0)
        ]
    )
    limits = path_limits(train, max_speed=0.2, max_turn=5.0, min_opacity=0.5)

    def line(x0, x1):
        s = Pose(origin=jnp.array([x0, 0.0, 0.0]), target=jnp.array([x0, 0.0, -1.0]), up=jnp.array([0.0, 1.0, 0.0]))
        e = Pose(origin=jnp.array([x1, 0.0, 0.0]), target=jnp.array([x1, 0.0, -1.0]), up=jnp.array([0.0, 1.0, 0.0]))
        return path_c2w(straight_path(s, e, 3), 11)

    opaque = jnp.ones(11)
    assert float(limits.violation(line(0.0, 1.0), opaque)[0]) == 0.0  # 0.1 extent per frame
    assert float(limits.violation(line(0.0, 1.0), opaque.at[3].set(0.2))[0]) > 0.0  # an empty frame
    assert float(limits.violation(line(-0.5, 1.0), opaque)[0]) > 0.0  # leaves the box (margin 0.1)
    far = path_limits(train, max_speed=0.2, max_turn=5.0, min_travel=1.5)  # the line travels 1 extent
    assert float(far.violation(line(0.0, 1.0), opaque)[0]) > 0.0
    assert float(path_limits(train, max_speed=0.2, min_travel=0.9).violation(line(0.0, 1.0), opaque)[0]) == 0.0
    fast = line(0.0, 1.0).at[5, 0, 3].add(0.5)
    assert float(limits.violation(fast, opaque)[0]) > 0.0
    assert np.isnan(float(limits.violation(line(0.0, 1.0).at[2, 0, 3].set(jnp.nan), opaque)[0]))


@pytest.fixture(scope="module")
def room():
    source = load_source("procedural:0", resolution=16, views=12)
    criterion = make_criterion("waldo_oracle", CriterionContext(room=source.room))
    scores, _ = initial_scores(source, criterion)

    def frame_fn(c2w):
        return criterion.apply(criterion.params, c2w, source.intrinsics), jnp.ones(c2w.shape[0])

    return source, jax.tree_util.Partial(frame_fn), scores, path_limits(source.train_c2w)


@pytest.mark.parametrize("method", ["egps", "evosax:CMA_ES"])
def test_same_seed_same_path_scan_equals_loop(room, method):
    source, frame_fn, scores, limits = room
    args = (frame_fn, source.train_c2w, scores, source.train_c2w, limits, dataclasses.replace(TINY, method=method))
    a = search_path(jax.random.key(3), *args)
    b = search_path(jax.random.key(3), *args)
    loop = search_path_loop(jax.random.key(3), *args)
    other = search_path(jax.random.key(4), *args)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(x, y)  # bit for bit
    # The loop breeds the same keyframes; its frame scores agree to float rounding (XLA fuses the
    # frame maths of the two programs differently).
    np.testing.assert_array_equal(loop.population.keyframes.origin, a.population.keyframes.origin)
    np.testing.assert_allclose(loop.population.score, a.population.score, rtol=1e-5)
    assert not np.array_equal(other.population.keyframes.origin, a.population.keyframes.origin)
    assert a.population.epoch.tolist() == [0] * 6 + [1] * 6 + [2] * 6


def test_a_path_method_is_resolved_once_into_a_hashable_protocol_object():
    egps_method, cma = path_method("egps"), path_method("evosax:CMA_ES")
    assert cma is path_method("evosax:CMA_ES")  # one object per name: compilations are shared
    assert len({egps_method, cma, path_method("egps")}) == 2  # hashable, usable as a static argument
    assert (egps_method.name, cma.name) == ("egps", "evosax:CMA_ES")
    assert egps_method.init(None, None, None, None, None, None) == ()  # stateless: no state, no key used
    assert cma.init_fn is not None and cma.tell_fn is not None
    assert float(default_params(PathConfig(method="evosax:CMA_ES")).std_init) == np.float32(EVOSAX_STD_INIT)
    assert float(default_params(PathConfig()).rank_bias) == float(egps_method.default_params().rank_bias)
    with pytest.raises(ValueError, match="egps or evosax:NAME"):
        path_method("pibs")
    with pytest.raises(ValueError, match="unknown evosax strategy"):
        PathConfig(method="evosax:Nope")


@pytest.mark.parametrize("method", ["egps", "evosax:CMA_ES"])
def test_output_paths_keep_the_limits(room, method):
    source, frame_fn, scores, limits = room
    config = PathConfig(keyframes=3, frames=8, epochs=2, initial_paths=6, paths_per_epoch=6, method=method)
    out = search_path_seeds(seed_keys(0, 4), frame_fn, source.train_c2w, scores, source.train_c2w, limits, config)
    assert bool(jnp.all(out.found))
    for s in range(4):
        c2w = out.best_c2w[s]
        motion = path_motion(c2w, limits.extent)
        assert float(jnp.max(motion.speed)) <= float(limits.max_speed) + 1e-6
        assert float(jnp.max(motion.turn)) <= float(limits.max_turn) + 1e-4
        origin = c2w[:, :3, 3]
        assert bool(jnp.all((origin >= limits.low) & (origin <= limits.high)))
        # Every result slot keeps the limits; its score is the aggregate of its frames.
        top = out.top_indices[s][out.top_valid[s]]
        assert bool(jnp.all(out.population.violation[s][top] == 0.0))
        np.testing.assert_allclose(out.best_score[s], jnp.mean(out.best_frame_scores[s]), rtol=1e-5)
        assert np.all(np.diff(np.asarray(out.curve[s])) >= 0)  # best so far never falls
    if method.startswith("evosax:"):
        # Another program with the same strategy shape (a cached evosax object must hold no tracer),
        # and the soft-minimum aggregate end to end.
        softmin = search_path(
            jax.random.key(0),
            frame_fn,
            source.train_c2w,
            scores,
            source.train_c2w,
            limits,
            dataclasses.replace(config, aggregate="softmin"),
        )
        assert bool(softmin.found)


def test_a_failed_frame_is_never_selected(room):
    source, frame_fn, scores, limits = room

    def failing(c2w):  # NaN wherever the camera is right of x = 2: the path fails
        value, opacity = frame_fn(c2w)
        return jnp.where(c2w[:, 0, 3] > 2.0, jnp.nan, value + 10.0), opacity

    loose = path_limits(source.train_c2w, max_speed=1.0, max_turn=90.0)  # most paths keep these
    out = search_path(jax.random.key(0), failing, source.train_c2w, scores, source.train_c2w, loose, TINY)
    assert np.isnan(np.asarray(out.population.score)).any() and int(jnp.sum(out.population.feasible)) > 3
    assert bool(out.found) and np.isfinite(float(out.best_score))
    assert bool(jnp.all(out.best_c2w[:, 0, 3] <= 2.0))


def test_path_search_beats_the_straight_path_on_the_room_for_most_seeds(room):
    """From the top poses of an EGPS explore run (the paper's top-k: close together, so the straight path
    between the two best keeps the limits), the path search's best path scores higher (mean Waldo oracle
    over its frames) than the straight path between the two best poses for most seeds."""
    source, frame_fn, scores, limits = room
    result = explore(
        jax.random.key(0),
        lambda c2w: frame_fn(c2w)[0],
        Initial(c2w=source.train_c2w, scores=scores),
        "egps",
        ExploreConfig(children_per_epoch=20, epochs=3, min_separation=0.0),
    )
    anchors = np.asarray(result.top_c2w)[np.asarray(result.top_valid)]
    anchor_scores = np.asarray(frame_fn(jnp.asarray(anchors))[0])
    config = PathConfig(keyframes=3, frames=12, epochs=3, initial_paths=8, paths_per_epoch=12)
    out = search_path_seeds(seed_keys(0, 8), frame_fn, anchors, anchor_scores, source.train_c2w, limits, config)
    straight = np.asarray(out.population.score[:, 1])  # initial path 1 is the straight path
    assert bool(jnp.all(out.population.violation[:, 1] == 0.0))
    rate = float(np.mean(np.asarray(out.best_score) > straight))
    assert rate >= 0.75, (rate, np.asarray(out.best_score), straight)


# ---------------------------------------------------------------------------------------------
# Exports.


def _frames():
    kf = _keyframes(jax.random.key(1), 3)
    return np.asarray(path_c2w(kf, 10)), Intrinsics.create(64, 48, 50.0)


def test_nerfstudio_camera_path_has_the_documented_fields_and_reads_back(tmp_path):
    c2w, intrinsics = _frames()
    meta = nerfstudio_camera_path(c2w, intrinsics, fps=10)
    assert meta["render_width"] == 64 and meta["render_height"] == 48 and meta["seconds"] == 1.0
    entry = meta["camera_path"][0]
    assert len(entry["camera_to_world"]) == 16 and entry["aspect"] == 64 / 48
    assert entry["fov"] == pytest.approx(np.degrees(2 * np.arctan(24 / 50.0)))
    np.testing.assert_allclose(np.reshape(entry["camera_to_world"], (4, 4)), c2w[0], atol=1e-6)  # row by row
    transform = np.eye(4)
    transform[:3, :3] = np.asarray(look_at(jnp.zeros(3), jnp.array([1.0, 0.2, 0.3]), jnp.array([0, 0, 1.0])))[:3, :3]
    transform[:3, 3] = [0.3, -0.2, 0.1]
    for dataparser in (None, (transform, 0.25)):
        path = tmp_path / ("ns.json" if dataparser is None else "ns_world.json")
        path.write_text(json.dumps(nerfstudio_camera_path(c2w, intrinsics, 10, dataparser)))
        back, back_intrinsics, _ = read_poses_file(path, Intrinsics.create(8, 8, 8.0))
        np.testing.assert_allclose(back, c2w, atol=1e-5)
        assert (back_intrinsics.width, back_intrinsics.height) == (64, 48)
        np.testing.assert_allclose(float(back_intrinsics.fy), 50.0, rtol=1e-5)
    world = json.loads((tmp_path / "ns_world.json").read_text())
    moved = np.reshape(world["camera_path"][0]["camera_to_world"], (4, 4))
    np.testing.assert_allclose(moved[:3, 3], 0.25 * (transform @ c2w[0])[:3, 3], atol=1e-6)
    # A zoom or another projection, edited in, was rendered as frame 0's perspective camera without a word.
    for edit, says in (
        (lambda m: m["camera_path"][1].update(fov=5.0), "fields of view differ"),
        (lambda m: m.update(camera_type="equirectangular"), "perspective cameras only"),
    ):
        edited = nerfstudio_camera_path(c2w, intrinsics, fps=10)
        edit(edited)
        (tmp_path / "edited.json").write_text(json.dumps(edited))
        with pytest.raises(SceneFormatError, match=says):
            read_poses_file(tmp_path / "edited.json", Intrinsics.create(8, 8, 8.0))


def test_instant_ngp_path_round_trips_and_is_ngps_frame(tmp_path):
    c2w, intrinsics = _frames()
    np.testing.assert_allclose(from_ngp(to_ngp(c2w[3], 0.5, [0.1, 0.2, 0.3]), 0.5, [0.1, 0.2, 0.3]), c2w[3], atol=1e-6)
    # NGP: y and z columns flipped, position scaled and offset, then rows cycled xyz <- yzx.
    ngp = to_ngp(np.eye(4), 0.33, [0.5, 0.5, 0.5])
    np.testing.assert_allclose(ngp, [[0, -1, 0, 0.5], [0, 0, -1, 0.5], [1, 0, 0, 0.5]], atol=1e-12)
    meta = instant_ngp_camera_path(c2w, intrinsics, 10, 0.5, [0.1, 0.2, 0.3])
    key = meta["path"][0]
    assert set(key) >= {"R", "T", "fov", "timestamp"} and np.linalg.norm(key["R"]) == pytest.approx(1.0)
    assert [k["timestamp"] for k in meta["path"]] == sorted(k["timestamp"] for k in meta["path"])
    path = tmp_path / "ngp.json"
    path.write_text(json.dumps(meta))
    back, _, _ = read_poses_file(path, Intrinsics.create(8, 8, 8.0))
    np.testing.assert_allclose(back, c2w, atol=1e-5)


def test_camera_paths_of_other_tools_are_refused(tmp_path):
    c2w, intrinsics = _frames()
    for name, meta in (
        ("ns.json", nerfstudio_camera_path(c2w, intrinsics, 10)),
        ("ngp.json", instant_ngp_camera_path(c2w, intrinsics, 10)),
    ):
        del meta["waldo"]
        (tmp_path / name).write_text(json.dumps(meta))
        with pytest.raises(SceneFormatError, match="another tool"):
            read_poses_file(tmp_path / name, intrinsics)


# ---------------------------------------------------------------------------------------------
# The command line.

CLI_TINY = [
    "--resolution",
    "16",
    "--views",
    "8",
    "--keyframes",
    "3",
    "--frames",
    "8",
    "--epochs",
    "2",
    "--initial-paths",
    "5",
    "--paths-per-epoch",
    "4",
    "--max-speed",
    "0.5",
    "--max-turn",
    "60",
]


@pytest.mark.filterwarnings("ignore:os.fork:RuntimeWarning")  # imageio-ffmpeg reads the MP4 in a subprocess
def test_waldo_path_writes_exports_video_and_plots_that_render_back(tmp_path, capsys):
    out = tmp_path / "path"
    assert main(["path", "procedural:1", "--out", str(out), "--seed", "2", *CLI_TINY]) == 0
    for name in (
        "camera_path.json",
        "instant_ngp_path.json",
        "poses.json",
        "path.mp4",
        "path.gif",
        "path_sheet.png",
        "scores.png",
        "path_plot.png",
        "results.json",
    ):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    results = json.loads((out / "results.json").read_text())
    assert results["cost"] == {"frames": 8 * (5 + 2 * 4), "paths": 13, "frames_per_path": 8}
    assert results["found"]["kept_limits"] and results["found"]["violation"] == 0.0
    assert results["found"]["max_speed"] <= results["limits"]["max_speed_extent_per_frame"] + 1e-6
    assert set(results["references"]) == {"straight", "training"}
    assert results["criterion_caption"].startswith("waldo_oracle: share of the image")  # what the scores are
    assert results["criterion_caption"].endswith("; higher is better, in [0, 1]")
    import imageio.v3 as iio
    from PIL import Image

    assert iio.imread(out / "path.mp4").shape[0] == 8  # eight frames
    with Image.open(out / "path.gif") as gif:  # the default 12 fps: 83.3 ms, to the centisecond
        assert gif.n_frames == 8 and gif.info["duration"] == results["video"]["gif_frame_ms"] == 80
    # Each file records the world its poses are in; they load back through `waldo render --poses` for the
    # procedural room in silence, and say so for another room.
    for name, block in (
        ("camera_path.json", "waldo"),
        ("instant_ngp_path.json", "waldo"),
        ("poses.json", "waldo_path"),
    ):
        assert json.loads((out / name).read_text())[block]["source_world"] == "procedural:1", name
    capsys.readouterr()
    for name in ("camera_path.json", "instant_ngp_path.json"):
        rendered = tmp_path / f"render_{name}"
        assert (
            main(["render", "procedural:1", "--poses", str(out / name), "--out", str(rendered), "--resolution", "12"])
            == 0
        )
        assert len(list(rendered.glob("*.png"))) == 8
        assert "warning" not in capsys.readouterr().err
    other = ["render", "procedural:2", "--poses", str(out / "poses.json"), "--out", str(tmp_path / "other")]
    assert main([*other, "--resolution", "12"]) == 0
    assert "was written for procedural:1, not for procedural:2" in capsys.readouterr().err
    # Same seed, same path; the command refuses to overwrite.
    again = tmp_path / "again"
    assert main(["path", "procedural:1", "--out", str(again), "--seed", "2", *CLI_TINY]) == 0
    assert json.loads((again / "results.json").read_text())["found"] == results["found"]
    capsys.readouterr()
    assert main(["path", "procedural:1", "--out", str(out), *CLI_TINY]) == 1
    assert "not empty" in capsys.readouterr().err


@pytest.mark.parametrize(
    "transform, scale, says",
    [
        (np.diag([1.0, 1.0, -1.0, 1.0])[:3], 1.0, "not a rotation"),  # a mirror: exported rotations of det -1
        (np.diag([2.0, 2.0, 2.0, 1.0])[:3], 1.0, "not a rotation"),
        (np.eye(4)[:3], 1e300, "scale must be between"),  # exports of infinities, written as null, exit 0
        # a 3x4 of a negative scale had said "got shape [4, 4]" (its shape after the row was added)
        (np.eye(4)[:3], -1.0, "dataparser scale must be positive, got -1$"),
        (np.full((3, 4), np.nan), 1.0, "holds a value that is not a finite number"),
        (np.eye(3), 1.0, r"must be a 3x4 matrix, got shape \[3, 3\]"),
    ],
    ids=["mirror", "scaled", "scale-1e300", "scale-negative", "nan", "3x3"],
)
def test_a_dataparser_transform_that_is_no_rotation_or_of_an_absurd_scale_is_refused(transform, scale, says):
    from waldo_jax.scenes.camera_paths import read_dataparser_transform

    with pytest.raises(ValueError, match=says):
        read_dataparser_transform({"transform": transform.tolist(), "scale": scale})


def test_the_softmin_of_a_path_is_exact_at_every_temperature():
    """softmin_t = -t log mean exp(-s / t) against float64, from t = 1e-3 (near the least score) to 1e10 (the
    mean; the former form cancelled to 0 for every path in float32 there), signed by the direction; a NaN
    frame makes the path NaN, and a -inf frame -inf."""
    rng = np.random.default_rng(0)
    scores = rng.uniform(0, 1, (6, 12)).astype(np.float32)
    for direction in ("max", "min"):
        for t in (1e-3, 0.05, 1.0, 100.0, 1e10):
            config = dataclasses.replace(PathConfig(), aggregate="softmin", temperature=t, direction=direction)
            signed = (1.0 if direction == "max" else -1.0) * scores.astype(np.float64)
            x = -signed / t
            top = x.max(-1, keepdims=True)
            want = -t * (top[:, 0] + np.log(np.mean(np.exp(x - top), -1)))
            got = np.asarray(aggregate_scores(jnp.asarray(scores), config), np.float64)
            np.testing.assert_allclose((1.0 if direction == "max" else -1.0) * got, want, rtol=1e-5, atol=1e-6)
    config = dataclasses.replace(PathConfig(), aggregate="softmin")
    edge = np.array([[0.5, np.nan, 0.2], [0.5, -np.inf, 0.2]], np.float32)
    got = np.asarray(aggregate_scores(jnp.asarray(edge), config))
    assert np.isnan(got[0]) and got[1] == -np.inf
    with pytest.raises(ValueError, match="temperature must be a positive number of at most 1e"):
        dataclasses.replace(PathConfig(), temperature=1e31)


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--keyframes", "1"], "--keyframes must be between 2"),
        (["--method", "pibs"], "egps or evosax:NAME"),
        (["--method", "evosax:Nope"], "unknown evosax strategy"),
        (["--aggregate", "max"], "unknown --aggregate"),
        (["--max-speed", "0"], "--max-speed must be a positive"),
        (["--min-opacity", "2"], "--min-opacity must lie"),
        (["--budget", "huge"], "unknown --budget"),
        (["--from-explore", "nowhere"], "no poses.json"),
        (["--paths-per-epoch", "1"], "--paths-per-epoch must be between 2"),
        (
            [
                "--seeds",
                "1000",
                "--frames",
                "2000",
                "--initial-paths",
                "3",
                "--paths-per-epoch",
                "2",
                "--epochs",
                "1",
                "--min-travel",
                "0",
            ],
            "do not fit in memory",
        ),
    ],
)
def test_waldo_path_refuses_bad_flags_before_writing(tmp_path, capsys, flags, message):
    out = tmp_path / "bad"
    assert main(["path", "procedural", "--out", str(out), *flags]) == 1
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not out.exists()


# Refused by the memory one path's frames take for each of 1000 seeds, before the room renders anything.
MEMORY_REFUSED = ["--seeds", "1000", "--frames", "2000", "--initial-paths", "3", "--epochs", "1"]


@pytest.mark.parametrize(
    "flags, warned",
    [
        (["--budget", "high", "--paths-per-epoch", "2"], "--budget high has no effect: --paths-per-epoch 2 wins"),
        (["--budget", "low", "--paths-per-epoch", "2"], "--budget low has no effect: --paths-per-epoch 2 wins"),
        (["--budget", "high"], None),  # the budget derives 2 paths per epoch here
        (["--paths-per-epoch", "2"], None),
    ],
    ids=["high-and-paths", "low-and-paths", "budget-alone", "paths-alone"],
)
def test_waldo_path_says_when_paths_per_epoch_overrides_the_budget(tmp_path, capsys, flags, warned):
    """--budget only derives the paths per epoch: beside --paths-per-epoch it changed nothing, in silence
    (an explicit `--budget low` too). One warning line now comes before the run's own first line (here
    the refusal of 1000 seeds, before any work); either flag alone says nothing."""
    out = tmp_path / "bad"
    assert main(["path", "procedural", "--out", str(out), *MEMORY_REFUSED, *flags]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[-1].startswith("waldo: error: ") and "do not fit in memory" in lines[-1], lines
    said = [f"waldo: warning: {warned} (the budget only derives the paths per epoch)"] if warned else []
    assert lines[:-1] == said
    assert not out.exists()


def test_waldo_path_with_a_rendering_criterion_checks_opacity(tmp_path):
    """A criterion that scores images renders every frame of every candidate (with its opacity, which
    --min-opacity limits)."""
    out = tmp_path / "colour"
    assert (
        main(
            [
                "path",
                "procedural:1",
                "--out",
                str(out),
                "--criterion",
                "colorfulness",
                "--min-opacity",
                "0.5",
                "--method",
                "evosax:SNES",
                *CLI_TINY,
            ]
        )
        == 0
    )
    results = json.loads((out / "results.json").read_text())
    assert results["criterion"] == "colorfulness" and results["limits"]["min_opacity"] == pytest.approx(0.5)
    assert results["found"]["kept_limits"] and results["found"]["video_opacity_min"] >= 0.5
    assert all(np.isfinite(results["found"]["frame_scores"]))

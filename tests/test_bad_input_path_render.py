"""Bad input to `waldo path` (and what it exports for `waldo render`): work and memory set by its flags and
by the poses of --from-explore, refused before the search runs with the flag, the amount and the memory;
legal flags that change less than they say, warned about.

Each refusal runs `waldo_jax.cli.main(argv)` in-process at the smallest settings and checks one line
`waldo: error: ...` naming the flag, exit status 1 and no --out folder made.
"""

import argparse
import json
import re
from pathlib import Path

import numpy as np
import pytest

import waldo_jax.cli.path as path_cli
from waldo_jax.cli import main

# The smallest search: 2 keyframes, 8 frames, 3 + 4 paths of 16x16 renders of a room of 4 views.
SMALL = ["--frames", "8", "--keyframes", "2", "--resolution", "16", "--epochs", "1", "--initial-paths", "3"]
SMALL += ["--paths-per-epoch", "4", "--views", "4", "--quiet"]


def _parse(argv):
    """`waldo path`'s flags parsed as the CLI parses them (`--out` given where the test does not)."""
    parser = argparse.ArgumentParser()
    path_cli.add_command(parser.add_subparsers())
    return parser.parse_args(argv if "--out" in argv else [*argv, "--out", "unused"])


def _never(*args, **kwargs):
    raise AssertionError("the search ran before the refusal")


def _refuses(argv, expected, capsys, out, monkeypatch):
    monkeypatch.setattr(path_cli, "run_path", _never)  # without the check: fails at once, not hours later
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("waldo: error: ") and "\n" not in err and "Traceback" not in err, err
    assert expected in err, err
    assert not out.exists(), "the output folder was made before the refusal"


def _explore_folder(folder, count):
    """A `waldo explore` --out folder whose poses.json holds `count` poses of the room."""
    folder.mkdir()
    angles = np.linspace(0.0, 2 * np.pi, max(count, 1), endpoint=False)[:count]
    frames = []
    for a in angles:
        c, s = np.cos(a), np.sin(a)
        # Cameras on a ring around the room's centre, looking at it (OpenGL: the camera looks down -z).
        m = [[c, 0.0, s, 3.0 * s], [0.0, 1.0, 0.0, 1.5], [-s, 0.0, c, 3.0 * c], [0.0, 0.0, 0.0, 1.0]]
        frames.append({"transform_matrix": m})
    (folder / "poses.json").write_text(json.dumps({"frames": frames}))
    return folder


@pytest.mark.slow
def test_path_search_past_memory_is_refused_before_it_runs(tmp_path, capsys, monkeypatch):
    """The candidates every seed keeps (--initial-paths + --epochs x --paths-per-epoch paths, each its
    --frames scores) were never set against memory: `--frames 2000 --initial-paths 10000 --paths-per-epoch
    10000 --epochs 100` filled the 23 GiB machine and was killed. XLA's analysis of the compiled search is
    now checked first (the memory made small here)."""
    monkeypatch.setattr(path_cli, "host_memory_bytes", lambda: 10_000)
    out = tmp_path / "new"
    _refuses(["path", "procedural:0", *SMALL, "--out", str(out)], "the compiled search needs", capsys, out, monkeypatch)


@pytest.mark.slow
def test_path_video_past_memory_is_refused_before_the_search(tmp_path, capsys, monkeypatch):
    """The video frames (rendered after the search, all held at once) were not bounded: 2000 frames of
    4096x4096 would have ended hours later in a MemoryError (about 1.2 TiB)."""
    import waldo_jax.pipeline.sources as sources

    room_scene = sources.room_scene

    def small_rooms_only(*args, resolution, **kwargs):  # the room's training views at the video's size took minutes
        assert resolution <= 64, "the room rendered its training views at the video's size before its memory check"
        return room_scene(*args, resolution=resolution, **kwargs)

    monkeypatch.setattr(sources, "room_scene", small_rooms_only)
    out = tmp_path / "new"
    argv = ["path", "procedural:0", *SMALL, "--frames", "2000", "--video-resolution", "4096", "--out", str(out)]
    _refuses(argv, "--frames 2000 x --video-resolution 4096", capsys, out, monkeypatch)


def test_path_from_explore_anchors_past_memory_are_refused(tmp_path, capsys, monkeypatch):
    """The poses of --from-explore are rendered and scored in one call: their count (read from the file)
    is set against memory before the source renders anything (the memory made small here)."""
    monkeypatch.setattr(path_cli, "memory_bytes", lambda: 100_000)
    explore = _explore_folder(tmp_path / "explore", 8)
    out = tmp_path / "new"
    argv = ["path", "procedural:0", *SMALL, "--from-explore", str(explore), "--out", str(out)]
    _refuses(argv, f"--from-explore {explore}: its poses.json holds 8 poses", capsys, out, monkeypatch)


def test_path_from_explore_with_one_pose_names_the_flag(tmp_path, capsys, monkeypatch):
    """One pose cannot start a path of two keyframes: said by --from-explore before the room loads (it was
    a message about "anchor poses with a finite score" after the source had loaded)."""
    explore = _explore_folder(tmp_path / "explore", 1)
    out = tmp_path / "new"
    argv = ["path", "procedural:0", *SMALL, "--from-explore", str(explore), "--out", str(out)]
    _refuses(argv, f"--from-explore {explore}: its poses.json holds 1 pose;", capsys, out, monkeypatch)


@pytest.mark.parametrize(
    "flags, expected",
    [
        (["--max-turn", "200"], "--max-turn 200: no frame turns more than 180 degrees"),
        (["--fps", "100"], "--fps 100: path.gif shows each frame 20 ms, 50 frames a second"),
        (["--fps", "40"], "--fps 40: path.gif shows each frame 20 ms, 50 frames a second"),
        # Flags off their default that the others make change nothing (ran in silence).
        (["--temperature", "0.1"], "--temperature 0.1 has no effect: it is for --aggregate softmin"),
        (["--initial", "renders", "--from-explore", "x"], "--initial renders has no effect: the anchors are"),
    ],
)
def test_path_flags_that_change_less_than_they_say_are_warned(flags, expected):
    """Degenerate but legal: a turn limit past 180 degrees limits nothing; a GIF cannot play past 50 fps
    (whole centiseconds, at least 2); a flag the others make idle. All ran in silence. Checked on the flags
    alone (`_config_from_args`), before any work."""
    with pytest.warns(UserWarning, match=re.escape(expected)):
        path_cli._config_from_args(_parse(["path", "procedural:0", *SMALL, *flags, "--out", "unused"]))


def test_path_usual_flags_are_not_warned(recwarn):
    """The defaults (12 fps: 80 ms GIF frames, 12.5 fps; a 5 degree turn limit), the usual video rates and a
    softmin's own --temperature: no warning."""
    path_cli._config_from_args(_parse(["path", "procedural:0", "--out", "unused"]))
    for fps in ("24", "25", "30"):  # GIF frames of 40, 40 and 30 ms: 25, 25 and 33.3 fps
        path_cli._config_from_args(_parse(["path", "procedural:0", "--fps", fps, "--out", "unused"]))
    path_cli._config_from_args(_parse(["path", "procedural:0", "--aggregate", "softmin", "--temperature", "0.1"]))
    assert not [w for w in recwarn if issubclass(w.category, UserWarning)]


def _exported_paths():
    """A 3-frame camera path of rigid poses as `waldo path` exports it for nerfstudio and Instant-NGP."""
    from waldo_jax.scenes.camera_paths import NgpFrame, instant_ngp_camera_path, nerfstudio_camera_path
    from waldo_jax.types import Intrinsics

    c2w = np.stack([np.eye(4)] * 3)
    c2w[:, 0, 3] = [0.0, 0.5, 1.0]
    intrinsics = Intrinsics.create(32, 24, 30.0)
    ns = nerfstudio_camera_path(c2w, intrinsics, fps=10)
    ngp = instant_ngp_camera_path(c2w, intrinsics, 10, frame=NgpFrame.create())
    return json.loads(json.dumps(ns)), json.loads(json.dumps(ngp)), intrinsics


def _set_fov(entries, value):
    for entry in entries:
        entry["fov"] = value


# (name, edit of the nerfstudio dict or of the Instant-NGP one, words of the message). Each was read as a
# number or a flag it is not (fov "60", render_width 16.9, ngp_from_mitsuba "false" -> True, world "mars"
# -> the scene's frame, frames -3 or 10^7), or ended in a KeyError / TypeError text, with exit 0 or a trace.
CAMERA_PATH_CASES = [
    ("ns-fov-text", lambda ns, ngp: _set_fov(ns["camera_path"], "60"), "camera_path 0 'fov' must be a number"),
    ("ns-fov-bool", lambda ns, ngp: _set_fov(ns["camera_path"], True), "camera_path 0 'fov' must be a number"),
    ("ns-width-text", lambda ns, ngp: ns.update(render_width="16"), "'render_width' must be a whole number"),
    ("ns-width-fraction", lambda ns, ngp: ns.update(render_width=16.9), "'render_width' must be a whole number"),
    ("ns-width-huge", lambda ns, ngp: ns.update(render_width=10**7), "'render_width' must be a whole number"),
    ("ns-no-width", lambda ns, ngp: ns.pop("render_width"), "'render_width' must be a whole number"),
    ("ns-entries-text", lambda ns, ngp: ns.update(camera_path="abc"), "'camera_path' must be a non-empty list"),
    ("ns-entry-list", lambda ns, ngp: ns.update(camera_path=[[1, 2]]), "'camera_path' entry 0 must be an object"),
    (
        "ns-matrix-text",
        lambda ns, ngp: ns["camera_path"][0].update(camera_to_world=["1"] * 16),
        "camera_path 0 'camera_to_world' must be 16 numbers",
    ),
    (
        "ns-matrix-missing",
        lambda ns, ngp: ns["camera_path"][1].pop("camera_to_world"),
        "camera_path 1 'camera_to_world' must be 16 numbers",
    ),
    ("ns-world-other", lambda ns, ngp: ns["waldo"].update(world="mars"), "'world' must be 'scene' or 'nerfstudio'"),
    (
        "ns-pose-scale-text",
        lambda ns, ngp: ns["waldo"].update(world="nerfstudio", pose_transform=np.eye(4)[:3].tolist(), pose_scale="1"),
        "'pose_scale' must be a number",
    ),
    ("ngp-frames-negative", lambda ns, ngp: ngp["waldo"].update(frames=-3), "'frames' must be a whole number"),
    ("ngp-frames-past-the-path", lambda ns, ngp: ngp["waldo"].update(frames=10**7), "'frames' must be a whole"),
    ("ngp-frames-text", lambda ns, ngp: ngp["waldo"].update(frames="3"), "'frames' must be a whole number"),
    ("ngp-mitsuba-text", lambda ns, ngp: ngp["waldo"].update(ngp_from_mitsuba="false"), "must be true or false"),
    ("ngp-scale-text", lambda ns, ngp: ngp["waldo"].update(ngp_scale="0.1"), "'ngp_scale' must be a number"),
    ("ngp-offset-short", lambda ns, ngp: ngp["waldo"].update(ngp_offset=[0.5, 0.5]), "'ngp_offset' must be 3"),
    ("ngp-rotation-text", lambda ns, ngp: ngp["path"][0].update(R=["0", "0", "0", "1"]), "keyframe 0 'R' must be"),
    ("ngp-position-nan", lambda ns, ngp: ngp["path"][0].update(T=[float("nan"), 0, 0]), "keyframe 0 'T' must be"),
    ("ngp-width-fraction", lambda ns, ngp: ngp["waldo"].update(render_width=16.5), "'render_width' must be a whole"),
    ("ngp-entry-number", lambda ns, ngp: ngp["path"].__setitem__(0, 5), "'path' entry 0 must be an object"),
]


@pytest.mark.parametrize("edit, says", [c[1:] for c in CAMERA_PATH_CASES], ids=[c[0] for c in CAMERA_PATH_CASES])
def test_every_field_of_a_camera_path_is_checked_by_its_key(edit, says):
    """`waldo render --poses` and `waldo path` read back the camera paths they export: every value is taken
    by its key, a number as a number, a count as a whole number in its range, a flag as true or false."""
    from waldo_jax.scenes.camera_paths import read_camera_path

    ns, ngp, intrinsics = _exported_paths()
    for meta in (ns, ngp):  # the undamaged exports read back
        assert read_camera_path(meta, intrinsics)[0].shape == (3, 4, 4)
    edit(ns, ngp)
    damaged = ns if ns != _exported_paths()[0] else ngp
    with pytest.raises(ValueError, match=re.escape(says)):
        read_camera_path(damaged, intrinsics)


def test_a_poses_file_is_checked_for_its_bottom_row_and_counted_before_its_poses(tmp_path):
    """A `transform_matrix` bottom row of [1, 2, 3, 4] was dropped unread (rendered, exit 0); a file of more
    poses than `waldo render` takes was checked pose by pose first (10^6: 49 s and 2 GB to be refused)."""
    from waldo_jax.errors import WaldoError
    from waldo_jax.scenes import read_poses_file
    from waldo_jax.types import Intrinsics

    intrinsics = Intrinsics.create(32, 24, 30.0)
    bottom = np.eye(4).tolist()
    bottom[3] = [1.0, 2.0, 3.0, 4.0]
    path = tmp_path / "poses.json"
    path.write_text(json.dumps({"frames": [{"transform_matrix": np.eye(4).tolist()}, {"transform_matrix": bottom}]}))
    with pytest.raises(WaldoError, match=re.escape("frame 1") + ".*bottom row"):
        read_poses_file(path, intrinsics)
    path.write_text(json.dumps({"frames": [{"transform_matrix": "not checked"}] * 5}))
    with pytest.raises(WaldoError, match="5 poses; at most 4 are read at once"):
        read_poses_file(path, intrinsics, max_poses=4)
    # waldo's Instant-NGP path of 3 frames holds 4 keyframes (the last repeats the last frame): 3 are counted.
    ngp = _exported_paths()[1]
    assert len(ngp["path"]) == 4
    path.write_text(json.dumps(ngp))
    assert len(read_poses_file(path, intrinsics, max_poses=3)[0]) == 3


@pytest.mark.parametrize(
    "meta, key",
    [({"scale": 10**400}, "scale"), ({"offset": [0, 10**400, 0]}, "offset"), ({"offset": -(10**400)}, "offset")],
)
def test_an_ngp_frame_number_past_float64_is_refused_by_its_key(meta, key):
    """JSON integers have no length bound, and `math.isfinite(10**400)` raised OverflowError, past the
    ValueError its callers catch. waldo's JSON reader turns such integers into floats (inf) already; this
    is the function itself, called with Python's numbers (`errors.is_finite_number`)."""
    from waldo_jax.scenes.tool_frames import ngp_frame

    with pytest.raises(ValueError, match=f"'{key}' must be a finite number, got int -?1000"):
        ngp_frame(meta)


@pytest.mark.parametrize("scale", ["0.5", True, 10**400])
def test_a_dataparser_scale_that_is_no_number_is_refused(scale):
    """nerfstudio's dataparser_transforms.json `scale` of "0.5" or true was read as 0.5 or 1."""
    from waldo_jax.scenes.tool_frames import read_dataparser_transform

    with pytest.raises(ValueError, match="dataparser scale must be a number"):
        read_dataparser_transform({"transform": np.eye(4)[:3].tolist(), "scale": scale})


def _path_files(folder, **names):
    """camera_path.json, instant_ngp_path.json and poses.json of a 3-frame path into `folder`, as `waldo path`
    writes them, their block naming the path's SOURCE and world by `names` (`source`, `source_world`; none:
    an older file or another tool's)."""
    from waldo_jax import io

    folder.mkdir(parents=True)
    ns, ngp, intrinsics = _exported_paths()
    ns["waldo"].update(names)
    ngp["waldo"].update(names)
    (folder / "camera_path.json").write_text(json.dumps(ns))
    (folder / "instant_ngp_path.json").write_text(json.dumps(ngp))
    c2w = np.stack([np.eye(4)] * 3)
    names_of_frames = [f"frame_{i:04d}" for i in range(3)]
    io.write_transforms(folder / "poses.json", c2w, intrinsics, names_of_frames, extra={"waldo_path": names})
    return folder


RENDER_SMALL = ["--resolution", "8", "--samples", "4", "--quiet"]


@pytest.mark.slow
@pytest.mark.parametrize("name", ["camera_path.json", "instant_ngp_path.json", "poses.json"])
def test_a_path_rendered_on_another_source_than_its_own_says_so(tmp_path, capsys, name):
    """`waldo render --poses` of a path found on procedural:1 rendered procedural:2 in silence: the same
    numbers, another room. The file names its world; a render in another one is one warning line."""
    poses = _path_files(tmp_path / "path", source="procedural:1", source_world="procedural:1") / name
    assert main(["render", "procedural:2", "--poses", str(poses), *RENDER_SMALL, "--out", str(tmp_path / "f")]) == 0
    assert capsys.readouterr().err.strip() == (
        f"waldo: warning: --poses {poses} was written for procedural:1, not for procedural:2: its poses place "
        "the cameras in another scene's world"
    )


@pytest.mark.slow
def test_a_path_rendered_on_its_own_source_or_naming_none_says_nothing(tmp_path, capsys):
    """The room the path was found on, named either way, and a file that names no source: no warning."""
    own = _path_files(tmp_path / "own", source="procedural:1", source_world="procedural:1") / "camera_path.json"
    unnamed = _path_files(tmp_path / "unnamed", source="procedural:1") / "camera_path.json"  # an older file
    for i, argv in enumerate(
        (["procedural:1", "--poses", str(own)], ["procedural", "--seed", "1", "--poses", str(own)])
        + (["procedural:2", "--poses", str(unnamed)],)
    ):
        assert main(["render", *argv, *RENDER_SMALL, "--out", str(tmp_path / f"frames{i}")]) == 0
        assert capsys.readouterr().err == "", argv


def test_a_sources_world_is_its_room_its_trained_scene_or_its_splat_file(tmp_path, monkeypatch):
    """The world recorded beside a path's poses: a room by its seed, also for a NeRF trained on it (the
    poses line up); another run by its scene's folder, resolved (through a link, or given by its file);
    splats by their file, or where waldo fitted them by their scene's. Read back from each block waldo
    writes; a world that is no text is none."""
    from types import SimpleNamespace

    from waldo_jax.pipeline.sources import source_world
    from waldo_jax.scenes.camera_paths import recorded_world

    def source(kind, **info):
        return SimpleNamespace(kind=kind, info=info)

    scene = tmp_path / "scenes" / "fox"
    scene.mkdir(parents=True)
    (scene / "transforms.json").write_text("{}")
    (tmp_path / "link").symlink_to(scene)
    monkeypatch.chdir(tmp_path / "scenes")
    assert source_world(source("procedural", procedural_seed=3)) == "procedural:3"
    assert source_world(source("run", procedural_seed=3, scene_path="procedural")) == "procedural:3"
    paths = (
        str(scene),
        str(scene / "transforms.json"),
        str(tmp_path / "link"),
        str(tmp_path / "link" / "transforms.json"),
    )
    worlds = {source_world(source("run", scene_path=p)) for p in paths}
    assert worlds == {str(scene.resolve())}
    assert source_world(source("run", scene_path=str(tmp_path / "other"))) != str(scene.resolve())
    assert source_world(source("run")) is None
    ply = scene / "point_cloud.ply"
    assert source_world(source("splats", splat_file=str(ply))) == str(ply)
    assert source_world(source("splats", splat_file=str(ply), scene_path=str(scene))) == str(scene.resolve())  # a fit
    for block in ("waldo", "waldo_path", "waldo_explore"):
        assert recorded_world({block: {"source": "a", "source_world": "procedural:3"}}) == "procedural:3"
    assert recorded_world({"waldo": {"source_world": 3}}) is None
    assert recorded_world({"waldo": {"source": "procedural:3"}}) is None  # written before worlds were
    assert recorded_world({"frames": []}) is None and recorded_world([]) is None


def test_a_world_that_cannot_be_told_is_none_and_a_world_not_on_this_machine_says_nothing(tmp_path, recwarn):
    """A relative scene path (an older run's: relative to a folder no longer known), a link loop: no world,
    and no traceback after the search. A recorded world that is a path not on this machine (a file from
    another machine, a scene moved since) warns nothing; one that is, or another room, warns once. A splat
    fit's .ply given alone takes its train.json's scene."""
    import warnings as stdlib_warnings
    from types import SimpleNamespace

    from waldo_jax.pipeline.sources import source_world, warn_other_world

    (tmp_path / "loop").symlink_to(tmp_path / "loop")
    for info in ({"scene_path": "scenes/fox"}, {"scene_path": str(tmp_path / "loop" / "x")}):
        assert source_world(SimpleNamespace(kind="run", info=info)) is None, info
    fit = SimpleNamespace(kind="splats", info={"splat_file": str(tmp_path / "a.ply"), "fit_scene_path": str(tmp_path)})
    assert source_world(fit) == str(tmp_path.resolve())
    with stdlib_warnings.catch_warnings():
        stdlib_warnings.simplefilter("error")
        warn_other_world("--poses f", str(tmp_path / "not-here"), "procedural:1", "procedural:1")
        warn_other_world("--poses f", None, "procedural:1", "procedural:1")
        warn_other_world("--poses f", "procedural:1", None, "run")
        warn_other_world("--poses f", "procedural:1", "procedural:1", "run")
    for recorded in (str(tmp_path), "procedural:2"):
        with pytest.warns(UserWarning, match=f"--poses f was written for {recorded}, not for procedural:1 \\(run\\)"):
            warn_other_world("--poses f", recorded, "procedural:1", "run")


def test_a_far_origin_is_told_to_rescale_only_where_the_poses_are_the_scenes_own(tmp_path):
    """`rigid_problem`'s far-origin message names a remedy only where one is given: a scene's own cameras
    (`check_rigid`: rescale the scene); a results.json the viewer reads or a poses file to render says no
    more than what is wrong."""
    from waldo_jax.errors import SceneFormatError
    from waldo_jax.scenes import read_poses_file
    from waldo_jax.scenes.common import check_rigid, rigid_problem
    from waldo_jax.types import Intrinsics
    from waldo_jax.viewer.fields import check_poses

    far = np.eye(4)
    far[0, 3] = 1e9
    plain = "camera origin has a coordinate of 1e+09, beyond the 1e+06 that float32 geometry handles"
    assert rigid_problem(np.stack([np.eye(4), far])) == (1, plain)
    with pytest.raises(SceneFormatError, match=re.escape(f"frame 3: {plain} (rescale the scene)")):
        check_rigid(far, tmp_path / "transforms.json", "frame 3")
    with pytest.raises(ValueError, match=re.escape(f"[1]: {plain}") + "$"):
        check_poses([np.eye(4).tolist(), far.tolist()], ValueError)
    (tmp_path / "poses.json").write_text(json.dumps({"frames": [{"transform_matrix": far.tolist()}]}))
    with pytest.raises(SceneFormatError, match=re.escape(f"frame 0 transform_matrix: {plain}") + "$"):
        read_poses_file(tmp_path / "poses.json", Intrinsics.create(8, 8, 8.0))


def test_numbers_past_float64_given_as_python_integers_are_not_finite():
    """`errors.is_finite_number`: JSON's integers have no bound and `math.isfinite(10**400)` raises
    OverflowError; the viewer's poses and cameras.json's focal lengths, called with Python's numbers (not
    through waldo's JSON reader, which turns them into inf), refuse them by name."""
    from waldo_jax.errors import SceneFormatError, is_finite_number
    from waldo_jax.splats.cameras_json import _camera_intrinsics
    from waldo_jax.viewer.fields import check_poses

    assert (
        is_finite_number(1) and is_finite_number(-2.5) and is_finite_number(np.float32(3)) and is_finite_number(10**300)
    )
    for value in (10**400, -(10**400), float("nan"), float("inf"), True, np.bool_(True), "1", None, [1]):
        assert not is_finite_number(value), value
    pose = np.eye(4).tolist()
    pose[1][3] = 10**400
    with pytest.raises(ValueError, match=r"\[1\]: pose has non-finite values"):
        check_poses([np.eye(4).tolist(), pose], ValueError)
    camera = {"width": 64, "height": 48, "fx": 10**400, "fy": 50.0}
    with pytest.raises(SceneFormatError, match="fx must be a finite focal length"):
        _camera_intrinsics(camera, Path("cameras.json"), "camera 0")


@pytest.mark.slow  # loads the room three times (3 s each); `warn_other_world` itself is tested above
@pytest.mark.parametrize("recorded, warned", [("procedural:1", True), ("procedural:0", False), (None, False)])
def test_from_explore_poses_of_another_scenes_world_are_said(tmp_path, capsys, monkeypatch, recorded, warned):
    """--from-explore's poses start the path in the SOURCE's world: an explore of another room (its
    poses.json's `source_world`) is one warning line once the source has loaded; its own room, or a file
    that records no world, none."""
    from waldo_jax.errors import WaldoError

    def stop(*args, **kwargs):
        raise WaldoError("stopped before the search")

    monkeypatch.setattr(path_cli, "run_path", stop)
    explore = _explore_folder(tmp_path / "explore", 4)
    if recorded is not None:
        poses = json.loads((explore / "poses.json").read_text())
        poses["waldo_explore"] = {"source": recorded, "source_world": recorded}
        (explore / "poses.json").write_text(json.dumps(poses))
    assert main(["path", "procedural:0", *SMALL, "--from-explore", str(explore), "--out", str(tmp_path / "o")]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[-1] == "waldo: error: stopped before the search"
    said = f"waldo: warning: --from-explore {explore} was written for procedural:1, not for procedural:0: its poses "
    assert lines[:-1] == ([said + "place the cameras in another scene's world"] if warned else [])

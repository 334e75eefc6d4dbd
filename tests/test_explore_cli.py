"""`waldo explore` and `waldo demo` end to end at tiny settings: files, fields, determinism, errors."""

import json
import warnings

import imageio.v3 as iio
import numpy as np
import pytest

from waldo_jax.cli import build_parser, main
from waldo_jax.cli.explore import explore_config_from_args
from waldo_jax.criteria import CRITERIA, CriterionContext, build_criterion, make_criterion
from waldo_jax.io import read_image
from waldo_jax.pipeline.demo import DEMO_ROOM_SEED, DemoSettings, run_demo
from waldo_jax.pipeline.sources import NERF_GRADIENT_COST
from waldo_jax.pipeline.experiment import initial_scores
from waldo_jax.errors import WaldoError
from waldo_jax.procedural import make_room, waldo_coverage
from waldo_jax.pipeline.sources import procedural_source, run_source
from waldo_jax.types import Intrinsics

TINY = ["--resolution", "16", "--views", "8", "--epochs", "2", "--children-per-epoch", "6", "--top-k", "4", "--quiet"]


def explore(out, *extra):
    return main(["explore", "procedural:1", "--out", str(out), *TINY, *extra])


@pytest.fixture(scope="module")
def egps_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("explore") / "egps"
    assert explore(out, "--method", "egps", "--seed", "3") == 0
    return out, json.loads((out / "results.json").read_text())


def test_results_json_has_what_the_issue_lists(egps_run):
    out, r = egps_run
    for key in (
        "method",
        "criterion",
        "direction",
        "seed",
        "budget",
        "n_train",
        "n_generated",
        "scores_train",
        "scores_generated",
        "cvir",
        "mcvir",
        "topk",
        "epochs",
        "seconds",
    ):
        assert key in r, key
    assert (r["method"], r["criterion"], r["direction"], r["seed"]) == ("egps", "waldo_oracle", "max", 3)
    assert r["budget"] is None  # --children-per-epoch 6 set the children, not the (default) budget
    assert r["criterion_caption"] == (
        "waldo_oracle: share of the image showing un-occluded Waldo (exact, procedural "
        "room); higher is better, in [0, 1]"
    )
    assert r["n_train"] == 8 and len(r["scores_train"]) == 8
    assert r["n_generated"] == 12 == len(r["scores_generated"]) and r["generated_epochs"] == [1] * 6 + [2] * 6
    assert len(r["epochs"]) == 3 and r["epochs"][0]["best"] == max(r["scores_train"])
    scores = [t["score"] for t in r["topk"]]
    assert len(scores) == 4 and scores == sorted(scores, reverse=True)
    everything = r["scores_train"] + r["scores_generated"]
    assert scores[0] == max(everything) == r["epochs"][-1]["best"]
    # CVIR: % gain of the best over the best training score (the paper's equation).
    best_train = max(r["scores_train"])
    assert r["cvir"] == pytest.approx(100.0 * (scores[0] - best_train) / best_train, rel=1e-4)


def test_files_are_written_and_consistent(egps_run):
    out, r = egps_run
    for name in ("contact_sheet.png", "pose_cloud.png", "poses.json", "topk/00.png", "topk/03.png"):
        assert (out / name).is_file(), name
    assert iio.imread(out / "topk" / "00.png").shape == (16, 16, 3)
    poses = json.loads((out / "poses.json").read_text())
    assert [f["file_path"] for f in poses["frames"]] == [t["image"] for t in r["topk"]]
    assert poses["waldo_explore"]["source_world"] == "procedural:1"  # `render --poses` elsewhere says so
    np.testing.assert_allclose(
        [f["transform_matrix"] for f in poses["frames"]], [t["c2w"] for t in r["topk"]], atol=1e-6
    )
    # The oracle's score of the saved pose is the reported score.
    room = make_room(1)
    intr = Intrinsics.from_fov(16, 16, np.radians(60.0))
    c2w = np.asarray(r["topk"][0]["c2w"], np.float32)
    assert float(waldo_coverage(room, c2w, intr)) == pytest.approx(r["topk"][0]["score"], rel=1e-4, abs=1e-7)


def _separation(a, b, frame):
    from waldo_jax.search.views import SceneFrame, view_separation

    frame = SceneFrame(focus=np.asarray(frame["focus"]), up=np.asarray(frame["up"]), radius=np.float32(frame["radius"]))
    return float(view_separation(np.asarray(a, np.float32), np.asarray(b, np.float32), frame))


def test_topk_are_different_shots_and_the_paper_topk_is_kept(egps_run, tmp_path):
    out, r = egps_run
    assert r["min_separation"] == 20.0 and len(r["topk"]) == 4 and len(r["paper_topk"]) == 4
    frame = r["archive"]["frame"]
    for i, a in enumerate(r["topk"]):  # every pair of the written top-k is at least 20 degrees apart
        for b in r["topk"][i + 1 :]:
            assert _separation(a["c2w"], b["c2w"], frame) >= 20.0
        assert set(a["view"]) == {"azimuth", "elevation", "distance"}
    assert r["topk"][0]["c2w"] == r["paper_topk"][0]["c2w"] and r["paper_topk"][0]["in_topk"]
    paper = [t["score"] for t in r["paper_topk"]]
    everything = sorted(r["scores_train"] + r["scores_generated"], reverse=True)
    assert paper == pytest.approx(everything[:4], rel=1e-6)  # the paper's top-k: the 4 best, however alike
    best_train = max(r["scores_train"])
    shots = [t["score"] for t in r["topk"]]
    assert r["dcvir"] == pytest.approx(100.0 * (np.mean(shots) - best_train) / best_train, rel=1e-4)
    assert r["shots_beating_train"] == sum(v > best_train for v in shots)
    assert 1 <= r["paper_topk_shots"] <= 4
    archive = r["archive"]
    assert archive["grid"]["cells"] == 96 and archive["cells_filled"] == len(archive["elites"]) > 0
    assert archive["coverage"] == pytest.approx(archive["cells_filled"] / 96)
    assert archive["qd_floor"] == pytest.approx(min(r["scores_train"]))
    assert (out / "archive.png").is_file()
    poses = json.loads((out / "poses.json").read_text())
    assert poses["waldo_explore"]["min_separation"] == 20.0
    # --min-separation 0: the paper's top-k, the same search bit for bit.
    assert explore(tmp_path / "paper", "--method", "egps", "--seed", "3", "--min-separation", "0") == 0
    paper_run = json.loads((tmp_path / "paper" / "results.json").read_text())
    assert [t["c2w"] for t in paper_run["topk"]] == [t["c2w"] for t in r["paper_topk"]]
    assert paper_run["scores_generated"] == r["scores_generated"] and paper_run["mcvir"] == r["mcvir"]


def test_map_elites_from_the_cli_writes_its_archive(tmp_path, capsys):
    out = tmp_path / "qd"
    assert explore(out, "--method", "map-elites", "--grid", "6x3", "--distance-edges", "", "--seed", "1") == 0
    r = json.loads((out / "results.json").read_text())
    assert r["method"] == "map-elites" and r["archive"]["grid"]["cells"] == 18
    assert all(e["distance_band"] == 0 for e in r["archive"]["elites"])
    sheet = iio.imread(out / "archive.png")
    assert sheet.shape[0] > 3 * 16 and sheet.shape[1] > 6 * 16
    for extra, message in (
        (["--grid", "6by3"], "--grid must be AZxEL"),
        (["--grid", "0x3"], "--grid must be an int"),
        (["--distance-edges", "2,1"], "--distance-edges must be"),
        (["--distance-edges", "a"], "--distance-edges must be comma-separated"),
        (["--min-separation", "-1"], "--min-separation must be"),
        (["--min-separation", "nan"], "--min-separation must be"),
    ):
        refused = tmp_path / "refused"
        assert explore(refused, "--method", "map-elites", *extra) == 1
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1 and not refused.exists()


def test_same_seed_same_scores_other_seed_differs(egps_run, tmp_path):
    _, first = egps_run
    assert explore(tmp_path / "again", "--method", "egps", "--seed", "3") == 0
    again = json.loads((tmp_path / "again" / "results.json").read_text())
    assert again["scores_generated"] == first["scores_generated"]
    assert [t["c2w"] for t in again["topk"]] == [t["c2w"] for t in first["topk"]]
    assert explore(tmp_path / "other", "--method", "egps", "--seed", "4") == 0
    other = json.loads((tmp_path / "other" / "results.json").read_text())
    assert other["scores_generated"] != first["scores_generated"]


def test_rendered_criterion_rerun_gives_byte_identical_scores(tmp_path):
    """Same seed, same results.json scores bit for bit, with a criterion scored on rendered images (the
    case that differed between two runs on a GPU before determinism was on by default), on whatever
    backend runs the suite."""
    runs = []
    for name in ("first", "second"):
        assert explore(tmp_path / name, "--method", "egps", "--seed", "5", "--criterion", "colorfulness") == 0
        r = json.loads((tmp_path / name / "results.json").read_text())
        runs.append(json.dumps([r["scores_train"], r["scores_generated"], [t["c2w"] for t in r["topk"]]]))
    assert runs[0] == runs[1]


def test_several_seeds_report_mean_and_std(tmp_path):
    assert explore(tmp_path / "seeds", "--method", "grs", "--seed", "5", "--seeds", "3") == 0
    r = json.loads((tmp_path / "seeds" / "results.json").read_text())
    assert r["seeds"] == [5, 6, 7] and [p["seed"] for p in r["per_seed"]] == [5, 6, 7]
    cvirs = [p["cvir"] for p in r["per_seed"]]
    assert r["cvir_mean"] == pytest.approx(np.mean(cvirs), rel=1e-5)
    assert r["cvir_std"] == pytest.approx(np.std(cvirs), rel=1e-4, abs=1e-6)
    assert r["cvir"] == pytest.approx(cvirs[0], rel=1e-6)  # the files show the first seed
    assert len(set(cvirs)) > 1


def test_image_criterion_renders_and_scores(tmp_path):
    out = tmp_path / "colour"
    assert explore(out, "--method", "pibs", "--criterion", "colorfulness") == 0
    r = json.loads((out / "results.json").read_text())
    assert r["initial_scores"] == "images" and r["direction"] == "max"
    assert r["pibs"] == {"top_c": 5, "fallback": "none"}  # the defaults of PIBS's own options
    source = procedural_source(1, resolution=16, views=8)
    crit = make_criterion("colorfulness")
    np.testing.assert_allclose(r["scores_train"], np.asarray(crit.score_images(source.train_images)), rtol=1e-5)
    # The saved top view, scored again from its PNG (8-bit), gives the reported score.
    png = iio.imread(out / r["topk"][0]["image"]).astype(np.float32) / 255.0
    assert float(crit.score_images(png[None])[0]) == pytest.approx(r["topk"][0]["score"], rel=0.02)


def test_top_c_past_the_runs_views_is_said_and_pairs_them_all(tmp_path, capsys):
    """PIBS pairs min(--top-c, the run's views): a larger --top-c says so in one warning line, and runs as
    --top-c equal to the views (8 training + 2 epochs x 6 children = 20) does, bit for bit."""
    runs = {}
    for top_c in (25, 20):
        capsys.readouterr()
        assert explore(tmp_path / str(top_c), "--method", "pibs", "--top-c", str(top_c)) == 0
        warned = [line for line in capsys.readouterr().err.splitlines() if "--top-c" in line]
        runs[top_c] = json.loads((tmp_path / str(top_c) / "results.json").read_text())
        said = "waldo: warning: --top-c 25 exceeds the 20 views of the run (8 training + 2 epochs x 6 children)"
        assert warned == ([f"{said}: all 20 are paired"] if top_c == 25 else [])
    assert runs[25]["scores_generated"] == runs[20]["scores_generated"]


def test_a_search_that_generates_nothing_says_so(tmp_path, capsys):
    """EGPS breeds from two views with a finite score: from one training view it generates none. The run
    still ends (its results.json says n_generated 0), with a warning line naming why and what to use, where
    it had reported a CVIR of 0 as if it had searched."""
    argv = ["--views", "1", "--method", "egps"]
    assert main(["explore", "procedural:1", "--out", str(tmp_path / "one"), *TINY, *argv]) == 0
    warned = [line for line in capsys.readouterr().err.splitlines() if "generated no views" in line]
    assert warned == [
        "waldo: warning: egps generated no views in 2 epochs: 1 of the run's 1 training views scored (a finite "
        "score), and EGPS and PIBS make each child from two of them. Use --method grs (or map-elites), or "
        "--pibs-fallback grs with PIBS"
    ]
    assert json.loads((tmp_path / "one" / "results.json").read_text())["n_generated"] == 0


@pytest.mark.parametrize(
    "flags, warned",
    [
        (["--budget", "high", "--children-per-epoch", "6"], True),
        (["--budget", "low", "--children-per-epoch", "6"], True),
        (["--budget", "high"], False),
        (["--children-per-epoch", "6"], False),
    ],
)
def test_a_budget_beside_children_per_epoch_says_it_changes_nothing(flags, warned):
    """The budget only derives the children per epoch: given beside --children-per-epoch it changed nothing,
    in silence. The default budget (low) where neither is given, and each alone, say nothing."""
    args = build_parser().parse_args(["explore", "procedural:1", "--out", "x", *flags])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        config = explore_config_from_args(args)
    said = [str(w.message) for w in caught if "--budget" in str(w.message)]
    budget = flags[1] if flags[0] == "--budget" else "low"
    text = (
        f"--budget {budget} has no effect: --children-per-epoch 6 wins (the budget only derives the children per epoch)"
    )
    assert said == ([text] if warned else [])
    assert config.budget == budget


def test_results_json_records_the_budget_only_where_it_set_the_children():
    """results.json's `budget` is the one that derived the children per epoch; where they were given
    (`--children-per-epoch`), it is null, unless the budget derives the very same number."""
    import dataclasses

    from waldo_jax.pipeline.outputs import _budget_used
    from waldo_jax.search import ExploreConfig

    for budget in ("low", "high", (100, 120)):
        derived = ExploreConfig(budget=budget).resolve(32)
        assert _budget_used(derived, 32) == (budget if isinstance(budget, str) else list(budget))
        given = dataclasses.replace(derived, children_per_epoch=derived.children_per_epoch + 1)
        assert _budget_used(given, 32) is None
    refined = ExploreConfig(method="egps+refine", budget="low").resolve(32)  # its gradient renders come out of it
    assert _budget_used(refined, 32) == "low"
    assert _budget_used(dataclasses.replace(refined, children_per_epoch=6), 32) is None
    assert _budget_used(ExploreConfig(budget=(5, 6), children_per_epoch=1), 32) is None  # the budget leaves none


def test_method_flags_become_the_options_of_the_method_that_has_them():
    def config(*flags):
        return explore_config_from_args(build_parser().parse_args(["explore", "procedural:1", "--out", "x", *flags]))

    assert config("--method", "grs", "--top-c", "3", "--pibs-fallback", "grs").options == ()
    assert config("--method", "pibs", "--top-c", "3", "--pibs-fallback", "grs").method_options == {
        "top_c": 3,
        "fallback": "grs",
    }
    refined = config("--method", "pibs+refine", "--top-c", "3", "--refine-steps", "2").method_options
    assert set(refined) == {"top_c", "fallback", "refine"} and refined["top_c"] == 3 and refined["refine"].steps == 2
    assert set(config("--method", "egps+refine", "--top-c", "3").method_options) == {"refine"}
    assert config("--method", "evosax:SNES", "--refine-steps", "2").options == ()


def test_refine_and_evosax_methods_from_the_cli(tmp_path, capsys):
    assert explore(tmp_path / "refine", "--method", "egps+refine", "--refine-poses", "2", "--refine-steps", "2") == 0
    r = json.loads((tmp_path / "refine" / "results.json").read_text())
    # The oracle's smooth stand-in costs 2 renders a gradient; the children are given here, so the
    # cost adds up rather than fitting a budget.
    assert r["method"] == "egps+refine" and r["refine"]["gradient_cost"] == 2
    assert r["cost"]["renders"] == 8 + 2 * 6 + 2 * 2 * 2
    assert explore(tmp_path / "cma", "--method", "evosax:CMA_ES", "--seed", "2") == 0
    assert explore(tmp_path / "cma2", "--method", "evosax:CMA_ES", "--seed", "2") == 0
    first, second = (json.loads((tmp_path / d / "results.json").read_text()) for d in ("cma", "cma2"))
    assert first["scores_generated"] == second["scores_generated"] and first["method"] == "evosax:CMA_ES"
    # Refused before anything is written: a criterion gradient steps cannot follow, an unknown strategy,
    # more refined poses than children.
    for extra, message in (
        (["--method", "egps+refine", "--criterion", "brisque"], "'brisque' is not differentiable"),
        (["--method", "evosax:CMAES"], "unknown --method 'evosax:CMAES'"),
        (["--method", "grs+refine", "--refine-poses", "7"], "refining 7 poses"),
        (["--method", "egps+refine", "--gradient-cost", "1"], "--gradient-cost must be"),
    ):
        if "brisque" in extra:
            from conftest import require_weights

            require_weights("brisque")
        out = tmp_path / "refused"
        assert explore(out, *extra) == 1
        err = capsys.readouterr().err
        assert message in err and len(err.strip().splitlines()) == 1 and not out.exists()


def test_errors_are_one_line(tmp_path, capsys):
    assert explore(tmp_path / "x", "--criterion", "nope") == 1
    assert "unknown criterion 'nope'" in capsys.readouterr().err
    assert explore(tmp_path / "y", "--method", "cmaes") == 1
    assert "unknown --method 'cmaes'" in capsys.readouterr().err
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "keep.txt").write_text("earlier run")
    assert explore(tmp_path / "full") == 1
    assert "full" in capsys.readouterr().err and (tmp_path / "full" / "keep.txt").read_text() == "earlier run"
    assert main(["explore", str(tmp_path / "no_such_run"), "--out", str(tmp_path / "z")]) == 1
    assert "no_such_run" in capsys.readouterr().err


def test_demo_refuses_an_unknown_method_on_renders_before_making_its_folder(tmp_path, capsys):
    """`--search-renders` takes a method of the exact rows' kind; another is refused before anything runs."""
    settings = DemoSettings(views=10, resolution=24, train_steps=20, seeds=2, search_renders="cma")
    with pytest.raises(WaldoError, match="search_renders must be one of grs, pibs, egps, map-elites"):
        run_demo(tmp_path / "demo", settings=settings, progress=False)
    assert not (tmp_path / "demo").exists()
    assert main(["demo", "--search-renders", "cma", "--out", str(tmp_path / "cli")]) == 1
    assert "unknown --search-renders 'cma': expected one of grs, pibs, egps, map-elites" in capsys.readouterr().err
    assert not (tmp_path / "cli").exists()


def test_demo_on_renders_trains_longer_unless_told(monkeypatch, tmp_path):
    """`waldo demo --search-renders` trains the full demo's NeRF RENDERS_TRAIN_STEPS steps (the finder judges
    Waldo by its pictures); `--train-steps` still wins, `--quick` keeps its own, and the report's command
    line names only what differs from these defaults."""
    from waldo_jax.cli import demo as demo_cli
    from waldo_jax.pipeline import demo as demo_pipeline

    seen = []
    monkeypatch.setattr(demo_cli, "run_demo", lambda out, settings, **kw: seen.append(settings) or tmp_path)
    for argv in (["demo"], ["demo", "--search-renders"], ["demo", "--search-renders", "egps", "--train-steps", "300"]):
        assert main([*argv, "--out", str(tmp_path / "x")]) == 0
    assert main(["demo", "--quick", "--search-renders", "--out", str(tmp_path / "q")]) == 0
    full, quick = demo_pipeline.SETTINGS["full"], demo_pipeline.SETTINGS["quick"]
    assert [(s.train_steps, s.search_renders) for s in seen] == [
        (full.train_steps, None),
        (demo_pipeline.RENDERS_TRAIN_STEPS, "grs"),
        (300, "egps"),
        (quick.train_steps, "grs"),
    ]
    assert demo_pipeline.RENDERS_TRAIN_STEPS > full.train_steps
    assert demo_pipeline._command(False, DEMO_ROOM_SEED, seen[1]) == "waldo demo --search-renders"
    assert (
        demo_pipeline._command(False, DEMO_ROOM_SEED, seen[2]) == "waldo demo --train-steps 300 --search-renders egps"
    )
    assert demo_pipeline._command(False, DEMO_ROOM_SEED, seen[0]) == "waldo demo"


def test_demo_writes_report_never_overwrites_and_its_nerf_explores(tmp_path):
    settings = DemoSettings(
        views=10, resolution=24, train_steps=20, seeds=2, test_views=2, render_step_scale=3.0, search_renders="grs"
    )
    out = run_demo(tmp_path / "demo", settings=settings, progress=False)
    report = (out / "report.md").read_text()
    for method in ("GRS", "PIBS", "EGPS"):
        assert f"| {method} |" in report
    summary = json.loads((out / "summary.json").read_text())
    assert set(summary["methods"]) == {"grs", "pibs", "egps", "grs_on_renders"} and summary["seeds"] == [
        DEMO_ROOM_SEED,
        DEMO_ROOM_SEED + 1,
    ]
    assert summary["room_seed"] == DEMO_ROOM_SEED and summary["criterion"] == "waldo_found"
    # The row on renders: GRS by the finder on the NeRF's images, its best views checked by the oracle.
    renders = summary["methods"]["grs_on_renders"]
    assert renders["scores_renders"] is True and renders["criterion"] == "waldo"
    assert not any(summary["methods"][m]["scores_renders"] for m in ("grs", "pibs", "egps"))
    assert "| GRS on renders |" in report and (out / "waldo_reference.png").is_file()
    for method in ("grs", "pibs", "egps", "grs_on_renders"):  # Waldo's share, the NeRF's PSNR at each best view
        m = summary["methods"][method]
        assert len(m["waldo_psnr_per_seed"]) == 2  # over Waldo's pixels; None where he has none
        assert all(v is None or np.isfinite(v) for v in m["waldo_psnr_per_seed"])
        assert len(m["best_visible_per_seed"]) == 2 and all(0.0 <= v <= 1.0 for v in m["best_visible_per_seed"])
        assert len(m["best_psnr_per_seed"]) == 2 and all(np.isfinite(m["best_psnr_per_seed"]))
        assert len(m["closeup_psnr_per_seed"]) == 2 and all(np.isfinite(m["closeup_psnr_per_seed"]))
        assert 1.0 <= m["closeup_zoom"] <= 6.0
    assert 0.0 <= summary["waldo_surface_seen_in_training"] <= 1.0 and "of Waldo's surface" in report
    assert "![Waldo close-ups](waldo_closeups.png)" in report and (out / "waldo_closeups.png").is_file()
    assert "Waldo visible in best view" in report and "NeRF render PSNR at best view" in report
    assert f"Scores in every table and figure: {summary['criterion_caption']}." in report
    assert summary["criterion_caption"].startswith("waldo_found: ") and "higher is better, in [0, 2]" in report
    for method in ("grs", "pibs", "egps"):
        assert (out / method / "results.json").is_file() and (out / method / "pose_cloud.png").is_file()
    assert (out / "contact_sheet.png").is_file() and (out / "nerf" / "checkpoint.ckpt").is_file()
    with pytest.raises(WaldoError):
        run_demo(out, settings=settings, progress=False)
    # The saved NeRF of the room is a SOURCE: it keeps the room, so the oracle applies.
    source = run_source(str(out / "nerf"), resolution=16)
    assert source.room is not None and source.truth is not None and source.n_train == 10
    assert (
        main(
            [
                "explore",
                str(out / "nerf"),
                "--out",
                str(tmp_path / "again"),
                "--resolution",
                "16",
                "--epochs",
                "1",
                "--children-per-epoch",
                "4",
                "--top-k",
                "2",
                "--quiet",
            ]
        )
        == 0
    )
    again = json.loads((tmp_path / "again" / "results.json").read_text())
    assert again["source_info"]["procedural_seed"] == DEMO_ROOM_SEED
    assert (tmp_path / "again" / "topk" / "00_truth.png").is_file()
    # Beyond the paper, on the trained run: gradient steps through the NeRF's marched render (reverse
    # mode, `Source.gradient`) with an image criterion, and an evosax strategy.
    tiny_run = ["--resolution", "16", "--epochs", "1", "--children-per-epoch", "4", "--top-k", "2", "--quiet"]
    assert (
        main(
            [
                "explore",
                str(out / "nerf"),
                "--out",
                str(tmp_path / "refined"),
                *tiny_run,
                "--method",
                "egps+refine",
                "--criterion",
                "colorfulness",
                "--refine-poses",
                "1",
                "--refine-steps",
                "2",
            ]
        )
        == 0
    )
    refined = json.loads((tmp_path / "refined" / "results.json").read_text())
    assert refined["cost"] == {
        "renders": 10 + 4 + 2 * NERF_GRADIENT_COST,
        "training_views": 10,
        "children": 4,
        "gradient_evaluations": 2,
        "renders_per_gradient_evaluation": NERF_GRADIENT_COST,
    }
    assert refined["refine"]["poses"] == 1 and refined["n_generated"] == 4
    assert (
        main(["explore", str(out / "nerf"), "--out", str(tmp_path / "cma"), *tiny_run, "--method", "evosax:CMA_ES"])
        == 0
    )
    assert json.loads((tmp_path / "cma" / "results.json").read_text())["method"] == "evosax:CMA_ES"
    # A camera path through the trained run; its nerfstudio export renders back with the NeRF, and the
    # room's analytic truth is written beside it.
    assert (
        main(
            [
                "path",
                str(out / "nerf"),
                "--out",
                str(tmp_path / "path"),
                "--resolution",
                "16",
                "--keyframes",
                "3",
                "--frames",
                "6",
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
        )
        == 0
    )
    assert (tmp_path / "path" / "path_truth.mp4").is_file()
    assert (
        main(
            [
                "render",
                str(out / "nerf"),
                "--poses",
                str(tmp_path / "path" / "camera_path.json"),
                "--out",
                str(tmp_path / "path_render"),
                "--resolution",
                "12",
            ]
        )
        == 0
    )
    assert len(list((tmp_path / "path_render").glob("*.png"))) == 6


@pytest.mark.parametrize("criterion", ["saliency", "iqa_cnn", "niqe", "brisque", "composition", "waldo"])
def test_explore_accepts_each_criterion(tmp_path, criterion):
    """Every criterion of the issue runs inside the search's jit (with the opacity guard), and the
    scores of the training views in results.json are the criterion's own."""
    from conftest import require_weights

    if criterion != "waldo":
        require_weights({"saliency": "csnet", "composition": "csnet", "iqa_cnn": "cnniqa"}.get(criterion, criterion))
    extra, target = [], None
    # NIQE and BRISQUE need whole 96 px patches: there, four training views keep the renders cheap.
    size, views = (96, 4) if criterion in ("niqe", "brisque") else (16, 8)
    source = procedural_source(1, resolution=size, views=views)
    if criterion == "waldo":  # a crop of a training view as the reference image
        path = tmp_path / "target.png"
        iio.imwrite(path, (np.clip(source.train_images[0, 4:12, 4:12], 0, 1) * 255).astype(np.uint8))
        extra, target = ["--target", str(path)], read_image(path)
    out = tmp_path / criterion
    assert (
        explore(
            out,
            "--method",
            "egps",
            "--criterion",
            criterion,
            "--guard",
            "opacity:0.5",
            *extra,
            "--resolution",
            str(size),
            "--views",
            str(views),
        )
        == 0
    )
    r = json.loads((out / "results.json").read_text())
    assert r["criterion"] == f"{criterion}|opacity>=0.5"
    assert r["direction"] == CRITERIA[criterion].direction
    assert r["n_generated"] == 12 and np.all(np.isfinite(r["scores_generated"]))
    # The training images scored by the same criterion (the program `waldo explore` compiled: no new one).
    guarded = build_criterion(criterion, CriterionContext(target=target), ["opacity:0.5"])
    assert r["scores_train"] == initial_scores(source, guarded, "images")[0].tolist()

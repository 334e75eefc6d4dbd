"""`benchmarks/paper_tables.py --quick` end to end (tiny settings) and its table / JSON helpers.

One run (module fixture) of the procedural room, plus fox when `$WALDO_DATA` has it, with the cheap
image criterion `colorfulness` (no weights) and two methods: the JSON's structure and its numbers'
consistency (CVIR recomputed from the stored best and best-training scores, means and stds from the
per-seed values), the printed tables, the Waldo-room table, the figures, the paper values' labels.
"""

from __future__ import annotations

import json
import math
import shutil
import signal
import statistics
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import built_once, require_scene
from waldo_jax import paths
from waldo_jax.procedural import make_room

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

import paper_tables  # noqa: E402
import paper_values  # noqa: E402

pytestmark = pytest.mark.slow

METHODS = ["grs", "egps"]
SEEDS = 2


def _fox_available() -> bool:
    data = paths.data_dir()
    return data is not None and (data / "scenes" / "fox").exists()


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    """One quick run per session (`built_once`: the first worker runs it, the others read its files)."""
    scenes = "room,fox" if _fox_available() else "room"

    def argv(tmp):
        return [
            "--quick",
            "--scenes",
            scenes,
            "--criteria",
            "colorfulness",
            "--methods",
            ",".join(METHODS),
            "--seeds",
            str(SEEDS),
            "--resolution",
            "24",
            "--train-steps",
            "20",
            "--room-steps",
            "30",
            "--room-views",
            "12",
            "--room-resolution",
            "32",
            "--downscale",
            "fox=32",
            "--render-step-scale",
            "3",
            "--runs",
            str(tmp / "runs"),
            "--out",
            str(tmp / "paper.json"),
        ]

    def build(folder):  # the JSON's name says whether the machine was loaded: keep the name it chose
        (folder / "out.txt").write_text(paper_tables.main(argv(folder))["out"])

    tmp = built_once(tmp_path_factory, "paper_tables_quick", build)
    path = Path((tmp / "out.txt").read_text())
    data = json.loads(path.read_text())
    return {"data": data, "scenes": scenes.split(","), "tmp": tmp, "argv": argv(tmp), "path": path}


def _close(a, b, tol=1e-3):
    return a is not None and b is not None and math.isclose(a, b, rel_tol=tol, abs_tol=tol)


def test_json_names_device_commit_date_and_settings(quick):
    data = quick["data"]
    assert data["benchmark"] == "paper_tables" and data["commit"] and data["date"]
    assert data["device"]["platform"] and "loaded" in data and "loadavg_start" in data
    s = data["settings"]
    assert s["quick"] and s["seeds"] == SEEDS and s["methods"] == METHODS and s["budgets"] == ["low"]
    assert s["children_override"] == {"low": 8} and s["epochs"] == 5 and s["top_k"] == 10
    assert set(data["nerfs"]) == set(quick["scenes"]) and "incomplete" not in data
    for scene, nerf in data["nerfs"].items():
        assert not nerf["reused"] and nerf["train"]["steps"] == (30 if scene == "room" else 20)
        assert max(nerf["render_size"]) == 24
    assert data["seconds"]["total"] > 0 and set(data["seconds"]["train"]) == set(quick["scenes"])


def test_cvir_and_mcvir_recompute_from_stored_scores(quick):
    data = quick["data"]
    cells = data["results"]["colorfulness"]["scenes"]
    sign = 1.0 if data["results"]["colorfulness"]["direction"] == "max" else -1.0
    assert set(cells) == set(quick["scenes"])
    for scene, by_budget in cells.items():
        for method in METHODS:
            cell = by_budget["low"][method]
            assert cell["children_per_epoch"] == 8 and cell["n_total"] == cell["n_train"] + 5 * 8
            assert [s["seed"] for s in cell["per_seed"]] == [0, 1]
            for s in cell["per_seed"]:
                assert 0 < s["n_generated"] <= 5 * 8
                assert _close(s["cvir"], 100 * sign * (s["best"] - s["best_train"]) / abs(s["best_train"]))
                assert _close(
                    s["mcvir"], 100 * sign * (s["mean_top_n"] - s["mean_top_n_train"]) / abs(s["mean_top_n_train"])
                )
                curve = [sign * v for v in s["best_per_epoch"]]
                assert len(curve) == 6 and all(b >= a for a, b in zip(curve, curve[1:]))  # never worse
                assert s["best_per_epoch"][0] == s["best_train"] and s["cvir"] >= 0
            cvirs = [s["cvir"] for s in cell["per_seed"]]
            assert _close(cell["cvir_mean"], statistics.fmean(cvirs))
            assert _close(cell["cvir_std"], statistics.pstdev(cvirs))
            assert _close(cell["mcvir_mean"], statistics.fmean(s["mcvir"] for s in cell["per_seed"]))


def test_tables_have_the_papers_layout(quick, capsys):
    table = quick["data"]["tables"]["colorfulness"]
    assert table["columns"] == quick["scenes"]
    assert [(r["budget"], r["method"]) for r in table["rows"]] == [("low", m) for m in METHODS]
    for row in table["rows"]:
        assert set(row["cells"]) == set(quick["scenes"]) and "±" in row["cells"]["room"]["cvir"]
    lines = [line for line in table["text"].splitlines() if line.startswith("| low*")]
    assert len(lines) == len(METHODS) and table["text"].count("room CVIR | room mCVIR") == 1
    assert table["paper_rows"] == [] and "has no table for colorfulness" in table["text"]


def test_tables_from_a_json_reprint_the_run_and_an_interrupted_one(quick, tmp_path):
    data = quick["data"]
    text = paper_tables.tables_from(quick["path"])
    assert data["tables"]["colorfulness"]["text"] in text
    assert data["waldo_table"]["text"] in text
    # an interrupted run: the room's cells only, the Waldo table unfinished
    partial = json.loads(json.dumps(data))
    partial["incomplete"] = "KeyboardInterrupt: "
    partial["results"]["colorfulness"]["scenes"] = {"room": data["results"]["colorfulness"]["scenes"]["room"]}
    for by_budget in partial["waldo"].values():
        by_budget["low"].pop(METHODS[-1])
    path = tmp_path / "partial.json"
    path.write_text(json.dumps(partial))
    text = paper_tables.tables_from(path)
    assert "Incomplete run" in text and "room CVIR" in text and "fox CVIR" not in text
    assert "Waldo room" not in text


def test_tables_from_several_runs_make_one_table(quick, tmp_path):
    require_scene("fox")
    data = quick["data"]

    def part(scene, name, **settings):
        piece = json.loads(json.dumps(data))
        piece["settings"].update(scenes=[scene], **settings)
        for record in piece["results"].values():
            record["scenes"] = {scene: record["scenes"][scene]}
        if scene != "room":
            piece.pop("waldo"), piece.pop("waldo_reference")
        (tmp_path / name).write_text(json.dumps(piece))
        return tmp_path / name

    fox, room = part("fox", "fox.json"), part("room", "room.json")
    merged = paper_tables.tables_from([room, fox])  # the columns follow the files' order
    assert merged == paper_tables.tables_from(quick["path"])
    swapped = paper_tables.tables_from([fox, room])
    assert swapped.index("fox CVIR") < swapped.index("room CVIR")
    assert data["tables"]["colorfulness"]["text"] in merged and data["waldo_table"]["text"] in merged
    with pytest.raises(SystemExit, match="seeds = 3 differs"):
        paper_tables.tables_from([fox, part("room", "room3.json", seeds=3)])
    with pytest.raises(SystemExit, match="scene 'fox' of colorfulness is also in an earlier JSON"):
        paper_tables.tables_from([fox, fox])


def test_waldo_room_table_from_the_exact_oracle(quick):
    data = quick["data"]
    rows = data["waldo"]["waldo_oracle"]["low"]
    assert set(rows) == set(METHODS)
    for row in rows.values():
        assert row["seeds"] == SEEDS and 0.0 <= row["found_share"] <= 1.0 and row["goal"] == 0.9
        assert len(row["per_seed"]) == SEEDS and 0.0 <= row["best_training_visibility"] <= 1.0
        for s in row["per_seed"]:
            assert 0.0 <= s["best_visibility"] <= 1.0 and 0 < s["n_generated"] <= 40
            if s["renders_to_goal"] is None:
                assert s["best_visibility"] < 0.9
            else:
                assert 1 <= s["renders_to_goal"] <= s["n_generated"] and s["best_visibility"] >= 0.9
        reached = [s for s in row["per_seed"] if s["renders_to_goal"] is not None]
        assert row["found_share"] == len(reached) / SEEDS
        assert (row["renders_to_goal_mean"] is None) == (not reached)
        assert _close(row["best_visibility_mean"], statistics.fmean(s["best_visibility"] for s in row["per_seed"]))
    assert len(data["waldo_table"]["rows"]) == len(METHODS)
    assert "Waldo room procedural:0, search" in data["waldo_table"]["text"]
    reference = data["waldo_reference"]
    assert reference["samples"] == 4096 and 0.0 <= reference["goal_share"] <= 1.0 and reference["goal"] == 0.9
    assert f"The best reachable: {reference['best']:.0%}" in data["waldo_table"]["text"]


def _room_source(room, views=12):
    """What `reachable_visibility` reads of a Source: the room, its training cameras, the intrinsics."""
    from types import SimpleNamespace

    import jax

    from waldo_jax.procedural import training_cameras
    from waldo_jax.types import Intrinsics

    intrinsics = Intrinsics.from_fov(32, 32, np.radians(60.0))
    c2w = training_cameras(jax.random.key(0), make_room(0), views, intrinsics)
    return SimpleNamespace(room=room, train_c2w=c2w, n_train=views, intrinsics=intrinsics)


def test_reachable_visibility_is_the_rooms_known_answer():
    # Without crates nothing hides Waldo: some pose in the training cameras' box sees all of him.
    bare = paper_tables.reachable_visibility(_room_source(make_room(0, num_clutter=0, num_crates=0)), 4096, 0.9)
    assert bare["best"] > 0.95 and bare["goal_share"] > 0.5
    low, high = np.asarray(bare["origin_low"]), np.asarray(bare["origin_high"])
    assert np.all(low <= bare["best_origin"]) and np.all(np.asarray(bare["best_origin"]) <= high)
    # The default room's pen hides part of him from every origin at the band's heights.
    pen = paper_tables.reachable_visibility(_room_source(make_room(0)), 4096, 0.9)
    assert 0.5 < pen["best"] < 0.9 and pen["goal_share"] == 0.0
    assert pen == paper_tables.reachable_visibility(_room_source(make_room(0)), 4096, 0.9)  # seeded
    row = {
        "goal": 0.9,
        "seeds": 1,
        "found_share": 0.0,
        "best_visibility_mean": 0.8,
        "best_visibility_max": 0.8,
        "best_scored_visibility_mean": 0.8,
        "renders_to_goal_mean": None,
        "cvir_mean": 50.0,
        "best_training_visibility": 0.4,
        "n_train": 12,
    }
    text = paper_tables.waldo_table({"waldo_visible": {"low": {"grs": row}}}, ["low"], ["grs"], {}, pen)["text"]
    assert "out of reach in this room" in text
    assert (
        "out of reach"
        not in paper_tables.waldo_table({"waldo_visible": {"low": {"grs": row}}}, ["low"], ["grs"], {}, bare)["text"]
    )


def test_a_reused_room_nerf_must_be_of_the_asked_room(quick, tmp_path):
    runs = tmp_path / "runs"
    shutil.copytree(quick["tmp"] / "runs" / "room", runs / paper_tables.room_folder(1))  # a seed-0 room's NeRF
    with pytest.raises(SystemExit, match="room seed 0, not --room-seed 1"):
        paper_tables.main(
            [
                "--quick",
                "--scenes",
                "room",
                "--room-seed",
                "1",
                "--criteria",
                "none",
                "--runs",
                str(runs),
                "--out",
                str(tmp_path / "x.json"),
            ]
        )
    assert paper_tables.room_folder(0) == "room" and paper_tables.room_folder(3) == "room_seed3"


def test_figures_are_written(quick):
    data = quick["data"]
    names = {Path(p).name for p in data["figures"]}
    for scene in quick["scenes"]:
        assert f"{scene}_colorfulness_views.png" in names and f"{scene}_colorfulness_egps_cloud.png" in names
    assert "room_waldo_oracle_views.png" in names
    for path in data["figures"]:
        assert Path(path).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_fox_is_in_the_quick_run(quick):
    require_scene("fox")
    data = quick["data"]
    assert "fox" in data["results"]["colorfulness"]["scenes"] and data["nerfs"]["fox"]["train"]["n_train"] > 0
    assert data["nerfs"]["fox"]["train"]["image_size"][1] <= 1920 // 32 + 1


def test_output_is_never_overwritten(tmp_path):
    first = tmp_path / "a.json"
    assert paper_tables.unique_path(first) == first
    first.write_text("{}")
    assert paper_tables.unique_path(first) == tmp_path / "a-2.json"
    (tmp_path / "a-2.json").write_text("{}")
    assert paper_tables.unique_path(first) == tmp_path / "a-3.json"


def test_paper_values_are_labelled_and_well_formed():
    for criterion, network in (("saliency", "BASNet"), ("composition", "SAMP-Net"), ("iqa_cnn", "CONTRIQUE")):
        label = paper_values.label(criterion)
        assert network in label and "Instant-NGP" in label and paper_values.SOURCE_URL in label
        described = paper_values.describe([criterion])["criteria"][criterion]
        entry = paper_values.TABLES[paper_values.table_for(criterion)]
        assert described["available"] == any(entry["values"].get(s) for s in paper_values.SCENES)
        assert described["available"] or "not found here" in described["note"]
        if paths.data_dir() is not None and (paths.data_dir() / paper_values.PAPER_FILE).is_file():
            assert described["available"] and entry["table"] in (1, 2, 3)  # read from ../shared/paper
        for scene, budgets in entry["values"].items():  # whatever is transcribed is a complete cell
            assert scene in paper_values.SCENES and set(budgets) <= {"low", "high"}
            for methods in budgets.values():
                assert set(methods) <= {"grs", "pibs", "egps"}
                assert all(len(cell) == 2 and all(np.isfinite(cell)) for cell in methods.values())
    assert paper_values.lookup("colorfulness", "fox", "low", "egps") is None


def test_paper_rows_are_printed_beside_ours_and_labelled(monkeypatch):
    monkeypatch.setitem(paper_values.TABLES["saliency"], "values", {"fox": {"low": {"egps": (12.5, 3.25)}}})
    cell = {"cvir_mean": 10.0, "cvir_std": 1.0, "mcvir_mean": 5.0, "mcvir_std": 0.5}
    cells = {"fox": {"low": {m: cell for m in ("grs", "egps")}}, "face": {"low": {"grs": cell}}}
    table = paper_tables.criterion_table("saliency", cells, ["fox", "face"], ["low"], ["grs", "egps"], {}, 3)
    assert len(table["rows"]) == 2 and table["rows"][1]["cells"]["face"] == {"cvir": "-", "mcvir": "-"}
    (paper,) = table["paper_rows"]
    assert (paper["method"], paper["cells"]["fox"]) == ("egps", {"cvir": "12.5", "mcvir": "3.2"})
    assert "BASNet" in paper["label"] and "Instant-NGP" in paper["label"]
    assert "| low | EGPS (paper) | 12.5 | 3.2 |  |  |" in table["text"] and "BASNet" in table["text"]


def test_a_cell_undefined_for_a_zero_training_score_says_why():
    seed = {"cvir": None, "mcvir": None, "best_train": 0.0, "best": 0.0625}
    zero = {"cvir_mean": None, "cvir_std": None, "mcvir_mean": None, "mcvir_std": None, "per_seed": [seed, seed]}
    fine = {
        "cvir_mean": 10.0,
        "cvir_std": 1.0,
        "mcvir_mean": 5.0,
        "mcvir_std": 0.5,
        "per_seed": [{"cvir": 10.0, "mcvir": 5.0, "best_train": 0.5, "best": 0.55}],
    }
    cells = {"fern": {"low": {"grs": zero}}, "fox": {"low": {"grs": fine}}}
    table = paper_tables.criterion_table("saliency", cells, ["fox", "fern"], ["low"], ["grs"], {}, 2)
    assert "| low | GRS | 10 ± 1 | 5 ± 0 | n/a | n/a |" in table["text"]
    (note,) = [n for n in table["notes"] if n.startswith("fern:")]
    assert "best training score is 0.000" in note and "0.062" in note
    assert not any(n.startswith("fox:") for n in table["notes"])


def test_stop_signals_raise_keyboard_interrupt_so_the_json_is_written():
    saved = {n: signal.getsignal(n) for n in (signal.SIGINT, signal.SIGTERM)}
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # as in a background job of a non-interactive shell
        previous = paper_tables._interrupt_on_signals()
        assert previous[signal.SIGINT] is signal.SIG_IGN
        for signum in (signal.SIGINT, signal.SIGTERM):
            with pytest.raises(KeyboardInterrupt, match=signal.Signals(signum).name):
                signal.getsignal(signum)(signum, None)
    finally:
        for signum, handler in saved.items():
            signal.signal(signum, handler)


def test_plan_counts_each_cells_renders_and_cuts_parts_of_the_limit():
    """`--plan` counts what the budgets cost (training views excluded, refinement included, times the
    seeds) and cuts the protocol into parts no longer than the limit, splitting by budget when needed."""
    import argparse

    import paper_plan
    from waldo_jax.search import ExploreConfig

    args = argparse.Namespace(epochs=5, top_k=10, seeds=3, initial="images")
    cells = paper_plan._cells("fox", 43, ["saliency"], ["egps", "egps+refine"], ["low", "high"], args, {})
    by = {(c["budget"], c["method"]): c["renders"] for c in cells}
    for (budget, method), renders in by.items():
        cost = ExploreConfig(method=method, budget=budget).cost(43)
        assert renders == 3 * (cost["renders"] - 43)
    assert 250 - 43 <= by[("low", "egps")] / 3 <= 300 - 43 and 900 - 43 <= by[("high", "egps")] / 3 <= 1000 - 43
    args.initial = "renders"  # the training poses are rendered once more
    assert (
        paper_plan._cells("fox", 43, ["saliency"], ["egps"], ["low"], args, {})[0]["renders"]
        == by[("low", "egps")] + 43
    )
    timed = [dict(c, seconds=s) for c, s in zip(cells, (100.0, 100.0, 400.0, 400.0))]
    parts = paper_plan._parts(timed, limit_s=600.0)
    assert [(p["budgets"], p["seconds"], p.get("over_limit")) for p in parts] == [
        ("low", 200.0, False),
        ("high", 800.0, True),
    ]
    # A probe's rate is its fastest chunk's; what the other chunks took beyond it is compilation.
    history = [
        {"step": 100, "seconds": 30.0, "loss": 1.0},
        {"step": 200, "seconds": 40.0, "loss": 1.0},
        {"step": 200, "seconds": 40.0, "psnr_test": 20.0},
        {"step": 300, "seconds": 52.0, "loss": 1.0},
    ]
    scratch = []
    probe = paper_plan._train_probe(
        "real", lambda run_dir: {"history": history, "steps": 300, "seconds": 52.0}, scratch
    )
    assert probe["seconds_per_step"] == pytest.approx(0.1) and probe["compile_s"] == pytest.approx(22.0)
    assert probe["chunks"] == 3 and len(scratch) == 1
    scratch[0].rmdir()
    assert paper_plan._parts(timed, limit_s=1000.0) == [
        {"scene": "fox", "criterion": "saliency", "budgets": None, "seconds": 1000.0}
    ]


def test_methods_beyond_the_papers_are_accepted_and_unknown_ones_named():
    assert paper_tables._method_names("grs,egps+refine,evosax:CMA_ES") == ["grs", "egps+refine", "evosax:CMA_ES"]
    with pytest.raises(SystemExit, match="unknown method 'nope'"):
        paper_tables._method_names("egps,nope")
    paper_tables._check_refinable(["egps+refine"], ["saliency", "iqa_cnn"])
    paper_tables._check_refinable(["egps"], ["niqe"])
    with pytest.raises(SystemExit, match="cannot refine on criterion 'niqe'"):
        paper_tables._check_refinable(["grs", "egps+refine"], ["saliency", "niqe"])

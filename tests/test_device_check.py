"""benchmarks/device_check.py: `--smoke` runs every step on the CPU, so the GPU command cannot rot
between the rare times a GPU is lent; `--pack` makes a folder that `--data` accepts and refuses what would
not travel; a step past its time box is killed with its children; bad input is one line."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from conftest import require_scene, require_weights

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"
sys.path.insert(0, str(BENCHMARKS))

import device_check  # noqa: E402  (stdlib only: no JAX in the parent process)
from device_steps import common, settings  # noqa: E402
from device_steps import pack as device_pack  # noqa: E402

SCRIPT = str(BENCHMARKS / "device_check.py")
HEADER_KEYS = (
    "benchmark",
    "date",
    "commit",
    "device",
    "jax",
    "jaxlib",
    "settings",
    "step",
    "status",
    "time_box_s",
    "seconds",
    "commands",
    "result",
)


def check(*args, timeout=600):
    return subprocess.run([sys.executable, SCRIPT, *map(str, args)], capture_output=True, text=True, timeout=timeout)


def data_dir() -> Path:
    fox = require_scene("fox")
    require_weights("csnet/csnet-L-x1.pth.tar")
    return fox.parent.parent


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    """--pack --smoke into a new folder, then --smoke on it: every step at tiny sizes on the CPU."""
    data = data_dir()
    root = tmp_path_factory.mktemp("device_check")
    packed = check("--pack", root / "data", "--smoke", "--no-wheels", "--data-from", data)
    assert packed.returncode == 0, packed.stderr
    start = time.perf_counter()
    # The check bounds itself by its budget (1800 s under --smoke); a loaded 2-core CPU takes 800 s and more.
    timeout = device_check.SMOKE_BUDGET_S + 300
    run = check("--smoke", "--data", root / "data", "--out", root / "out", "--work", root / "work", timeout=timeout)
    seconds = time.perf_counter() - start
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    report = json.loads((root / "out" / "device_check.json").read_text())
    return root, report, run.stdout, seconds


@pytest.mark.slow
def test_smoke_runs_every_step_and_writes_its_json(smoke):
    root, report, stdout, seconds = smoke
    assert report["finished"] and report["settings"]["smoke"]
    assert list(report["steps"]) == list(device_check.STEP_NAMES)
    statuses = {name: step["status"] for name, step in report["steps"].items()}
    assert set(statuses.values()) == {"done"}, statuses
    # Each step's JSON, written when it finished, names the device, versions, commit and its settings.
    files = sorted((root / "work" / "steps").glob("*.json"))
    assert [f.name.split("_", 1)[1][:-5] for f in files] == list(device_check.STEP_NAMES)
    for path in files:
        step = json.loads(path.read_text())
        for key in HEADER_KEYS:
            assert key in step, (path.name, key)
        assert step["device"]["platform"] == "cpu" and step["jax"] and step["commit"] != "unknown"
        assert all(c["returncode"] == 0 and not c["timed_out"] for c in step["commands"]), path.name
    # What comes back from the device machine: few files, at most 8.
    assert sorted(p.name for p in (root / "out").iterdir()) == sorted(device_check.OUT_FILES)
    steps = {name: step["result"] for name, step in report["steps"].items()}
    env = steps["environment"]
    assert (
        env["jax_default_matmul_precision"] == "highest"
        and "--xla_gpu_deterministic_ops=true" in env["xla_flags_in_force"]
        and env["devices"][0]["platform"] == "cpu"
    )
    totals = steps["correctness"]["totals"]
    assert (totals["passed"], totals["failed"], totals["errors"], totals["not_run"]) == (2, 0, 0, 0)
    lines = (root / "out" / "pytest_reports.jsonl").read_text().splitlines()
    assert sum('"outcome": "passed"' in line for line in lines) == 2
    training = steps["training"]
    for key in ("ms_per_step", "field_fwd_bwd_ms", "step_over_field", "psnr_test", "steps", "downscale"):
        assert training[key] is not None, key
    assert training["steps"] == settings.SMOKE.train_steps and training["preset"] == "quality"
    trained = steps["rendering"]["render_trained"]
    for key in ("rays_per_s", "evaluations_per_ray", "passes_per_view", "field_points_per_s", "render_efficiency"):
        assert trained[key] > 0, key
    assert set(steps["rendering"]["batched_over_loop"]) == {str(r) for r in settings.SMOKE.population_resolutions}
    assert [run["seconds"]["search"] > 0 for run in steps["search"]["runs"]] == [True]
    assert steps["gradient"]["cases"][0]["gradient_finite"]
    splats = steps["splats"]
    cells = [c for c in splats["render_splats"]["synthetic"] if c.get("status") == "measured"]
    assert cells and all(c["pair_overflow"] == 0 and c["views_per_s"] > 0 for c in cells)
    assert splats["explore_donut"]["refine"]["gradient"] == "reverse"
    assert splats["explore_donut"]["renderer"]["views_over_max_pairs"] == 0
    # The targets, each as target / measured / met (a CPU says so in the note).
    targets = report["summary"]["targets"]
    assert len(targets) >= 7 and all({"target", "measured", "met"} <= set(t) for t in targets)
    assert all("not a GPU" in t["note"] for t in targets)
    assert "same-seed reruns byte-identical" in stdout
    print(f"smoke run: {seconds:.0f} s")


@pytest.mark.slow
def test_smoke_determinism_compares_same_seed_runs_byte_for_byte(smoke):
    _, report, _, _ = smoke
    result = report["steps"]["determinism"]["result"]
    assert result["identical"] is True
    runs = result["runs"]
    assert [r["label"] for r in runs] == ["default, first", "default, second", "WALDO_DETERMINISTIC=0"]
    assert runs[0]["scores_sha256"] == runs[1]["scores_sha256"] is not None
    assert runs[2]["env"]["WALDO_DETERMINISTIC"] == "0" and all(r["seconds"]["search"] > 0 for r in runs)


@pytest.mark.slow
def test_pack_copies_the_fox_whole_and_records_its_size(smoke):
    root, report, _, _ = smoke
    manifest = json.loads((root / "data" / device_pack.MANIFEST).read_text())
    source = data_dir() / "scenes" / "fox"
    copied = root / "data" / "scenes" / "fox"
    assert sorted(p.relative_to(copied) for p in copied.rglob("*") if p.is_file()) == sorted(
        p.relative_to(source) for p in source.rglob("*") if p.is_file()
    )
    assert (copied / "transforms.json").read_bytes() == (source / "transforms.json").read_bytes()
    assert (root / "data" / "weights" / "csnet").is_dir()
    sizes = manifest["sizes_mib"]
    assert sizes["total"] == pytest.approx(sizes["working_tree"] + sizes["wheels"] + sizes["data"], abs=0.02)
    assert sizes["total"] <= sizes["limit"] and set(manifest["left_out"]) == set(device_pack.PACK_OPTIONAL)
    assert report["pack"]["code_digest_at_pack"] == report["code_digest"] and report["code_matches_pack"] is True


def test_pack_refuses_what_would_not_fit_before_copying_anything(tmp_path):
    data = data_dir()
    result = check("--pack", tmp_path / "data", "--no-wheels", "--data-from", data, "--limit-mib", "8", timeout=120)
    assert result.returncode != 0
    message = result.stderr.strip().splitlines()[-1]
    assert "too big for the device machine" in message and "> 8 MiB" in message
    assert not (tmp_path / "data").exists()


def test_pack_leaves_out_optional_data_that_does_not_fit(tmp_path):
    data = data_dir()
    # Room for the working tree and the required data, but not for the optional scenes.
    tree = device_pack.working_tree_bytes()
    required = sum(
        src.stat().st_size for name in device_pack.PACK_REQUIRED for src, _ in device_pack.pack_sources(data, name)
    )
    limit = (tree + required) / 2**20 + 0.5
    result = check(
        "--pack",
        tmp_path / "data",
        "--no-wheels",
        "--data-from",
        data,
        "--limit-mib",
        f"{limit:.3f}",
        "--reserve-mib",
        "0",
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    manifest = json.loads((tmp_path / "data" / device_pack.MANIFEST).read_text())
    assert set(manifest["items"]) == set(device_pack.PACK_REQUIRED)
    assert all(
        "does not fit" in manifest["left_out"][name]
        for name in ("scenes/face", "scenes/garden")
        if name in manifest["left_out"]
    )
    assert manifest["sizes_mib"]["total"] <= limit


def test_bad_input_is_one_line_and_an_earlier_output_is_kept(tmp_path):
    data = data_dir()
    cases = [
        (["--steps", "environment,warp", "--out", tmp_path / "a"], "unknown warp"),
        (["--data", tmp_path / "nowhere", "--out", tmp_path / "b"], "no such folder"),
        (["--data", tmp_path, "--out", tmp_path / "c"], "lacks"),
        (["--budget", "0", "--out", tmp_path / "d"], "--budget must be a positive"),
        ([], "give --out"),
        (["--fox-run", tmp_path, "--out", tmp_path / "e"], "no checkpoint.ckpt"),
    ]
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / "device_check.json").write_text("{}")
    cases.append((["--data", data, "--out", earlier], "refusing to overwrite"))
    not_a_pack = tmp_path / "not_a_pack"
    not_a_pack.mkdir()
    (not_a_pack / "keep.txt").write_text("mine")
    cases.append((["--pack", not_a_pack, "--no-wheels", "--data-from", data, "--force"], "not an earlier pack"))
    for args, message in cases:
        result = check(*args, timeout=60)
        assert result.returncode != 0, args
        lines = result.stderr.strip().splitlines()
        assert message in lines[-1] and "Traceback" not in result.stderr, (args, result.stderr)
    assert (earlier / "device_check.json").read_text() == "{}" and (not_a_pack / "keep.txt").read_text() == "mine"


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    status = Path(f"/proc/{pid}/status")
    return not (status.exists() and "State:\tZ" in status.read_text())


def test_a_command_past_its_time_box_is_killed_with_its_children(tmp_path):
    """The time box kills the command's whole process group (pytest-xdist workers, a CLI's children)."""
    log = open(tmp_path / "log", "ab", buffering=0)
    ctx = common.Context(
        settings=settings.SMOKE,
        smoke=True,
        data=tmp_path,
        work=tmp_path,
        out=tmp_path,
        log=log,
        env=dict(os.environ),
        header={},
    )
    pid_file = tmp_path / "grandchild.pid"
    code = (
        "import subprocess, sys, time; p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(60)']);"
        f"open({str(pid_file)!r}, 'w').write(str(p.pid)); print('started', flush=True); time.sleep(60)"
    )
    start = time.monotonic()
    entry = ctx.run("sleeper", [sys.executable, "-c", code], 3.0)
    assert time.monotonic() - start < 20
    assert entry["timed_out"] and entry["returncode"] != 0 and "started" in entry["output_tail"]
    grandchild = int(pid_file.read_text())
    for _ in range(50):
        if not _alive(grandchild):
            break
        time.sleep(0.1)
    assert not _alive(grandchild)
    assert "killed after its time box" in (tmp_path / "log").read_text()


def test_time_left_by_a_step_goes_to_the_later_ones():
    deadline = time.monotonic() + 90.0
    box = common.split_box(deadline, [1, 2])
    assert box(0) == pytest.approx(30.0, abs=0.5) and box(1) == pytest.approx(90.0, abs=0.5)


@pytest.mark.slow
def test_sigterm_ends_cleanly_and_writes_what_was_done(tmp_path):
    data = data_dir()
    proc = subprocess.Popen(
        [
            sys.executable,
            SCRIPT,
            "--smoke",
            "--data",
            str(data),
            "--out",
            str(tmp_path / "out"),
            "--work",
            str(tmp_path / "work"),
            "--steps",
            "environment,determinism",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    report = tmp_path / "out" / "device_check.json"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:  # wait until the determinism step's first explore runs
        if report.exists() and "environment" in json.loads(report.read_text()).get("steps", {}):
            break
        time.sleep(0.2)
    time.sleep(2.0)
    proc.send_signal(signal.SIGTERM)
    output, _ = proc.communicate(timeout=60)
    assert proc.returncode == 130, output
    result = json.loads(report.read_text())
    assert result["finished"] is False and result["interrupted"]
    assert result["steps"]["environment"]["status"] == "done"
    assert result["steps"]["determinism"]["status"] == "interrupted"
    assert not _processes_naming(str(tmp_path / "work"))


def _processes_naming(text: str) -> list:
    """Live processes whose command line contains `text`."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if text in (entry / "cmdline").read_bytes().decode(errors="replace") and _alive(int(entry.name)):
                found.append(int(entry.name))
        except OSError:  # the process ended meanwhile
            continue
    return found


def test_pack_works_from_a_fresh_clone(tmp_path):
    """On a fresh clone neither .device/ nor .whl/ exists yet: both still count as ignored (the folder
    patterns of .gitignore), so --pack into .device/data with the default wheel folder is accepted.

    The clone gets this tree's device-check code (device_check.py and device_steps/, committed or not),
    so that the test checks the code under test rather than the last commit's."""
    data = data_dir()
    clone = tmp_path / "clone"
    subprocess.run(["git", "clone", "--quiet", str(BENCHMARKS.parent), str(clone)], check=True, timeout=300)
    assert not (clone / ".whl").exists() and not (clone / ".device").exists()
    shutil.copy2(BENCHMARKS / "device_check.py", clone / "benchmarks" / "device_check.py")
    shutil.rmtree(clone / "benchmarks" / "device_steps", ignore_errors=True)
    shutil.copytree(
        BENCHMARKS / "device_steps",
        clone / "benchmarks" / "device_steps",
        ignore=shutil.ignore_patterns("__pycache__"),
    )
    probe = (
        "import sys; sys.path.insert(0, 'benchmarks'); import device_steps.pack as d; "
        "print(*(d.is_ignored(d.REPO / p) for p in ('.whl', '.device/data', 'waldo_jax')))"
    )
    ignored = subprocess.run([sys.executable, "-c", probe], cwd=clone, capture_output=True, text=True, timeout=120)
    assert ignored.stdout.split() == ["True", "True", "False"], ignored.stderr
    script = str(clone / "benchmarks" / "device_check.py")
    packed = subprocess.run(
        [sys.executable, script, "--pack", ".device/data", "--smoke", "--no-wheels", "--data-from", str(data)],
        cwd=clone,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert packed.returncode == 0, packed.stderr[-3000:]
    assert (clone / ".device" / "data" / device_pack.MANIFEST).is_file()

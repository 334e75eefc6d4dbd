"""The correctness step: pytest on the device, first the files that failed on a GPU before, then the rest
of the suite as far as the step's time allows.

A child (`device_check.py _pytest REPORT -- ARGS`) runs `pytest.main` with a plugin that appends one JSON
line per test report to `pytest_reports.jsonl` as tests finish, so a run cut short by its time box still
tells what it did; the step counts outcomes, failures and skip reasons from those lines.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from .common import REPO, Context, module_available

# Never in the correctness step: this check's own test (it runs the check itself, on the CPU).
NOT_IN_SUITE = ("test_device_check.py",)
# Test files that cannot even be collected without these packages (none of them is on the device machine).
TEST_FILE_PACKAGES = {"test_notebooks.py": ("nbformat", "nbclient", "ipykernel")}
COUNTS = ("collected", "passed", "failed", "errors", "skipped", "xfailed", "xpassed", "not_run", "collection_errors")


def step(ctx: Context, deadline: float) -> dict:
    """pytest in two runs (failed before, the rest), each given the time left in the step."""
    settings = ctx.settings
    report = ctx.out / "pytest_reports.jsonl"
    first, rest, not_run_files = _select_files(ctx)
    env = {"XLA_PYTHON_CLIENT_PREALLOCATE": "false"}  # several pytest workers share one GPU
    workers = ["-n", str(settings.pytest_workers)]
    common = ["-p", "no:cacheprovider", "-q", "-rfE", *workers]
    commands, runs = [], []
    for label, files in (("failed before", first), ("the rest", rest)):
        left = deadline - time.monotonic()
        if not files:
            continue
        if left < 10 and not ctx.smoke:
            runs.append({"files": label, "not_run": f"no time left in the step ({left:.0f} s)", "paths": files})
            continue
        marker = len(report.read_text().splitlines()) if report.exists() else 0
        command = ctx.run(
            f"correctness: {label}", ctx.self_child("_pytest", report, "--", *common, *files), left, env=env
        )
        commands.append(command)
        runs.append(
            {
                "files": label,
                "paths": files,
                **summarise_reports(report, marker),
                "timed_out": command["timed_out"],
                "exitstatus": command["returncode"],
            }
        )
    if not commands:
        return {
            "status": "skipped",
            "reason": "no time left in the step to start pytest",
            "commands": [],
            "result": {"runs": runs, "totals": None, "not_run_files": not_run_files},
        }
    totals = {k: sum(r.get(k, 0) for r in runs if isinstance(r.get(k, 0), int)) for k in COUNTS}
    failures = [f for r in runs for f in r.get("failures", [])]
    # Complete: every selected file ran to its end (no time box hit, nothing left unrun).
    complete = all(isinstance(r.get("not_run"), int) and r["not_run"] == 0 and not r.get("timed_out") for r in runs)
    status = "timed_out" if any(c["timed_out"] for c in commands) else "done"
    return {
        "status": status,
        "commands": commands,
        "result": {
            "totals": totals,
            "runs": runs,
            "failures": failures,
            "failed_names": [f["nodeid"] for f in failures],
            "suite_complete": complete and settings.pytest_rest is None,
            "not_run_files": not_run_files,
            "packages_missing": (ctx.results.get("environment") or {}).get("packages_missing"),
            "workers": settings.pytest_workers,
            "env": env,
        },
    }


def _select_files(ctx: Context) -> tuple:
    """(the tests run first, the rest, {test file not run: why}): files needing a missing package left out."""
    settings = ctx.settings
    not_run_files = {}
    missing = {name: [m for m in modules if not module_available(m)] for name, modules in TEST_FILE_PACKAGES.items()}
    for name, gone in missing.items():
        if gone:
            not_run_files[f"tests/{name}"] = f"needs {', '.join(gone)}: not installed on this machine"
    first = [t for t in settings.pytest_first if t.split("::")[0] not in not_run_files]
    if settings.pytest_rest is None:
        taken = {Path(t.split("::")[0]).name for t in settings.pytest_first} | set(NOT_IN_SUITE)
        rest = [
            f"tests/{p.name}"
            for p in sorted((REPO / "tests").glob("test_*.py"))
            if p.name not in taken and f"tests/{p.name}" not in not_run_files
        ]
    else:
        rest = list(settings.pytest_rest)
    return first, rest, not_run_files


def summarise_reports(report: Path, skip_lines: int) -> dict:
    """Counts and failures from the JSON lines the `_pytest` child wrote (from line `skip_lines` on)."""
    outcomes, failures, collection_errors, collected, skips = {}, [], [], 0, {}
    if report.exists():
        for i, line in enumerate(report.read_text().splitlines()):
            if i < skip_lines or not line.strip():
                continue
            try:
                event = json.loads(line)
            except ValueError:
                continue
            kind = event.get("event")
            if kind == "collected":
                collected = max(collected, int(event["count"]))
            elif kind == "collect_error":
                collection_errors.append({"nodeid": event["nodeid"], "message": event.get("message", "")})
            elif kind == "report":
                node, when, outcome = event["nodeid"], event["when"], event["outcome"]
                previous = outcomes.get(node)
                if outcome == "failed":
                    verdict = "failed" if when == "call" else "errors"
                    if previous != "failed":
                        outcomes[node] = verdict
                    failures.append({"nodeid": node, "when": when, "message": event.get("message", "")})
                elif outcome == "skipped" and previous is None:
                    outcomes[node] = "xfailed" if event.get("xfail") else "skipped"
                    reason = event.get("message", "")[-200:]
                    skips[reason] = skips.get(reason, 0) + 1
                elif outcome == "passed" and when == "call" and previous is None:
                    outcomes[node] = "xpassed" if event.get("xfail") else "passed"
    counts = {
        k: sum(1 for v in outcomes.values() if v == k)
        for k in ("passed", "failed", "errors", "skipped", "xfailed", "xpassed")
    }
    return {
        "collected": collected,
        **counts,
        "not_run": max(0, collected - len(outcomes)),
        "collection_errors": len(collection_errors),
        "collection_error_list": collection_errors,
        "failures": failures[:200],
        "skip_reasons": dict(sorted(skips.items(), key=lambda kv: -kv[1])[:20]),
    }


# ---------------------------------------------------------------------------------------------
# The child: runs pytest in its own process.


def child(argv: list) -> int:
    """pytest.main on the arguments after '--', every test report appended to argv[0] as a JSON line."""
    import pytest

    path, args = argv[0], argv[argv.index("--") + 1 :]
    return int(pytest.main(args, plugins=[_report_log_plugin(pytest)(path)]))


def _report_log_plugin(pytest):
    """The ReportLog plugin class (made here: only the child process imports pytest)."""

    class ReportLog:
        """A pytest plugin: one JSON line per test report, written as the controller receives it (so a
        run killed by its time box still tells what it did)."""

        def __init__(self, path: str):
            self.file = open(path, "a", buffering=1)

        def _write(self, event: dict) -> None:
            self.file.write(json.dumps(event) + "\n")

        def pytest_runtest_logreport(self, report):
            if report.when != "call" and report.outcome == "passed":
                return
            event = {
                "event": "report",
                "nodeid": report.nodeid,
                "when": report.when,
                "outcome": report.outcome,
                "duration": round(report.duration, 3),
                "xfail": bool(getattr(report, "wasxfail", "")),
            }
            if report.outcome == "failed":
                event["message"] = str(report.longreprtext)[-2500:]
            elif report.outcome == "skipped":
                longrepr = report.longrepr
                event["message"] = str(longrepr[2] if isinstance(longrepr, tuple) else longrepr)
            self._write(event)

        def pytest_collectreport(self, report):
            if report.failed:
                self._write(
                    {"event": "collect_error", "nodeid": report.nodeid, "message": str(report.longreprtext)[-2500:]}
                )

        def pytest_collection_finish(self, session):
            self._write({"event": "collected", "count": len(session.items)})

        @pytest.hookimpl(optionalhook=True)
        def pytest_xdist_node_collection_finished(self, node, ids):
            self._write({"event": "collected", "count": len(ids)})

        def pytest_sessionfinish(self, session, exitstatus):
            self._write({"event": "finish", "exitstatus": int(exitstatus)})

    return ReportLog

"""Bad input through the real CLI entry point: a one-line error naming the value, exit status 1, no
traceback, and nothing written or changed (issue [2/6]; the cases are added class by class).

Each case runs `waldo_jax.cli.main(argv)` in-process with `{tmp}` in argv replaced by a fresh folder
that already holds an earlier run (`{tmp}/run/keep.txt`), and checks that folder is byte-identical
afterwards and that no other file appeared.
"""

import hashlib
import os

import pytest

from waldo_jax.cli import main
from waldo_jax.errors import MAX_SEED, WaldoError, check_seed

BIG = "100000000000000000000"  # 1e20 as an integer: overflows int64

CASES = [
    # (id, argv, text the one-line message must contain)
    ("train-seed-overflow", ["train", "{tmp}/scene", "--out", "{tmp}/new", "--seed", BIG], BIG),
    ("train-seed-negative", ["train", "{tmp}/scene", "--out", "{tmp}/new", "--seed", "-1"], "--seed"),
    ("render-seed-overflow", ["render", "procedural", "--out", "{tmp}/new", "--seed", BIG], BIG),
    ("explore-seed-overflow", ["explore", "procedural", "--out", "{tmp}/new", "--seed", BIG], BIG),
    ("explore-seeds-past-the-limit", ["explore", "procedural", "--out", "{tmp}/new", "--seed", str(MAX_SEED),
                                      "--seeds", "2"], str(MAX_SEED)),
    ("demo-seed-overflow", ["demo", "--out", "{tmp}/new", "--seed", BIG], BIG),
    ("procedural-negative-seed", ["explore", "procedural:-1", "--out", "{tmp}/new"], "procedural:-1"),
    ("procedural-seed-overflow", ["render", f"procedural:{BIG}", "--out", "{tmp}/new"], BIG),
    ("demo-into-an-earlier-run", ["demo", "--out", "{tmp}/run"], "{tmp}/run"),
]


def _snapshot(folder):
    """{relative path: sha256} of every file under folder."""
    out = {}
    for root, _, files in os.walk(folder):
        for name in files:
            path = os.path.join(root, name)
            with open(path, "rb") as f:
                out[os.path.relpath(path, folder)] = hashlib.sha256(f.read()).hexdigest()
    return out


@pytest.mark.parametrize("argv, expected", [pytest.param(a, e, id=i) for i, a, e in CASES])
def test_bad_input_is_one_line_and_changes_nothing(tmp_path, capsys, argv, expected):
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "keep.txt").write_text("an earlier run")
    before = _snapshot(tmp_path)
    status = main([a.replace("{tmp}", str(tmp_path)) for a in argv])
    err = capsys.readouterr().err.strip()
    assert status == 1, err
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("waldo: error: "), err
    assert "Traceback" not in err
    assert expected.replace("{tmp}", str(tmp_path)) in lines[0], lines[0]
    assert _snapshot(tmp_path) == before
    assert sorted(os.listdir(tmp_path)) == ["run"]  # nothing created


def test_demo_refusal_does_not_suggest_a_flag_it_lacks(tmp_path, capsys):
    (tmp_path / "keep.txt").write_text("an earlier run")
    assert main(["demo", "--out", str(tmp_path)]) == 1
    err = capsys.readouterr().err
    assert "not empty" in err and "--force" not in err


def test_check_seed_bounds():
    assert check_seed(0) == 0 and check_seed(MAX_SEED) == MAX_SEED
    assert check_seed(MAX_SEED - 3, count=4) == MAX_SEED - 3
    for bad, count in ((-1, 1), (MAX_SEED + 1, 1), (MAX_SEED - 2, 4), (True, 1), (1.5, 1)):
        with pytest.raises(WaldoError, match="--seed"):
            check_seed(bad, count=count)

"""The published CVIR / mCVIR of "Finding Waldo" for fox and face, to print beside ours.

Source: Skartados, Yucel, Manganelli, Drosou, Saà-Garriga, "Finding Waldo: Towards Efficient
Exploration of NeRF Scene Spaces", ACM MMSys 2024, arXiv 2403.04508: Tables 1 (photo-composition,
SAMP-Net), 2 (image quality, CONTRIQUE) and 3 (saliency, BASNet), each with GRS / PIBS / EGPS rows
for the low (250-300 images) and high (900-1000 images) budgets, on Instant-NGP NeRFs.

The numbers are not typed in here: they are read from `$WALDO_DATA/paper/finding_waldo_tables.json`
(`../shared/paper`, checked cell by cell against the paper), exactly as printed. Without that file
the tables are empty, the benchmark's paper rows say where the file should be, and its JSON records
`available: false` with that reason.

Scenes: the paper's fox and face are ours too, so their paper rows sit under ours. fern stands in
for the paper's LLFF scenes trex and horns, garden for family (Tanks and Temples): different scenes,
no paper row beside them (`STAND_INS`). plant_new (the authors' own capture) has no counterpart.

The comparison is of kind, not of value: the paper's criteria are BASNet, SAMP-Net and CONTRIQUE on
Instant-NGP renders at full resolution; ours are CSNet (`saliency`), rule-based composition on the
CSNet map (`composition`) and CNNIQA / NIQE / BRISQUE (`iqa_cnn`, `niqe`, `brisque`) on our JAX
hash-grid NeRFs. Only the ranking of the methods and the order of magnitude can agree.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any, Dict, Optional, Tuple

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from waldo_jax.paths import data_dir  # noqa: E402

__all__ = [
    "SOURCE_URL",
    "NERF",
    "TABLES",
    "CRITERION_TABLE",
    "SCENES",
    "STAND_INS",
    "PAPER_FILE",
    "table_for",
    "lookup",
    "label",
    "describe",
    "stand_in_notes",
    "load_tables",
]

SOURCE_URL = "https://arxiv.org/abs/2403.04508"
NERF = "Instant-NGP"
SCENES = ("fox", "face")
STAND_INS = {"fern": ("trex", "horns"), "garden": ("family",)}
PAPER_FILE = Path("paper") / "finding_waldo_tables.json"

_NETWORKS = {
    "saliency": ("BASNet", "saliency maximisation (number of salient pixels, BASNet)"),
    "composition": ("SAMP-Net", "photo-composition score (SAMP-Net, mean opinion score in [1, 5])"),
    "iqa": ("CONTRIQUE", "no-reference image quality (CONTRIQUE)"),
}


def load_tables(path: Optional[Path] = None) -> Dict[str, Dict[str, Any]]:
    """The paper's tables for our scenes from its JSON (default `$WALDO_DATA/paper/...`); empty values
    with a note naming the missing file when it cannot be read.

    Returns {"saliency" | "composition" | "iqa": {"paper_network", "paper_criterion", "table",
    "values": {scene: {budget: {method: (cvir, mcvir)}}}, "note"}}.
    """
    if path is None:
        root = data_dir()
        path = None if root is None else root / PAPER_FILE
    meta, note = None, ""
    if path is None or not Path(path).is_file():
        note = (
            f"the paper's values are read from $WALDO_DATA/{PAPER_FILE.as_posix()}, not found here "
            f"({path or 'WALDO_DATA unset'}); no value is typed in"
        )
    else:
        meta = json.loads(Path(path).read_text(encoding="utf-8"))
    tables = {}
    for name, (network, criterion) in _NETWORKS.items():
        entry = (meta or {}).get("tables", {}).get(name, {})
        values = {
            scene: {
                budget: {method: (float(cell["cvir"]), float(cell["mcvir"])) for method, cell in methods.items()}
                for budget, methods in entry.get("values", {}).get(scene, {}).items()
            }
            for scene in SCENES
            if scene in entry.get("values", {})
        }
        tables[name] = {
            "paper_network": network,
            "paper_criterion": criterion,
            "table": entry.get("table"),
            "values": values,
            "note": note,
        }
    return tables


# One entry per results table of the paper, read once at import.
TABLES: Dict[str, Dict[str, Any]] = load_tables()

# Which paper table each of our criteria stands in for (criteria not listed have none).
CRITERION_TABLE = {
    "saliency": "saliency",
    "composition": "composition",
    "iqa_cnn": "iqa",
    "niqe": "iqa",
    "brisque": "iqa",
}


def table_for(criterion: str) -> Optional[str]:
    """The paper table our `criterion` stands in for, or None."""
    return CRITERION_TABLE.get(criterion)


def lookup(criterion: str, scene: str, budget: str, method: str) -> Optional[Tuple[float, float]]:
    """(CVIR %, mCVIR %) the paper printed for this cell, or None (no such table, or the paper file is absent)."""
    table = table_for(criterion)
    if table is None:
        return None
    cell = TABLES[table]["values"].get(scene, {}).get(budget, {}).get(method)
    return None if cell is None else (float(cell[0]), float(cell[1]))


def label(criterion: str) -> str:
    """How the paper's rows are labelled beside ours: which network, which NeRF."""
    table = table_for(criterion)
    if table is None:
        return f"paper: no table for {criterion}"
    entry = TABLES[table]
    number = f"Table {entry['table']}" if entry["table"] is not None else "table not read"
    return f"paper ({entry['paper_network']} on {NERF}, a different network and NeRF from ours; {SOURCE_URL}, {number})"


def stand_in_notes(scenes) -> list:
    """One line per stand-in scene among `scenes`: which of the paper's scenes it replaces."""
    return [
        f"{scene} stands in for the paper's {' and '.join(STAND_INS[scene])} (a different scene: no (paper) row "
        f"beside it)."
        for scene in scenes
        if scene in STAND_INS
    ]


def describe(criteria) -> Dict[str, Any]:
    """The JSON record of the paper values used for `criteria`: label, availability, values, reason."""
    out: Dict[str, Any] = {
        "source": SOURCE_URL,
        "file": f"$WALDO_DATA/{PAPER_FILE.as_posix()}",
        "nerf": NERF,
        "scenes": list(SCENES),
        "stand_ins": {k: list(v) for k, v in STAND_INS.items()},
        "comparable": "in kind only: different criterion networks and NeRF (see paper_values.py)",
        "criteria": {},
    }
    for criterion in criteria:
        table = table_for(criterion)
        if table is None:
            out["criteria"][criterion] = {
                "paper_table": None,
                "available": False,
                "label": label(criterion),
                "note": "the paper has no table for this criterion",
            }
            continue
        entry = TABLES[table]
        available = any(entry["values"].get(scene) for scene in SCENES)
        out["criteria"][criterion] = {
            "paper_table": table,
            "paper_network": entry["paper_network"],
            "paper_criterion": entry["paper_criterion"],
            "table_number": entry["table"],
            "label": label(criterion),
            "available": available,
            "values": {
                scene: {
                    budget: {method: list(cell) for method, cell in methods.items()}
                    for budget, methods in entry["values"].get(scene, {}).items()
                }
                for scene in SCENES
                if entry["values"].get(scene)
            },
            "note": "" if available else entry["note"],
        }
    return out

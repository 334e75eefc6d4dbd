"""The published CVIR / mCVIR of "Finding Waldo" for fox and face, to print beside ours.

Source: Skartados, Yucel, Manganelli, Drosou, Saà-Garriga, "Finding Waldo: Towards Efficient
Exploration of NeRF Scene Spaces", ACM MMSys 2024, arXiv 2403.04508,
https://arxiv.org/html/2403.04508v2 : its saliency table (criterion BASNet, the number of salient
pixels), its photo-composition table (SAMP-Net) and its image-quality table (CONTRIQUE), each with
GRS / PIBS / EGPS rows for the low (250-300 images) and high (900-1000 images) budgets and a
CVIR | mCVIR column pair per scene, all on Instant-NGP NeRFs.

**Nothing is transcribed yet.** The session that wrote this file could reach only the opening of
the stored copy of that page (title, authors, abstract, the start of the introduction); the
results tables were out of its reach, and so was every other copy it found (sciencestack.ai,
bohrium, themoonlight.io, the Samsung Research blog, which give the abstract only). A number
that was not read from the paper is not written here: every `VALUES` table below is empty, the
benchmark prints "not transcribed" in the paper rows, and `benchmarks/paper_tables.py` records
`available: false` with this reason in its JSON.

To fill it in, read the three tables of the paper and enter, per table,
`VALUES[scene][budget][method] = (cvir_percent, mcvir_percent)` with scene "fox" or "face",
budget "low" or "high", method "grs", "pibs" or "egps", set `table` to the paper's table number
and keep the numbers exactly as printed (no rounding, no sign change).

Even then the comparison is of kind, not of value: the paper's criteria are BASNet, SAMP-Net and
CONTRIQUE on Instant-NGP renders at full resolution; ours are CSNet (`saliency`), rule-based
composition on the CSNet map (`composition`) and CNNIQA / NIQE / BRISQUE (`iqa_cnn`, `niqe`,
`brisque`) on our JAX hash-grid NeRFs at small resolutions. Only the ranking of the methods and
the order of magnitude can agree.
"""

from __future__ import annotations

from typing import Any, Dict, Optional, Tuple

__all__ = ["SOURCE_URL", "NERF", "TABLES", "CRITERION_TABLE", "SCENES", "NOT_TRANSCRIBED", "table_for",
           "lookup", "label", "describe"]

SOURCE_URL = "https://arxiv.org/html/2403.04508v2"
NERF = "Instant-NGP"
SCENES = ("fox", "face")

NOT_TRANSCRIBED = ("not transcribed: the stored copy of " + SOURCE_URL + " reachable when this file was written "
                   "holds only the page's opening (abstract, start of the introduction), not its results tables; "
                   "no value was invented")

# One entry per results table of the paper. `table`: the paper's table number (None: not read).
# `values[scene][budget][method] = (CVIR %, mCVIR %)` exactly as printed; empty = not transcribed.
TABLES: Dict[str, Dict[str, Any]] = {
    "saliency": {
        "paper_network": "BASNet",
        "paper_criterion": "saliency maximisation (number of salient pixels, BASNet)",
        "table": None,
        "values": {},
        "note": NOT_TRANSCRIBED,
    },
    "composition": {
        "paper_network": "SAMP-Net",
        "paper_criterion": "photo-composition score (SAMP-Net, mean opinion score in [1, 5])",
        "table": None,
        "values": {},
        "note": NOT_TRANSCRIBED,
    },
    "iqa": {
        "paper_network": "CONTRIQUE",
        "paper_criterion": "no-reference image quality (CONTRIQUE)",
        "table": None,
        "values": {},
        "note": NOT_TRANSCRIBED,
    },
}

# Which paper table each of our criteria stands in for (criteria not listed have none).
CRITERION_TABLE = {"saliency": "saliency", "composition": "composition", "iqa_cnn": "iqa", "niqe": "iqa",
                   "brisque": "iqa"}


def table_for(criterion: str) -> Optional[str]:
    """The paper table our `criterion` stands in for, or None."""
    return CRITERION_TABLE.get(criterion)


def lookup(criterion: str, scene: str, budget: str, method: str) -> Optional[Tuple[float, float]]:
    """(CVIR %, mCVIR %) the paper printed for this cell, or None (no such table, or not transcribed)."""
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
    number = f"Table {entry['table']}" if entry["table"] is not None else "table number not read"
    return (f"paper ({entry['paper_network']} on {NERF}, a different network and NeRF from ours; "
            f"{SOURCE_URL}, {number})")


def describe(criteria) -> Dict[str, Any]:
    """The JSON record of the paper values used for `criteria`: label, availability, values, reason."""
    out: Dict[str, Any] = {"source": SOURCE_URL, "nerf": NERF, "scenes": list(SCENES),
                           "comparable": "in kind only: different criterion networks and NeRF (see paper_values.py)",
                           "criteria": {}}
    for criterion in criteria:
        table = table_for(criterion)
        if table is None:
            out["criteria"][criterion] = {"paper_table": None, "available": False, "label": label(criterion),
                                          "note": "the paper has no table for this criterion"}
            continue
        entry = TABLES[table]
        available = any(entry["values"].get(scene) for scene in SCENES)
        out["criteria"][criterion] = {
            "paper_table": table, "paper_network": entry["paper_network"],
            "paper_criterion": entry["paper_criterion"], "table_number": entry["table"],
            "label": label(criterion), "available": available,
            "values": {scene: {budget: {method: list(cell) for method, cell in methods.items()}
                               for budget, methods in entry["values"].get(scene, {}).items()}
                       for scene in SCENES if entry["values"].get(scene)},
            "note": "" if available else entry["note"],
        }
    return out

"""The figures that decide the method, as the report opens with them and `umad compare` sets them
side by side: the run's protocol in one line; first the shipped configuration (what the graph as run
produced: its fusion weights, label-free masks and refinement), with its weakest drive; then, as the
ablation, the best weight row per mask setting next to MNAD (chosen on the test data after the fact;
with the setting's lowest FPR95, which another row may reach), and the ratios shipped/MNAD, UMAD/MNAD,
unsupervised/GT and unsupervised/no mask.

The paper's published figures (Bogdoll, Ollick et al., BMVC 2024, on AnoVox) stand beside them as a
reference column; they were measured on another dataset with other models.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from umad_common.viz.pages import Cell, Table

SCORES = (("AP", True), ("FPR95", False), ("AUROC", True))  # (key, higher is better)

PAPER_REFERENCE = {  # the paper's column -> its published figures, % on AnoVox (docs/design.md, "The ablation table")
    "gt": "AP 29.90, FPR95 16.93 (PD)",
    "unsupervised": "U2Seg: AP 18.88 (PD); best FPR95 56.54",
    "none": "AP 10.86, FPR95 32.91 (PD)",
    "single": "FPR95 ≈ 86–94",
    "mnad": "AP 6.37, FPR95 89.61, AUROC 61.96",
}
PAPER_RATIOS = {  # from the figures above: U2Seg PD 18.88 against MNAD 6.37, GT PD 29.90, no-mask PD 10.86
    "UMAD / MNAD (AP)": 18.88 / 6.37,
    "unsupervised / GT masks (AP)": 18.88 / 29.90,
    "unsupervised / no mask (AP)": 18.88 / 10.86,
}
COLUMN_TITLES = {
    "gt": "GT masks (mean)",
    "unsupervised": "unsupervised masks (mean)",
    "sam": "SAM masks (mean)",
    "max": "max value",
    "none": "no mask",
    "single": "single mask",
    "unsupervised_pixel": "unsupervised masks (mean_pixel, ours)",
}


def headline_figures(
    rows: list[dict[str, Any]],
    baseline: dict[str, Any] | None,
    settings: list[tuple[str, str]],
    shipped: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The shipped configuration, the best-AP weight row per paper mask setting with the setting's
    lowest-FPR95 row, MNAD and the ratios, JSON-ready.

    Args:
        rows: the ablation rows (`report.table_rows`): `weights_label`, `masks`, AP, FPR95, AUROC.
        baseline: the MNAD row or None.
        settings: (setting label, column) of the paper's mask settings in its order, then ours.
        shipped: the shipped configuration's figures (`report.shipped_figures`) or None.

    Returns:
        {"shipped": {...} | None, "settings": [{column, title, masks, weights_label, AP, FPR95, AUROC,
        lowest_FPR95: {weights_label, FPR95, AP} | None}], "mnad": {...} | None, "ratios": {name: value or None}}.
    """
    best = []
    for label, column in settings:
        scored = [r for r in rows if r["masks"] == label and r["AP"] is not None]
        if not scored:
            continue
        top = max(scored, key=lambda r: r["AP"])
        title = COLUMN_TITLES[column]
        if column in ("unsupervised", "max", "single", "unsupervised_pixel"):
            title += f": {label.rsplit(' ', 1)[0]}"
        best.append(
            {"column": column, "title": title, "masks": label, "weights_label": top["weights_label"]}
            | {key: top[key] for key, _ in SCORES}
            | {"lowest_FPR95": lowest_fpr(rows, label)}
        )
    mnad = None if baseline is None else {key: baseline[key] for key, _ in SCORES}

    def ap(column: str) -> float | None:
        return next((s["AP"] for s in best if s["column"] == column), None)

    def ratio(a: float | None, b: float | None) -> float | None:
        return None if a is None or not b else a / b

    unsupervised = ap("unsupervised")
    ratios = {
        "shipped / MNAD (AP)": ratio(shipped and shipped["AP"], mnad and mnad["AP"]),
        "shipped / MNAD (FPR95)": ratio(shipped and shipped["FPR95"], mnad and mnad["FPR95"]),
        "UMAD / MNAD (AP)": ratio(unsupervised, mnad and mnad["AP"]),
        "unsupervised / GT masks (AP)": ratio(unsupervised, ap("gt")),
        "unsupervised / no mask (AP)": ratio(unsupervised, ap("none")),
    }
    return {"shipped": shipped, "settings": best, "mnad": mnad, "ratios": ratios}


def lowest_fpr(rows: list[dict[str, Any]], masks: str) -> dict[str, Any] | None:
    """The row of mask setting `masks` with the lowest FPR95, as {weights_label, FPR95, AP}; None
    where no row has an FPR95."""
    scored = [r for r in rows if r["masks"] == masks and r["FPR95"] is not None]
    if not scored:
        return None
    low = min(scored, key=lambda r: r["FPR95"])
    return {"weights_label": low["weights_label"], "FPR95": low["FPR95"], "AP": low["AP"]}


def scored_every(protocol: dict[str, Any]) -> int:
    """k of "one frame in every k" scored. The sweep scores the seqs divisible by its k among those
    the source marked scored (divisible by the source's `score_every`): the two combine as their
    least common multiple, times the source's own sampling of the data. A report written before
    the protocol kept `score_every` apart multiplies the source's figure by the sweep's."""
    sweep_every = protocol.get("sweep_every", 1)
    if "score_every" in protocol:
        return protocol.get("world_model_every", 1) * math.lcm(protocol["score_every"], sweep_every)
    return protocol.get("every", 1) * sweep_every


def sampling_text(every: int) -> str:
    """`every frame` or `one frame in every 10`."""
    return "every frame" if every == 1 else f"one frame in every {every}"


def percent(value: float | None) -> str:
    return "n/a" if value is None else f"{100 * value:.2f}"


def ratio_text(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.2f}×"


def protocol_line(protocol: dict[str, Any]) -> str:
    """The run's protocol in one line: data, drives, frames, every-k, scoring resolution, models, PD network."""
    models = protocol.get("models", {})
    every = scored_every(protocol)
    score = "×".join(map(str, protocol.get("score_resolution") or ["?"]))
    label = "×".join(map(str, protocol.get("label_resolution") or ["?"]))
    parts = [
        f"Data {protocol.get('data', 'unknown')}: {protocol.get('drives', 0)} drives, "
        f"{protocol.get('frames', 0)} frames scored ({sampling_text(every)})",
        f"pixels scored at {score} (model resolution; labels {label} resized {protocol.get('label_resize', '?')})",
    ]
    for key, name in (("world_model", "world model"), ("perceptual", "PD network"), ("mnad", "MNAD")):
        if key in models:
            parts.append(f"{name}: {describe_model(models[key])}")
    segmenters = protocol.get("segmenters", {}).values()
    if segmenters:
        parts.append("masks: " + ", ".join(describe_model(s) if "file" in s else s["method"] for s in segmenters))
    if protocol.get("incomplete"):  # reported with --allow-incomplete only
        parts.append(f"INCOMPLETE LOG, {protocol['incomplete']}")
    return "; ".join(parts) + "."


def describe_model(record: dict[str, Any]) -> str:
    """One phrase: `label-free feature net feature_net.safetensors (trained on /data/synth, 16 epochs)`."""
    details = [f"trained on {record['trained_on']}"] if "trained_on" in record else []
    details += [f"{record[k]} {k}" for k in ("drives", "epochs") if k in record]
    name = record.get("network")
    file_name = Path(record["file"]).name if "file" in record else "?"
    return f"{name + ' ' if name else ''}{file_name}" + (f" ({', '.join(details)})" if details else "")


def lowest_fpr_text(lowest: dict[str, Any] | None) -> str:
    """`21.18 (ssim_shift, robust; AP 11.23)`, or `n/a` where no row has an FPR95."""
    if lowest is None:
        return "n/a"
    return f"{percent(lowest['FPR95'])} ({lowest['weights_label']}; AP {percent(lowest['AP'])})"


def weakest_drive_text(shipped: dict[str, Any]) -> str:
    """`AUROC 71.02 (Scenario_246dee45), 1 of 12 below 80 %`, or `n/a` without per-drive figures."""
    weakest = shipped.get("weakest")
    if not weakest:
        return "n/a"
    drives = sum(value is not None for value in shipped["per_drive_AUROC"].values())
    floor = f"{100 * shipped['floor']:.0f} %"
    return f"AUROC {percent(weakest['AUROC'])} ({weakest['drive']}), {shipped['below_floor']} of {drives} below {floor}"


def shipped_table(shipped: dict[str, Any]) -> Table:
    """The shipped configuration's one line: what the graph as run produced."""
    return Table(
        ["shipped configuration", "weights", "masks", "AP ↑", "FPR95 ↓", "AUROC ↑", "weakest drive"],
        [
            [
                Cell(f"as the graph ran ({shipped['refiner'] or 'fusion, no mask'})"),
                Cell(shipped["weights_label"]),
                Cell(shipped["masks"]),
                *(Cell(percent(shipped[key])) for key, _ in SCORES),
                Cell(weakest_drive_text(shipped)),
            ]
        ],
        "The graph's own fusion weights, label-free masks and refinement, as a user runs it: the figure to "
        "expect on new data. Each drive's AUROC: per_scenario.md (`shipped: …`). Values in %.",
    )


def headline_tables(headline: dict[str, Any]) -> list[Table]:
    """The shipped configuration, then the best row per mask setting (and the setting's lowest FPR95) next to
    MNAD, then the ratios; each with the paper's column."""
    best = Table(
        ["mask setting", "best weights", "AP ↑", "FPR95 ↓", "AUROC ↑", "lowest FPR95 ↓", "paper (AnoVox, %)"],
        [
            [
                Cell(s["title"]),
                Cell(s["weights_label"]),
                *(Cell(percent(s[key])) for key, _ in SCORES),
                Cell(lowest_fpr_text(s["lowest_FPR95"])),
                Cell(PAPER_REFERENCE.get(s["column"], "")),
            ]
            for s in headline["settings"]
        ],
        "The ablation: the best AP row per mask setting, chosen on the test data after the fact (not a "
        "configuration to ship), with that row's FPR95 and AUROC; then the setting's lowest FPR95 over all "
        "its rows, that row's weights and AP (the paper also reports a best FPR95 apart); values in %. The "
        "paper's figures were measured on AnoVox with its own models: a reference, not a target on this data.",
    )
    if headline["mnad"] is not None:
        mnad = headline["mnad"]
        best.rows.append(
            [
                Cell("MNAD baseline"),
                Cell("-"),
                *(Cell(percent(mnad[k])) for k, _ in SCORES),
                Cell("-"),
                Cell(PAPER_REFERENCE["mnad"]),
            ]
        )
    ratios = Table(
        ["ratio", "this run", "paper (AnoVox)"],
        [
            [Cell(name), Cell(ratio_text(value)), Cell(ratio_text(PAPER_RATIOS.get(name)))]
            for name, value in headline["ratios"].items()
        ],
        "shipped = the shipped configuration; UMAD = the best unsupervised-mask row (mean refinement).",
    )
    shipped = headline.get("shipped")
    return ([shipped_table(shipped)] if shipped else []) + [best, ratios]

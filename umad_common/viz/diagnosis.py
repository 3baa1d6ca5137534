"""The report's diagnosis (`umad_common.metrics.diagnosis`): results.json's `diagnosis`, its tables
and the picture of the anomaly's score against frames since it first became visible.

It answers two questions at a glance: does a map's error sit on the object or on a normal region
(the top 1 % of each frame's pixels by semantic class), and does the object's score hold while the
ego watches it (its frame AUROC, i.e. mean percentile rank among the frame's normal pixels, per
bin of frames since it first became visible; 50 % = no different from the background).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from umad_common.datasets.anovox import class_name
from umad_common.viz.headline import percent
from umad_common.viz.pages import Cell, Section, Table, text_cells
from umad_common.viz.plots import plot_since_visible

TOP_CLASSES = 6  # classes shown as columns in the overall location table


def named_location(location: dict[int, float]) -> dict[str, float]:
    """Tag -> share to class name -> share (tags of one name, e.g. every anomaly tag, summed), largest first."""
    named: dict[str, float] = {}
    for tag, share in location.items():
        named[class_name(tag)] = named.get(class_name(tag), 0.0) + share
    return dict(sorted(named.items(), key=lambda kv: (-kv[1], kv[0])))


def diagnosis_json(diagnosis: dict) -> dict[str, Any]:
    """The sweep's Diagnosis.compute() with class names for tags and NaN-free numbers."""
    if not diagnosis:
        return {}

    def clean(value: Any) -> Any:
        return None if isinstance(value, float) and math.isnan(value) else value

    return {
        "top_fraction": diagnosis["fraction"],
        "bin_frames": diagnosis["bin_frames"],
        "location": {
            scope: {name: named_location(shares) for name, shares in maps.items()}
            for scope, maps in diagnosis["location"].items()
        },
        "since_visible": {
            name: {run: [{k: clean(v) for k, v in b.items()} for b in bins] for run, bins in curves.items()}
            for name, curves in diagnosis["since_visible"].items()
        },
        "first_visible": diagnosis["first_visible"],
    }


def _map_label(name: str, map_names: dict[str, str]) -> str:
    return map_names.get(name, name)


def location_tables(summary: dict[str, Any], map_names: dict[str, str]) -> list[Table]:
    """Overall: one line per map, the share (%) of the top pixels per class. Per scenario: one line
    per scenario, each map's three largest classes and the anomaly's share."""
    location = summary.get("location", {})
    overall = location.get("overall", {})
    if not overall:
        return []
    order = sorted(overall, key=lambda n: (n == "fused", list(map_names).index(n) if n in map_names else 99, n))
    totals: dict[str, float] = {}
    for shares in overall.values():
        for cls, share in shares.items():
            totals[cls] = totals.get(cls, 0.0) + share
    columns = [c for c, _ in sorted(totals.items(), key=lambda kv: (-kv[1], kv[0]))][:TOP_CLASSES]
    if "anomaly" in totals and "anomaly" not in columns:
        columns[-1] = "anomaly"
    lines = []
    for name in order:
        shares = overall[name]
        other = 1.0 - sum(shares.get(c, 0.0) for c in columns)
        lines.append(
            [Cell(_map_label(name, map_names)), *(Cell(percent(shares.get(c, 0.0))) for c in columns)]
            + [Cell(percent(max(other, 0.0)))]
        )
    first = Table(
        ["map", *columns, "other"],
        lines,
        f"Share (%) of the top {100 * summary['top_fraction']:g} % of each frame's pixels by semantic class, "
        "all scenarios; ignored pixels left out.",
    )
    runs = [run for run in location if run != "overall"]
    rows = []
    for run in runs:
        cells = [Cell(run)]
        for name in order:
            shares = location[run].get(name, {})
            top = list(shares.items())[:3]
            text = ", ".join(f"{cls} {100 * share:.0f}" for cls, share in top)
            if "anomaly" not in dict(top):
                text += f"; anomaly {100 * shares.get('anomaly', 0.0):.1f}"
            cells.append(Cell(text if shares else ""))
        rows.append(cells)
    second = Table(
        ["scenario", *(_map_label(n, map_names) for n in order)],
        rows,
        "Per scenario: each map's three largest classes among its top pixels, and the anomaly's share (%).",
    )
    return [first, second]


def since_visible_tables(summary: dict[str, Any]) -> list[Table]:
    """Per followed map: one line per scenario (and all), the frame AUROC (%) per bin of frames since
    the anomaly first became visible."""
    tables = []
    bin_frames = summary.get("bin_frames")
    for name, curves in summary.get("since_visible", {}).items():
        starts = sorted({b["from"] for bins in curves.values() for b in bins})
        header = [f"scenario ({name})", "first visible", *(f"{s}-{s + bin_frames - 1}" for s in starts)]
        lines = []
        for run, bins in curves.items():
            by_start = {b["from"]: b for b in bins}
            first = summary["first_visible"].get(run, "")
            lines.append(
                [
                    *text_cells(run, first),
                    *(Cell(percent(by_start[s]["rank"]) if s in by_start else "") for s in starts),
                ]
            )
        tables.append(
            Table(
                header,
                lines,
                f"{name}: the anomaly pixels' mean percentile rank among the frame's normal pixels (the frame's "
                "AUROC, %; 50 = no different from the background), mean per bin of frames since the anomaly's "
                "first visible frame (seq).",
            )
        )
    return tables


def diagnosis_section(summary: dict[str, Any], out: Path, map_names: dict[str, str], default_weights: str) -> Section:
    """The report section: location tables, the since-visible picture and tables."""
    if not summary:
        return Section("Diagnosis", ["(no frames with anomaly labels)"])
    lines = [
        f"Where the error lives: of every difference map and of the fused map (default weights: {default_weights}), "
        f"the top {100 * summary['top_fraction']:g} % of each frame's pixels counted by the semantic class under them"
        + ("" if summary["location"] else " (the data carries no semantic labels: not computed)")
        + ". A large share of one normal class (building, sky, road line) is a background the model finds hard.",
        "The anomaly's score while it stays in view: its frame AUROC against frames since it first became visible; "
        "a line that falls while the ego waits is an object the model learns to draw. Files: results.json "
        "(`diagnosis`: also the ratio of the anomaly's mean score to the normal pixels' mean and 99th percentile), "
        "since_visible.png.",
    ]
    images = []
    if summary["since_visible"]:
        plot_since_visible(summary["since_visible"], summary["bin_frames"], out / "since_visible.png")
        images.append(("since_visible.png", "the anomaly's frame AUROC against frames since it first became visible"))
    tables = location_tables(summary, map_names) + since_visible_tables(summary)
    return Section("Diagnosis: where the error lives, and the anomaly's score over time", lines, tables, images)

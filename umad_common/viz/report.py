"""The evaluation report of a sweep: results.json, the ablation table (Markdown, CSV), curves,
overlay grids, the per-scenario breakdown and an index (Markdown and HTML) tying them together.

Table values are percentages; in each metric column the best value is **bold** and the second best
_italic_ (AP and AUROC: higher is better; FPR95: lower is better), the MNAD baseline included.
"""

from __future__ import annotations

import csv
import html
import json
import math
import re
from fractions import Fraction
from pathlib import Path
from typing import TYPE_CHECKING, Any

from umad_common.datasets.anovox import ANOMALY_CATEGORIES
from umad_common.metrics.pixel import PixelMetrics
from umad_common.viz.plots import plot_curves, plot_overlay_grid

if TYPE_CHECKING:
    from replay.sweep import SweepResult

METRIC_COLUMNS = {"abs": "ABS", "mse": "MSE", "ssim": "SSIM", "perceptual": "PD", "temporal": "TD"}
PAPER_METRICS = tuple(METRIC_COLUMNS)
SCORES = (("AP", True), ("FPR95", False), ("AUROC", True))  # (key, higher is better)


def _number(value: float) -> float | None:
    return None if value is None or math.isnan(value) else float(value)


def component_table(components: dict[str, dict]) -> str:
    """SegmentMeIfYouCan component metrics per configuration (Markdown)."""
    if not components:
        return "(not computed)\n"
    lines = [
        "| configuration | threshold | sIoU | PPV | mean F1 | GT components | predicted components |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, c in components.items():
        cells = [f"{c['threshold']:.4g}", *(_percent(_number(c[k])) for k in ("sIoU", "PPV", "mean_F1"))]
        lines.append(
            f"| {name} | " + " | ".join([*cells, str(c["n_truth_components"]), str(c["n_predicted_components"])]) + " |"
        )
    return (
        "\n".join(lines) + "\n\nScore maps thresholded at each configuration's best pixel-F1 threshold; values in %.\n"
    )


def table_rows(result: SweepResult) -> list[dict[str, Any]]:
    """One dict per configuration, in table order: weight row, then mask setting; MNAD excluded."""
    order = {label: i for i, label in enumerate(result.setting_labels())}
    configs = sorted(result.metrics, key=lambda c: (c.row, order.get(result.setting_label(c), 99)))
    rows = []
    for config in configs:
        scores = result.metrics[config].compute()
        rows.append(
            {
                "weights": {m: float(w) for m, w in result.rows[config.row].items()},
                "weights_label": result.row_label(config.row),
                "masks": result.setting_label(config),
                "segmenter": config.segmenter,
                "mode": config.mode,
                "AP": _number(scores["AP"]),
                "FPR95": _number(scores["FPR95"]),
                "AUROC": _number(scores["AUROC"]),
                "frames": result.frames[config],
                "n_anomaly": scores["n_anomaly"],
                "n_normal": scores["n_normal"],
            }
        )
    return rows


def baseline_row(result: SweepResult) -> dict[str, Any] | None:
    if result.baseline is None:
        return None
    scores = result.baseline.compute()
    return {
        "name": "MNAD",
        "masks": "no mask",
        "AP": _number(scores["AP"]),
        "FPR95": _number(scores["FPR95"]),
        "AUROC": _number(scores["AUROC"]),
        "frames": result.baseline_frames,
        "n_anomaly": scores["n_anomaly"],
        "n_normal": scores["n_normal"],
    }


def rank_marks(rows: list[dict[str, Any]]) -> list[dict[str, str]]:
    """Per row and score column: "best", "second" or "" (values equal as shown, in % to 2 decimals, share a mark)."""
    marks = [{key: "" for key, _ in SCORES} for _ in rows]
    for key, higher in SCORES:
        shown = [None if r[key] is None else round(100 * r[key], 2) for r in rows]
        values = sorted({v for v in shown if v is not None}, reverse=higher)
        for mark, value in zip(("best", "second"), values, strict=False):
            for i, v in enumerate(shown):
                if v == value:
                    marks[i][key] = mark
    return marks


def _percent(value: float | None, mark: str = "") -> str:
    if value is None:
        return "n/a"
    text = f"{100 * value:.2f}"
    return f"**{text}**" if mark == "best" else f"_{text}_" if mark == "second" else text


def write_table(rows: list[dict[str, Any]], baseline: dict[str, Any] | None, md_path: Path, csv_path: Path) -> str:
    """The ablation table as Markdown (returned too) and CSV, baseline last."""
    everything = rows + ([baseline] if baseline else [])
    marks = rank_marks(everything)
    header = [METRIC_COLUMNS[m] for m in PAPER_METRICS] + ["Masks", "AP ↑", "FPR95 ↓", "AUROC ↑", "frames"]
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    with open(csv_path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            ["method", *PAPER_METRICS, "masks", "AP", "FPR95", "AUROC", "AP_mark", "FPR95_mark", "AUROC_mark", "frames"]
        )
        for row, mark in zip(everything, marks, strict=True):
            weights = row.get("weights", {})
            fractions = [str(Fraction(weights[m]).limit_denominator(10)) if m in weights else "" for m in PAPER_METRICS]
            cells = fractions if "weights" in row else ["MNAD baseline", "", "", "", ""]
            lines.append(
                "| "
                + " | ".join(
                    [*cells, row["masks"], *(_percent(row[k], mark[k]) for k, _ in SCORES), str(row["frames"])]
                )
                + " |"
            )
            writer.writerow(
                [
                    "UMAD" if "weights" in row else row["name"],
                    *fractions,
                    row["masks"],
                    *("" if row[k] is None else f"{row[k]:.6f}" for k, _ in SCORES),
                    *(mark[k] for k, _ in SCORES),
                    row["frames"],
                ]
            )
    text = "\n".join(lines) + "\n\n**bold** = best, _italic_ = second best per column (MNAD included). Values in %.\n"
    md_path.write_text(text)
    return text


def pivot_table(rows: list[dict[str, Any]], baseline: dict[str, Any] | None, key: str = "AP") -> str:
    """One score as a weight-row x mask-setting grid (Markdown), the compact view of the ablation."""
    settings = list(dict.fromkeys(r["masks"] for r in rows))
    labels = list(dict.fromkeys(r["weights_label"] for r in rows))
    cell = {(r["weights_label"], r["masks"]): r[key] for r in rows}
    lines = [f"| {key} (%) | " + " | ".join(settings) + " |", "|---|" + "---|" * len(settings)]
    for label in labels:
        lines.append(f"| {label} | " + " | ".join(_percent(cell.get((label, s))) for s in settings) + " |")
    if baseline is not None:
        lines.append("| MNAD baseline | " + " | ".join([_percent(baseline[key])] + [""] * (len(settings) - 1)) + " |")
    return "\n".join(lines) + "\n"


def scenario_table(result: SweepResult, md_path: Path, csv_path: Path) -> str:
    """AP / FPR95 / AUROC per scenario for the default weight row under each mask setting and MNAD,
    with the AnoVox categories found under the scenario's anomaly pixels."""
    present = {label for per_run in result.per_scenario.values() for label in per_run}
    settings = [label for label in [*result.setting_labels(), "MNAD"] if label in present]
    lines = [
        "| scenario | anomaly | " + " | ".join(f"{s} AP / FPR95 / AUROC" for s in settings) + " |",
        "|---|---|" + "---|" * len(settings),
    ]
    with open(csv_path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["scenario", "anomaly", "setting", "AP", "FPR95", "AUROC", "n_anomaly", "n_normal"])
        for run in sorted(result.per_scenario):
            tags = sorted(result.scenario_tags.get(run, ()))
            anomaly = "+".join(ANOMALY_CATEGORIES.get(t, str(t)) for t in tags) or "-"
            cells = []
            for setting in settings:
                metrics = result.per_scenario[run].get(setting)
                if metrics is None:
                    cells.append("")
                    continue
                s = metrics.compute()
                cells.append(" / ".join(_percent(_number(s[k])) for k, _ in SCORES))
                writer.writerow(
                    [run, anomaly, setting, *(_number(s[k]) for k, _ in SCORES), s["n_anomaly"], s["n_normal"]]
                )
            lines.append(f"| {run} | {anomaly} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    md_path.write_text(text)
    return text


def selected_curves(result: SweepResult, rows: list[dict[str, Any]]) -> dict[str, PixelMetrics]:
    """Curves worth drawing: the best-AP configuration, the default row per mask setting, MNAD."""
    curves: dict[str, PixelMetrics] = {}
    scored = [c for c in result.metrics if result.metrics[c].n_anomaly]
    if scored:
        best = max(scored, key=lambda c: result.metrics[c].compute()["AP"])
        curves[f"best: {result.row_label(best.row)}, {result.setting_label(best)}"] = result.metrics[best]
    if result.default_row is not None:
        for config in result.metrics:
            if config.row == result.default_row and config.mode in ("none", "mean"):
                curves[f"{result.row_label(config.row)}, {result.setting_label(config)}"] = result.metrics[config]
    if result.baseline is not None:
        curves["MNAD"] = result.baseline
    return curves


def write_report(result: SweepResult, out: str | Path, log_path: str | Path | None = None) -> Path:
    """Write every report file into `out`; returns the index.md path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows, baseline = table_rows(result), baseline_row(result)
    stats = result.stats
    summary = {
        "log": str(log_path) if log_path else None,
        "rows": rows,
        "baseline": baseline,
        "default_weights": None if result.default_row is None else result.row_label(result.default_row),
        "per_scenario": {
            run: {label: {k: _number(m.compute()[k]) for k, _ in SCORES} for label, m in per_run.items()}
            for run, per_run in sorted(result.per_scenario.items())
        },
        "components": {
            name: {k: (_number(v) if isinstance(v, float) else v) for k, v in c.items()}
            for name, c in result.components.items()
        },
        "segmenters": result.segmenters,
        "skipped_weight_rows": [result.row_label(i) for i in result.skipped_rows],
        "log_stats": {k: v for k, v in vars(stats).items() if k != "segmenters"},
        "sweep_seconds": round(result.seconds, 2),
    }
    (out / "results.json").write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")
    table = write_table(rows, baseline, out / "table.md", out / "table.csv")
    summary_pivot = pivot_table(rows, baseline)
    scenarios = scenario_table(result, out / "per_scenario.md", out / "per_scenario.csv")
    plot_curves(selected_curves(result, rows), out / "pr_curves.png", out / "roc_curves.png")
    overlay_files = []
    for i, frame in enumerate(result.overlays):
        name = f"overlay_{i:02d}.png"
        title = f"{frame.run} #{frame.seq}: {frame.anomaly_pixels} anomaly pixels"
        plot_overlay_grid(frame.images, title, out / name)
        overlay_files.append((name, title))
    components = component_table(result.components)
    (out / "components.md").write_text(components)
    index = _index_markdown({**summary, "pivot": summary_pivot}, table, scenarios, components, overlay_files)
    (out / "index.md").write_text(index)
    (out / "index.html").write_text(_index_html(summary, out, overlay_files))
    return out / "index.md"


def _log_lines(summary: dict[str, Any]) -> list[str]:
    s = summary["log_stats"]
    lines = [
        f"- log: `{summary['log']}`" if summary["log"] else "- log: (in memory)",
        f"- frames: {s['frames']} grouped from {s['messages']} messages ({s['decoded']} decoded); "
        f"{s['duplicates']} duplicates, {s['late']} late, {s['bad']} undecodable",
        f"- sweep time: {summary['sweep_seconds']} s for {len(summary['rows'])} configurations",
        f"- default weights for the breakdown and pictures: {summary['default_weights']}",
    ]
    if s["truncated"]:
        lines.append(f"- **log truncated**: {s['truncated']}")
    if summary["skipped_weight_rows"]:
        lines.append(f"- weight rows without their metrics in the log: {', '.join(summary['skipped_weight_rows'])}")
    return lines


def _index_markdown(
    summary: dict[str, Any], table: str, scenarios: str, components: str, overlays: list[tuple[str, str]]
) -> str:
    parts = ["# UMAD evaluation report", "", *_log_lines(summary), ""]
    parts += ["## AP by weights and masks", "", summary["pivot"]]
    parts += ["## Ablation table", "", "Files: `results.json`, `table.md`, `table.csv`.", "", table]
    parts += ["## Component metrics (SegmentMeIfYouCan)", "", components]
    parts += ["## Curves", "", "![precision-recall](pr_curves.png)", "![ROC](roc_curves.png)", ""]
    parts += ["## Per scenario (default weights)", "", "Files: `per_scenario.md`, `per_scenario.csv`.", "", scenarios]
    parts += ["## Frames with the largest anomalies", ""]
    parts += [f"### {title}\n\n![{title}]({name})\n" for name, title in overlays] or ["(no frame with anomaly pixels)"]
    return "\n".join(parts) + "\n"


def markdown_tables_html(text: str) -> str:
    """The report's Markdown (pipe tables, **best**, _second_, plain lines) as HTML, so the page
    shows exactly the table files' values and marks."""

    def cell(c: str, tag: str) -> str:
        c = html.escape(c.strip())
        c = re.sub(r"\*\*(.+?)\*\*", r"<b>\1</b>", c)
        c = re.sub(r"(?<![\w])_(.+?)_(?![\w])", r"<i>\1</i>", c)
        return f"<{tag}>{c}</{tag}>"

    parts, rows = [], []
    for line in [*text.splitlines(), ""]:
        if line.startswith("|"):
            if not set(line) <= set("|-: "):
                rows.append(line.strip().strip("|").split("|"))
            continue
        if rows:
            head = "".join(cell(c, "th") for c in rows[0])
            body = "".join("<tr>" + "".join(cell(c, "td") for c in r) + "</tr>" for r in rows[1:])
            parts.append(f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>")
            rows = []
        if line.strip():
            parts.append(f"<p>{cell(line, 'span')}</p>")
    return "".join(parts)


def _index_html(summary: dict[str, Any], out: Path, overlays: list[tuple[str, str]]) -> str:
    def tables(name: str) -> str:
        return markdown_tables_html((out / name).read_text())

    items = "".join(f"<li>{html.escape(line[2:])}</li>" for line in _log_lines(summary))
    pictures = "".join(f"<h3>{html.escape(t)}</h3><img src='{n}' alt='{html.escape(t)}'>" for n, t in overlays)
    return (
        "<!doctype html><html><head><meta charset='utf-8'><title>UMAD evaluation report</title>"
        "<style>body{font-family:sans-serif;margin:2em}table{border-collapse:collapse;font-size:12px}"
        "td,th{border:1px solid #ccc;padding:2px 6px}img{max-width:100%}</style></head><body>"
        f"<h1>UMAD evaluation report</h1><ul>{items}</ul>"
        f"<h2>Ablation table</h2>{tables('table.md')}"
        f"<h2>Component metrics (SegmentMeIfYouCan)</h2>{tables('components.md')}"
        "<h2>Curves</h2><img src='pr_curves.png' alt='precision-recall'><img src='roc_curves.png' alt='ROC'>"
        f"<h2>Per scenario (default weights)</h2>{tables('per_scenario.md')}"
        f"<h2>Frames with the largest anomalies</h2>{pictures}</body></html>\n"
    )

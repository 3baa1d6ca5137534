"""The evaluation report of a sweep: results.json, the ablation table (Markdown, CSV), curves,
overlay grids, the per-scenario, diagnosis (`diagnosis.py`) and component tables, and the page tying them together
(index.md and index.html, rendered from the same rows by the templates in `templates/`).

The page opens with the headline (`headline.py`): the run's protocol in one line, the shipped
configuration (what the graph as run produced, with its weakest drive), the best row per mask setting
(chosen on this data: the ablation) next to MNAD and the ratios; then the AP pivot (weights x
mask settings), the pictures, and the full tables. Rows and mask settings that are not in the
paper's table are marked `extra`.

Table values are percentages; in each metric column the best value is **bold** and the second best
_italic_ (AP and AUROC: higher is better; FPR95: lower is better), the MNAD baseline included.
"""

from __future__ import annotations

import csv
import json
import math
from fractions import Fraction
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from umad_common.datasets.anovox import ANOMALY_CATEGORIES
from umad_common.metrics.pixel import PixelMetrics
from umad_common.refine import fusion_note
from umad_common.viz.diagnosis import diagnosis_json, diagnosis_section
from umad_common.viz.headline import SCORES, headline_figures, headline_tables, percent, protocol_line
from umad_common.viz.pages import Cell, Page, Section, Table, render_table_markdown, text_cells, write_page
from umad_common.viz.plots import plot_curves, plot_overlay_grid

if TYPE_CHECKING:
    from umad_replay.sweep import SweepResult

METRIC_COLUMNS = {  # a weight row's metric -> its column: the paper's five, then ours
    "abs": "ABS",
    "mse": "MSE",
    "ssim": "SSIM",
    "perceptual": "PD",
    "temporal": "TD",
    "ssim_shift": "SSIM±2",
    "lidar": "LIDAR",
}
METRICS = tuple(METRIC_COLUMNS)
AUROC_FLOOR = 0.80  # a scenario whose AUROC is below this is one the detector fails (issue 30's bar)
Layout = Literal["long", "paper"]
LAYOUTS = ("long", "paper")


def _number(value: float | None) -> float | None:
    return None if value is None or math.isnan(value) else float(value)


def table_rows(result: SweepResult) -> list[dict[str, Any]]:
    """One dict per configuration, in table order: weight row, then mask setting; MNAD excluded.
    `extra` is True where the weight row or the mask setting is not in the paper's table,
    `extra_weights` where the weight row is not."""
    order = {label: i for i, label in enumerate(result.setting_labels())}
    paper = {setting.label for setting in result.paper_settings()}
    configs = sorted(result.metrics, key=lambda c: (c.row, order.get(result.setting_label(c), 99)))
    rows = []
    for config in configs:
        scores = result.metrics[config].compute()
        label = result.setting_label(config)
        rows.append(
            {
                "weights": {m: float(w) for m, w in result.rows[config.row].weights.items()},
                "weights_label": result.row_label(config.row),
                "masks": label,
                "extra": result.rows[config.row].extra or label not in paper,
                "extra_weights": result.rows[config.row].extra,
                "normalization": result.rows[config.row].normalization,
                "above_lidar_weight": result.rows[config.row].above_lidar_weight,
                "lidar_camera_exponent": result.rows[config.row].lidar_camera_exponent,
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


def shipped_figures(result: SweepResult) -> dict[str, Any] | None:
    """What the graph as run produced (`SweepResult.shipped`): its weights, masks, AP / FPR95 / AUROC,
    each drive's AUROC (from the second pass), the weakest drive and how many fall below AUROC_FLOOR;
    None where the graph had no shipped configuration or the log none of its maps."""
    name = result.shipped_name()
    if name is None or result.shipped not in result.metrics:
        return None
    scores = result.metrics[result.shipped].compute()
    per_drive = {
        run: _number(per_run[name].compute()["AUROC"])
        for run, per_run in sorted(result.per_scenario.items())
        if name in per_run
    }
    scored = {run: auroc for run, auroc in per_drive.items() if auroc is not None}
    weakest = min(scored, key=scored.get) if scored else None
    spec = result.protocol.get("shipped", {})
    return {
        "name": name,
        "refiner": spec.get("refiner"),
        "weights_label": result.row_label(result.shipped.row),
        "masks": result.setting_label(result.shipped),
        **{key: _number(scores[key]) for key, _ in SCORES},
        "per_drive_AUROC": per_drive,
        "weakest": None if weakest is None else {"drive": weakest, "AUROC": scored[weakest]},
        "below_floor": sum(auroc < AUROC_FLOOR for auroc in scored.values()),
        "floor": AUROC_FLOOR,
    }


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


def rank_marks(rows: list[dict[str, Any]], keys: tuple[tuple[str, bool], ...] = SCORES) -> list[dict[str, str]]:
    """Per row and score column: "best", "second" or "" (values equal as shown, in % to 2 decimals, share a mark)."""
    marks = [{key: "" for key, _ in keys} for _ in rows]
    for key, higher in keys:
        shown = [None if r.get(key) is None else round(100 * r[key], 2) for r in rows]
        values = sorted({v for v in shown if v is not None}, reverse=higher)
        for mark, value in zip(("best", "second"), values, strict=False):
            for i, v in enumerate(shown):
                if v == value:
                    marks[i][key] = mark
    return marks


def _fractions(weights: dict[str, float]) -> list[str]:
    return [str(Fraction(weights[m]).limit_denominator(60)) if m in weights else "" for m in METRICS]


def _normalization_note(row: dict[str, Any]) -> str:
    """`, robust` for a row fused from robust-normalised maps, then how its fusion departs from the
    paper's (`fusion_note`); nothing for the paper's fusion of min-max maps."""
    normalization = row.get("normalization", "minmax")
    extras = fusion_note(row.get("above_lidar_weight", 1.0), row.get("lidar_camera_exponent", 0.0))
    return ("" if normalization == "minmax" else f", {normalization}") + extras


def _row_name(row: dict[str, Any]) -> str:
    return row["weights_label"] + (" (extra)" if row["extra_weights"] else "")


def ablation_table(rows: list[dict[str, Any]], baseline: dict[str, Any] | None) -> Table:
    """Every configuration, one line each (weights, masks, AP, FPR95, AUROC, frames), MNAD last."""
    everything = rows + ([baseline] if baseline else [])
    marks = rank_marks(everything)
    header = [*METRIC_COLUMNS.values(), "Masks", "AP ↑", "FPR95 ↓", "AUROC ↑", "frames", "in paper"]
    lines = []
    for row, mark in zip(everything, marks, strict=True):
        weights = _fractions(row["weights"]) if "weights" in row else ["MNAD baseline"] + [""] * (len(METRICS) - 1)
        in_paper = ("extra" if row.get("extra") else "yes") + _normalization_note(row)
        lines.append(
            [
                *text_cells(*weights, row["masks"]),
                *(Cell(percent(row[k]), mark[k]) for k, _ in SCORES),
                *text_cells(row["frames"], in_paper),
            ]
        )
    return Table(header, lines, "**bold** = best, _italic_ = second best per column (MNAD included). Values in %.")


def paper_layout_table(rows: list[dict[str, Any]], baseline: dict[str, Any] | None, settings: list[str]) -> Table:
    """The paper's layout: one line per weight row, AP and FPR95 under each of its mask settings in
    its order (GT / unsupervised / SAM with mean refinement, max value, no mask, single mask)."""
    cell = {(r["weights_label"], r["masks"]): r for r in rows}
    weight_rows = {r["weights_label"]: r for r in rows}  # label -> a row with its weights and extra flag
    keys = tuple((f"{s} {k}", k == "AP") for s in settings for k in ("AP", "FPR95"))
    grid = [
        {f"{s} {k}": (cell.get((label, s)) or {}).get(k) for s in settings for k in ("AP", "FPR95")}
        for label in weight_rows
    ]
    marks = rank_marks(grid, keys)
    header = [*METRIC_COLUMNS.values(), "row", *(f"{name} {'↑' if higher else '↓'}" for name, higher in keys)]
    lines = [
        [
            *text_cells(
                *_fractions(row["weights"]), ("extra" if row["extra_weights"] else "paper") + _normalization_note(row)
            ),
            *(Cell(percent(values[k]), mark[k]) for k, _ in keys),
        ]
        for row, values, mark in zip(weight_rows.values(), grid, marks, strict=True)
    ]
    note = "Bold / italic: best / second best per column. Values in %."
    if baseline is not None:
        note += f" MNAD baseline: AP {percent(baseline['AP'])}, FPR95 {percent(baseline['FPR95'])}."
    return Table(header, lines, note)


def pivot_table(rows: list[dict[str, Any]], baseline: dict[str, Any] | None, paper_settings: list[str]) -> Table:
    """AP as a weight-row x mask-setting grid, the compact view of the ablation; best and second
    best weight row marked per mask setting (column)."""
    settings = list(dict.fromkeys(r["masks"] for r in rows))
    names = list(dict.fromkeys(_row_name(r) for r in rows))
    cell = {(_row_name(r), r["masks"]): r["AP"] for r in rows}
    grid = [{s: cell.get((name, s)) for s in settings} for name in names]
    marks = rank_marks(grid, tuple((s, True) for s in settings))
    header = ["AP (%)", *(s if s in paper_settings else f"{s} (extra)" for s in settings)]
    lines = [
        [Cell(name), *(Cell(percent(values[s]), mark[s]) for s in settings)]
        for name, values, mark in zip(names, grid, marks, strict=True)
    ]
    if baseline is not None:  # MNAD scores pixels without masks: its AP stands under "no mask"
        lines.append(
            [Cell("MNAD baseline"), *(Cell(percent(baseline["AP"]) if s == "no mask" else "") for s in settings)]
        )
    return Table(header, lines, "Bold / italic: best / second best weight row under each mask setting.")


def write_ablation_csv(rows: list[dict[str, Any]], baseline: dict[str, Any] | None, path: Path) -> None:
    """The long table as CSV (fractions, masks, scores as fractions of 1, marks), MNAD last."""
    everything = rows + ([baseline] if baseline else [])
    marks = rank_marks(everything)
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(
            ["method", *METRICS, "masks", "AP", "FPR95", "AUROC", "AP_mark", "FPR95_mark", "AUROC_mark"]
            + ["frames", "extra"]
        )
        for row, mark in zip(everything, marks, strict=True):
            writer.writerow(
                [
                    "UMAD" if "weights" in row else row["name"],
                    *(_fractions(row["weights"]) if "weights" in row else [""] * len(METRICS)),
                    row["masks"],
                    *("" if row[k] is None else f"{row[k]:.6f}" for k, _ in SCORES),
                    *(mark[k] for k, _ in SCORES),
                    row["frames"],
                    int(bool(row.get("extra"))),
                ]
            )


def component_table(components: dict[str, dict]) -> Table:
    """SegmentMeIfYouCan component metrics per configuration."""
    header = ["configuration", "threshold", "sIoU", "PPV", "mean F1", "GT components", "predicted components"]
    lines = [
        [
            Cell(name),
            Cell(f"{c['threshold']:.4g}"),
            *(Cell(percent(_number(c[k]))) for k in ("sIoU", "PPV", "mean_F1")),
            *text_cells(c["n_truth_components"], c["n_predicted_components"]),
        ]
        for name, c in components.items()
    ]
    note = "Score maps thresholded at each configuration's best pixel-F1 threshold; values in %."
    return Table(header, lines, note if components else "(not computed)")


def scenario_table(result: SweepResult, csv_path: Path) -> Table:
    """AP / FPR95 / AUROC per scenario for the default weight row under each mask setting, the shipped
    configuration (`shipped: <setting>: <row>`) and the best row under each headline mask setting
    (`best <setting>: <row>`), both from the sweep's second pass, and
    MNAD, with the AnoVox categories found under the scenario's anomaly pixels and the drive's weather
    (`?` where the data's scenario config does not name it); also written as CSV. A last line names
    each setting's weakest scenario (and its weather) by AUROC and how many fall below AUROC_FLOOR."""
    present = list(dict.fromkeys(label for per_run in result.per_scenario.values() for label in per_run))
    default_row = [label for label in result.setting_labels() if label in present]
    best_rows = [label for label in present if label not in default_row and label != "MNAD"]
    settings = default_row + best_rows + (["MNAD"] if "MNAD" in present else [])
    aurocs: dict[str, dict[str, float]] = {setting: {} for setting in settings}  # setting -> run -> AUROC
    weathers = result.protocol.get("scenario_weather", {})
    lines = []
    with open(csv_path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["scenario", "anomaly", "weather", "setting", "AP", "FPR95", "AUROC", "n_anomaly", "n_normal"])
        for run in sorted(result.per_scenario):
            tags = sorted(result.scenario_tags.get(run, ()))
            anomaly = "+".join(ANOMALY_CATEGORIES.get(t, str(t)) for t in tags) or "-"
            weather = weathers.get(run, "?")
            cells = text_cells(run, anomaly, weather)
            for setting in settings:
                metrics = result.per_scenario[run].get(setting)
                if metrics is None:
                    cells.append(Cell(""))
                    continue
                s = metrics.compute()
                scores = {k: _number(s[k]) for k, _ in SCORES}
                if scores["AUROC"] is not None:
                    aurocs[setting][run] = scores["AUROC"]
                cells.append(Cell(" / ".join(map(percent, scores.values()))))
                writer.writerow([run, anomaly, weather, setting, *scores.values(), s["n_anomaly"], s["n_normal"]])
            lines.append(cells)
    if len(result.per_scenario) > 1:
        lines.append(
            text_cells(
                "weakest scenario",
                f"below {100 * AUROC_FLOOR:.0f} % AUROC",
                "",
                *(weakest_text(per_run, weathers) for per_run in aurocs.values()),
            )
        )
    return Table(["scenario", "anomaly", "weather", *(f"{s} AP / FPR95 / AUROC" for s in settings)], lines)


def weakest_text(aurocs: dict[str, float], weathers: dict[str, str]) -> str:
    """`AUROC <lowest> (<its scenario's short name>[, <its weather>]), <n> of <N> below AUROC_FLOOR`
    for one setting's per-scenario AUROCs (run -> AUROC), or "" when none was scored."""
    if not aurocs:
        return ""
    run = min(aurocs, key=aurocs.get)
    below = sum(value < AUROC_FLOOR for value in aurocs.values())
    name = ", ".join([run.removeprefix("Scenario_")[:8], *([weathers[run]] if run in weathers else [])])
    return f"AUROC {percent(aurocs[run])} ({name}), {below} of {len(aurocs)} below"


def selected_curves(result: SweepResult) -> dict[str, PixelMetrics]:
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


def run_protocol(result: SweepResult, layout: Layout) -> dict[str, Any]:
    """The log's protocol (data, models, PD network) with what the sweep scored: drives, frame ids,
    every-k and the resolutions; `umad compare` checks two runs' frames against it."""
    return {
        **result.protocol,
        "layout": layout,
        "sweep_every": result.every,
        "drives": len(result.frames_evaluated),
        "frames": sum(len(seqs) for seqs in result.frames_evaluated.values()),
        "score_resolution": _shape(result.score_shapes),
        "label_resolution": _shape(result.truth_shapes),
        "frames_evaluated": result.frames_evaluated,
    }


def _shape(shapes: set[tuple[int, int]]) -> list[int] | list[list[int]] | None:
    """One (h, w) as a list; several (a run that mixed sizes) as a list of them; None if none."""
    ordered = sorted(shapes)
    return list(ordered[0]) if len(ordered) == 1 else [list(s) for s in ordered] or None


def write_report(
    result: SweepResult, out: str | Path, log_path: str | Path | None = None, layout: Layout = "long"
) -> Path:
    """Write every report file into `out`; returns the index.md path.

    Args:
        result: the sweep.
        out: report folder (created).
        log_path: the log the sweep read, named in the report.
        layout: `long` (table.md: one line per configuration) or `paper` (table.md in the paper's
            layout: one line per weight row, AP and FPR95 per paper mask setting).
    """
    if layout not in LAYOUTS:
        raise ValueError(f"report layout {layout!r}; expected one of {LAYOUTS}")
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rows, baseline = table_rows(result), baseline_row(result)
    paper_settings = result.paper_settings()
    paper_labels = [s.label for s in paper_settings]
    settings = [(s.label, s.column) for s in result.headline_settings()]
    headline = headline_figures(rows, baseline, settings, shipped_figures(result))
    protocol = run_protocol(result, layout)
    stats = result.stats
    summary = {
        "log": str(log_path) if log_path else None,
        "protocol": protocol,
        "headline": headline,
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
        "diagnosis": diagnosis_json(result.diagnosis),
        "segmenters": result.segmenters,
        "skipped_weight_rows": [result.row_label(i) for i in result.skipped_rows],
        "log_stats": {k: v for k, v in vars(stats).items() if k not in ("segmenters", "map_notes")},
        "sweep_seconds": round(result.seconds, 2),
    }
    (out / "results.json").write_text(json.dumps(summary, indent=2, allow_nan=False) + "\n")

    long_table = ablation_table(rows, baseline)
    table = paper_layout_table(rows, baseline, paper_labels) if layout == "paper" else long_table
    write_ablation_csv(rows, baseline, out / "table.csv")
    scenarios = scenario_table(result, out / "per_scenario.csv")
    components = component_table(result.components)
    protocol_text = protocol_line(protocol)
    for name, written in (("table.md", table), ("per_scenario.md", scenarios), ("components.md", components)):
        (out / name).write_text(f"{render_table_markdown(written)}\nProtocol: {protocol_text}\n")

    plot_curves(selected_curves(result), out / "pr_curves.png", out / "roc_curves.png")
    overlays = []
    for i, frame in enumerate(result.overlays):
        name = f"overlay_{i:02d}.png"
        title = f"{frame.run} #{frame.seq}: {frame.anomaly_pixels} anomaly pixels"
        plot_overlay_grid(frame.images, title, out / name)
        overlays.append((name, title))

    sections = [
        Section("Headline", tables=headline_tables(headline)),
        Section("AP by weights and mask settings", tables=[pivot_table(rows, baseline, paper_labels)]),
        Section(
            "Curves and frames with the largest anomalies",
            images=[("pr_curves.png", "precision-recall"), ("roc_curves.png", "ROC"), *overlays],
        ),
        Section(
            "Ablation table" + (" (the paper's layout)" if layout == "paper" else ""),
            ["Files: results.json, table.md, table.csv (every configuration, one line each)."],
            [table],
        ),
        Section(
            "Per scenario",
            [
                f"Default weights ({summary['default_weights']}) under each mask setting, then the shipped "
                "configuration (`shipped: …`, what the graph as run produced), then the best row under each "
                "headline mask setting (`best …`, chosen on this data); the last line names each one's weakest "
                f"scenario by AUROC and counts those below {100 * AUROC_FLOOR:.0f} %. Each drive's weather is the "
                "one the data's scenario config names (`?` where it names none). Files: per_scenario.md, "
                "per_scenario.csv."
            ],
            [scenarios],
        ),
        diagnosis_section(summary["diagnosis"], out, METRIC_COLUMNS, str(summary["default_weights"])),
        Section("Component metrics (SegmentMeIfYouCan)", tables=[components]),
        Section("Run", _run_lines(summary)),
    ]
    page = Page("UMAD evaluation report", protocol_text, sections)
    index, _ = write_page(page, out, "index")
    return index


def _run_lines(summary: dict[str, Any]) -> list[str]:
    s = summary["log_stats"]
    lines = [
        f"Log: {summary['log'] or '(in memory)'}",
        f"Frames: {s['frames']} grouped from {s['messages']} messages ({s['decoded']} decoded); "
        f"{s['duplicates']} duplicates, {s['late']} late, {s['bad']} undecodable.",
        f"Sweep time: {summary['sweep_seconds']} s for {len(summary['rows'])} configurations.",
        "Normalization per metric: "
        + (", ".join(f"{m}: {n}" for m, n in summary["protocol"].get("normalization", {}).items()) or "unknown"),
    ]
    if s["truncated"]:
        lines.append(f"Log truncated: {s['truncated']}")
    if summary["skipped_weight_rows"]:
        lines.append(f"Weight rows without their metrics in the log: {', '.join(summary['skipped_weight_rows'])}")
    return lines

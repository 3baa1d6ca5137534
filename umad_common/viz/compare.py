"""Two evaluation runs side by side (`umad compare`): the shipped configuration, the headline figures
and every ablation row of run A and run B with the difference B - A, each B value marked where B is
better.

Runs are compared only when they scored the same frames: the same scenarios, the same frame ids
in each, the same every-k (read from each results.json's `protocol`). Otherwise `FramesDiffer`
names the first difference. The data folder may differ (the built-in benchmark is generated into
each run's own folder); the page says so.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from umad_common.viz.headline import (
    SCORES,
    describe_model,
    lowest_fpr,
    percent,
    protocol_line,
    ratio_text,
    sampling_text,
    scored_every,
)
from umad_common.viz.pages import Cell, Page, Section, Table

SHOWN_RUNS = 3  # scenario names listed in a refusal


class FramesDiffer(ValueError):
    """The two runs did not score the same frames; the message names the difference."""


def load_results(path: Path) -> dict[str, Any]:
    """results.json of an evaluation folder, or the file itself."""
    file = path / "results.json" if path.is_dir() else path
    if not file.is_file():
        raise FileNotFoundError(
            f"{path}: no results.json; expected a `umad eval` / `umad sweep` folder or its results.json"
        )
    try:
        results = json.loads(file.read_text())
    except ValueError as exc:
        raise ValueError(f"{file}: not valid JSON ({exc})") from None
    for key in ("protocol", "headline", "rows"):
        if key not in results:
            raise ValueError(f"{file}: no {key!r}; written by an older umad, re-run `umad sweep` on its run.mcap")
    return results


def frames_difference(a: dict[str, Any], b: dict[str, Any]) -> str | None:
    """Why runs A and B did not score the same frames, or None when they did."""
    pa, pb = a["protocol"], b["protocol"]
    every_a, every_b = scored_every(pa), scored_every(pb)
    if every_a != every_b:
        return f"A scored {sampling_text(every_a)}, B {sampling_text(every_b)}"
    frames_a, frames_b = pa.get("frames_evaluated", {}), pb.get("frames_evaluated", {})
    only_a, only_b = sorted(set(frames_a) - set(frames_b)), sorted(set(frames_b) - set(frames_a))
    if only_a or only_b:
        parts = [
            f"only {name} has {len(runs)} scenario(s): {', '.join(runs[:SHOWN_RUNS])}{' ...' if len(runs) > SHOWN_RUNS else ''}"
            for name, runs in (("A", only_a), ("B", only_b))
            if runs
        ]
        return "; ".join(parts)
    for run in sorted(frames_a):
        seqs_a, seqs_b = frames_a[run], frames_b[run]
        if seqs_a != seqs_b:
            first = next((x for x, y in zip(seqs_a, seqs_b, strict=False) if x != y), None)
            where = f", first differing frame id {first}" if first is not None else ""
            return f"scenario {run}: A scored {len(seqs_a)} frames, B {len(seqs_b)}{where}"
    return None


def _delta_cells(value_a: float | None, value_b: float | None, higher: bool, text) -> list[Cell]:
    """A, B (marked better / worse than A) and B - A."""
    if value_a is None or value_b is None:
        return [Cell(text(value_a)), Cell(text(value_b)), Cell("n/a")]
    mark = "" if value_a == value_b else "better" if (value_b > value_a) == higher else "worse"
    return [Cell(text(value_a)), Cell(text(value_b), mark), Cell(_signed(value_b - value_a, text))]


def _signed(delta: float, text) -> str:
    shown = text(abs(delta))
    if shown == text(0.0):  # a difference that rounds away carries no sign
        return shown
    return f"+{shown}" if delta > 0 else f"-{shown}"


def _score_header(first: list[str]) -> list[str]:
    return first + [f"{key} {run}" for key, _ in SCORES for run in ("A", "B", "B - A")]


def headline_settings(a: dict[str, Any], b: dict[str, Any]) -> list[tuple[str, dict, dict]]:
    """(mask setting, A's headline entry, B's) for every headline setting of either run, A's order
    first; an entry is {} where that run lacks the setting."""
    settings_a = {s["masks"]: s for s in a["headline"]["settings"]}
    settings_b = {s["masks"]: s for s in b["headline"]["settings"]}
    return [
        (label, settings_a.get(label, {}), settings_b.get(label, {}))
        for label in dict.fromkeys([*settings_a, *settings_b])
    ]


def shipped_table(a: dict[str, Any], b: dict[str, Any]) -> Table | None:
    """The shipped configuration of A and B (what each graph as run produced): AP, FPR95, AUROC, the
    weakest drive's AUROC, and B - A; None where neither run has one."""
    sa, sb = a["headline"].get("shipped") or {}, b["headline"].get("shipped") or {}
    if not sa and not sb:
        return None
    cells = [
        Cell(f"{sa.get('masks', '-')} / {sb.get('masks', '-')}"),
        Cell(f"{sa.get('weights_label', '-')} / {sb.get('weights_label', '-')}"),
    ]
    for key, higher in SCORES:
        cells += _delta_cells(sa.get(key), sb.get(key), higher, percent)
    weakest_a, weakest_b = sa.get("weakest") or {}, sb.get("weakest") or {}
    cells += _delta_cells(weakest_a.get("AUROC"), weakest_b.get("AUROC"), True, percent)
    header = _score_header(["shipped masks A / B", "weights A / B"]) + [
        f"weakest drive AUROC {r}" for r in ("A", "B", "B - A")
    ]
    drives = f"A: {weakest_a.get('drive', 'n/a')}, B: {weakest_b.get('drive', 'n/a')}"
    return Table(header, [cells], f"What each graph as run produced; values in %. Weakest drive {drives}.")


def headline_table(a: dict[str, Any], b: dict[str, Any]) -> Table:
    """Best row per mask setting and MNAD: AP, FPR95, AUROC of A and B and the difference."""
    lines = []
    for _, sa, sb in headline_settings(a, b):
        rows = [
            Cell((sa or sb)["title"]),
            Cell(f"{sa.get('weights_label', '-')} / {sb.get('weights_label', '-')}"),
        ]
        for key, higher in SCORES:
            rows += _delta_cells(sa.get(key), sb.get(key), higher, percent)
        lines.append(rows)
    mnad_a, mnad_b = a["headline"]["mnad"] or {}, b["headline"]["mnad"] or {}
    if mnad_a or mnad_b:
        cells = [Cell("MNAD baseline"), Cell("-")]
        for key, higher in SCORES:
            cells += _delta_cells(mnad_a.get(key), mnad_b.get(key), higher, percent)
        lines.append(cells)
    return Table(
        _score_header(["mask setting", "best weights A / B"]),
        lines,
        "Best AP row per mask setting in each run, chosen on the test data; values in %. Bold: B better than A, "
        "italic: B worse.",
    )


def lowest_fpr_table(a: dict[str, Any], b: dict[str, Any]) -> Table:
    """Each headline mask setting's lowest FPR95 over all its rows in A and B, which row reached it,
    and B - A."""
    lines = []
    for label, sa, sb in headline_settings(a, b):
        low_a, low_b = lowest_fpr(a["rows"], label) or {}, lowest_fpr(b["rows"], label) or {}
        lines.append(
            [
                Cell((sa or sb)["title"]),
                Cell(f"{low_a.get('weights_label', '-')} / {low_b.get('weights_label', '-')}"),
                *_delta_cells(low_a.get("FPR95"), low_b.get("FPR95"), False, percent),
            ]
        )
    return Table(
        ["mask setting", "its row A / B", "lowest FPR95 A", "B", "B - A"],
        lines,
        "The lowest FPR95 over every weight row of each mask setting; values in %.",
    )


def ratio_table(a: dict[str, Any], b: dict[str, Any]) -> Table:
    ratios_a, ratios_b = a["headline"]["ratios"], b["headline"]["ratios"]
    lines = [
        [Cell(name), *_delta_cells(ratios_a.get(name), ratios_b.get(name), True, ratio_text)]
        for name in dict.fromkeys([*ratios_a, *ratios_b])
    ]
    return Table(["ratio", "A", "B", "B - A"], lines)


def ablation_table(a: dict[str, Any], b: dict[str, Any]) -> Table:
    """Every configuration of either run, matched by weight row and mask setting."""
    rows_a = {(r["weights_label"], r["masks"]): r for r in a["rows"]}
    rows_b = {(r["weights_label"], r["masks"]): r for r in b["rows"]}
    lines = []
    for key in dict.fromkeys([*rows_a, *rows_b]):
        ra, rb = rows_a.get(key, {}), rows_b.get(key, {})
        cells = [Cell(key[0]), Cell(key[1])]
        for score, higher in SCORES:
            cells += _delta_cells(ra.get(score), rb.get(score), higher, percent)
        lines.append(cells)
    return Table(_score_header(["weights", "masks"]), lines, "Values in %. Bold: B better than A, italic: B worse.")


def model_lines(a: dict[str, Any], b: dict[str, Any]) -> list[str]:
    """Where the two runs' data folders and models differ (file or training data)."""
    lines = []
    if a["protocol"].get("data") != b["protocol"].get("data"):
        lines.append(
            f"Data folders differ (same scenarios and frame ids): A {a['protocol'].get('data')}, "
            f"B {b['protocol'].get('data')}."
        )
    models_a, models_b = a["protocol"].get("models", {}), b["protocol"].get("models", {})
    for key in dict.fromkeys([*models_a, *models_b]):
        record_a, record_b = models_a.get(key), models_b.get(key)
        if record_a == record_b:
            continue
        text_a, text_b = (describe_model(r) if r else "none" for r in (record_a, record_b))
        if text_a == text_b:  # same name and training record: the files differ
            text_a, text_b = record_a.get("file"), record_b.get("file")
        lines.append(f"{key}: A {text_a}; B {text_b}.")
    return lines or ["Same data folder and models (files and training records)."]


def compare_page(a: dict[str, Any], b: dict[str, Any], name_a: str, name_b: str) -> Page:
    """The comparison page; raises FramesDiffer when the runs did not score the same frames."""
    difference = frames_difference(a, b)
    if difference:
        raise FramesDiffer(f"{name_a} and {name_b} did not score the same frames: {difference}")
    protocol = a["protocol"]
    headline = (
        f"A = {name_a}, B = {name_b}: the same {protocol.get('frames', 0)} frames of {protocol.get('drives', 0)} drives "
        f"({sampling_text(scored_every(protocol))})."
    )
    sections = [
        Section(
            "Headline",
            tables=[
                *filter(None, [shipped_table(a, b)]),
                headline_table(a, b),
                lowest_fpr_table(a, b),
                ratio_table(a, b),
            ],
        ),
        Section(
            "What differs",
            model_lines(a, b) + [f"A: {protocol_line(a['protocol'])}", f"B: {protocol_line(b['protocol'])}"],
        ),
        Section("Every ablation row", tables=[ablation_table(a, b)]),
    ]
    return Page("UMAD runs compared", headline, sections)

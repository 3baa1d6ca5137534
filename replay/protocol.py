"""What a recorded run used, read back from the run itself: the graph the launcher stored in the
log's metadata (with its `--set` overrides and base folder), each operator's parameters completed
with its schema's defaults, and the JSON record beside every model file.

Nothing here is assumed: a model whose JSON is missing is reported as such, and the network behind
the perceptual difference is the one its operator was configured with (ImageNet VGG16 from a file,
or the label-free feature net and the data it was trained on).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import yaml

from umad_common import recorded_path, resolve_path
from umad_common.dataflow.api.assignments import merge_params, parse_assignment
from umad_common.dataflow.api.operator import load_operator_class
from umad_common.datasets.anovox import scenario_weathers

LABEL_RESIZE = "nearest"  # labels are resized to the score maps' size, never the maps to the labels


def model_record(weights: Path) -> dict[str, Any]:
    """A model file and what its JSON record (`<name>.json` beside it) says about its training:
    the data folder, how many drives and frames, epochs, seconds, and the network widths."""
    record: dict[str, Any] = {"file": recorded_path(weights)}
    info_path = weights.with_suffix(".json")
    try:
        info = json.loads(info_path.read_text())
    except (OSError, ValueError):
        record["trained_on"] = f"unknown ({info_path.name} not found or unreadable)"
        return record
    merged = {**info, **info.get("training", {})}
    config = info.get("config", {})
    record["trained_on"] = merged.get("data", "unknown (not in its JSON)")
    if "training_drives" in merged:
        record["drives"] = len(merged["training_drives"])
    for key, names in (
        ("frames", ("training_frames", "frames")),
        ("epochs", ("epochs",)),
        ("seconds", ("train_seconds", "seconds")),
        ("widths", ("widths", "image_channels")),
    ):
        value = next((source[n] for source in (merged, config) for n in names if n in source), None)
        if value is not None:
            record[key] = value
    return record


def operator_params(graph: dict[str, Any], sets: dict[str, dict[str, Any]]) -> dict[str, tuple[str, dict[str, Any]]]:
    """op id -> (kind, parameters with `--set` overrides and the schema's defaults filled in)."""
    out = {}
    for op in graph.get("operators", []):
        params = dict(op.get("params") or {})
        merge_params(params, sets.get(op["id"], {}))
        kind = op.get("kind") or op.get("uses") or ""
        try:
            params = load_operator_class(op.get("kind"), op.get("uses")).validate_params(params).model_dump()
        except Exception:  # a custom operator not importable here: its parameters as written
            pass
        out[op["id"]] = (kind, params)
    return out


def graph_operators(metadata: dict[str, str]) -> dict[str, tuple[str, dict[str, Any]]]:
    """The logged graph's operators: op id -> (kind, parameters with the launcher's `--set` overrides
    and the schema's defaults); {} where the log holds no graph."""
    graph = yaml.safe_load(metadata.get("graph") or "") or {}
    sets_by_op: dict[str, dict[str, Any]] = {}
    for assignment in json.loads(metadata.get("sets") or "[]"):  # the launcher's `--set OP.PARAM=VALUE` list
        op, param, value = parse_assignment(assignment)
        sets_by_op.setdefault(op, {})[param] = value
    return operator_params(graph, sets_by_op)


def shipped_configuration(metadata: dict[str, str]) -> dict[str, Any] | None:
    """What the graph as run produced, as the sweep names configurations: the fusion weights (metric ->
    weight > 0, as the fusion operator had them), its `above_lidar_weight` and `lidar_camera_exponent`, the
    label-free segmenter op and the refinement mode.

    The shipped configuration is the first mask refiner in the graph whose masks are not the ground
    truth's (in the default graph `refine_unsup`: `geometry` masks, `mean_pixel`); a graph without one
    ships its fusion's map ("none": no mask). None where the log holds no graph or no fusion.
    """
    ops = graph_operators(metadata)
    graph = yaml.safe_load(metadata.get("graph") or "") or {}
    inputs = {op["id"]: op.get("inputs") or {} for op in graph.get("operators", [])}

    def source_op(op_id: str, port: str) -> str | None:
        wired = inputs.get(op_id, {}).get(port)
        return wired.split("/")[0] if isinstance(wired, str) else None

    fusions = [op_id for op_id, (kind, _) in ops.items() if kind == "fusion"]
    for op_id, (kind, params) in ops.items():
        segmenter = source_op(op_id, "masks")
        if kind != "mask_refiner" or segmenter not in ops or ops[segmenter][1].get("method") == "gt":
            continue
        fusion = source_op(op_id, "fused")
        if fusion in fusions:
            return {
                "refiner": op_id,
                "fusion": fusion,
                "weights": {m: w for m, w in ops[fusion][1]["weights"].items() if w > 0},
                "above_lidar_weight": float(ops[fusion][1].get("above_lidar_weight", 1.0)),
                "lidar_camera_exponent": float(ops[fusion][1].get("lidar_camera_exponent", 0.0)),
                "segmenter": segmenter,
                "method": ops[segmenter][1].get("method"),
                "mode": params["mode"],
            }
    if not fusions:
        return None
    weights = {m: w for m, w in ops[fusions[0]][1]["weights"].items() if w > 0}
    return {
        "refiner": None,
        "fusion": fusions[0],
        "weights": weights,
        "above_lidar_weight": float(ops[fusions[0]][1].get("above_lidar_weight", 1.0)),
        "lidar_camera_exponent": float(ops[fusions[0]][1].get("lidar_camera_exponent", 0.0)),
        "segmenter": None,
        "method": None,
        "mode": "none",
    }


def run_protocol(metadata: dict[str, str], map_notes: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """The run's data, frame sampling, models and perceptual network from the log's `umad` metadata,
    and each drive's weather where the data folder's scenario config names it (read from the data
    folder now, so older logs get it too while their data is at hand).

    Args:
        metadata: the log's metadata record (`graph` YAML text, `base_dir`, `sets` as a JSON list of
            `OP.PARAM=VALUE`, `version`).
        map_notes: metric -> the notes its difference maps carried (`normalization`, `extractor`).

    Returns:
        A JSON-ready dict; empty values where the log holds no graph (a log not written by the launcher).
    """
    base = Path(metadata.get("base_dir") or ".")

    def resolve(path: str) -> Path:
        return resolve_path(path, base)

    protocol: dict[str, Any] = {"version": metadata.get("version"), "models": {}, "label_resize": LABEL_RESIZE}
    for op_id, (kind, params) in graph_operators(metadata).items():
        if kind == "segmenter":
            protocol.setdefault("segmenters", {})[op_id] = segmenter_record(params, resolve)
        elif kind == "replayer":
            protocol["data"] = recorded_path(resolve(params["source"]))
            protocol["scenario_weather"] = scenario_weathers(resolve(params["source"]))  # {} for data without it
            protocol["every"] = params.get("every", 1) * params.get("score_every", 1)  # frames per scored frame
            protocol["world_model_every"] = params.get("every", 1)  # frames per frame the world model sees
            protocol["score_every"] = params.get("score_every", 1)  # published frames per frame marked scored
        elif kind == "world_model":
            protocol["models"]["world_model"] = model_record(resolve(params["model"]))
        elif kind == "mnad":
            protocol["models"]["mnad"] = model_record(resolve(params["weights"]))
        elif kind == "difference" and params.get("metric") in ("perceptual", "pd"):
            protocol["models"]["perceptual"] = perceptual_network(params, resolve)
        if kind == "difference":
            protocol.setdefault("normalization", {})[params.get("metric")] = params.get("normalization")
    shipped = shipped_configuration(metadata)
    if shipped is not None:
        protocol["shipped"] = shipped
    extractor = map_notes.get("perceptual", {}).get("extractor")
    if extractor and "perceptual" in protocol["models"]:
        protocol["models"]["perceptual"]["extractor_in_maps"] = extractor
    return protocol


def perceptual_network(params: dict[str, Any], resolve) -> dict[str, Any]:
    """The network behind Δ_PD as configured: ImageNet VGG16 when `vgg_weights` is set, else the feature net."""
    if params.get("vgg_weights"):
        return {
            "network": "ImageNet VGG16",
            "file": recorded_path(resolve(params["vgg_weights"])),
            "trained_on": "ImageNet",
        }
    return {"network": "label-free feature net", **model_record(resolve(params["features"]))}


def segmenter_record(params: dict[str, Any], resolve) -> dict[str, Any]:
    """A segmenter's method and, where the method loads one, its model file and training record."""
    method = params.get("method")
    options = params.get("options") or {}
    if method == "sam":
        return {
            "method": method,
            "network": f"SAM {options.get('model', 'vit_b')}",
            "file": recorded_path(resolve(options["checkpoint"])),
        }
    if method == "kmeans" and options.get("features") == "feature_net":
        return {
            "method": method,
            "network": "label-free feature net",
            **model_record(resolve(options["feature_net"])),
        }
    return {"method": method}

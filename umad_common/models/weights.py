"""Weight files of every model: NAME.safetensors with NAME.json beside it (the config and the
training record), and the one error every loader raises for a file that cannot be used.

Every loader returns `(model, record)`: the model in eval mode and the JSON record (`{}` for a file
in its upstream format, such as a torchvision VGG16 state dict, which has no record beside it). A
loader's `device` (default the CPU) is where the tensors are read to and the model is put; weights
are always saved from the CPU, so a file written on a GPU machine loads anywhere."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import fields
from pathlib import Path
from typing import TypeVar

import torch
from safetensors.torch import load_file, save_file
from torch import nn

M = TypeVar("M", bound=nn.Module)
C = TypeVar("C")


class WeightsError(ValueError):
    """A weight file is missing, unreadable or does not fit the model: names the file, the tensor or
    key, and the shape expected against the shape found."""


def weight_paths(path: str | Path) -> tuple[Path, Path]:
    """`dir/name`, `dir/name.safetensors` or `dir/name.json` -> (dir/name.safetensors, dir/name.json)."""
    path = Path(path)
    stem = path.with_suffix("") if path.suffix in (".safetensors", ".json") else path
    return stem.with_name(stem.name + ".safetensors"), stem.with_name(stem.name + ".json")


def config_from_dict(cls: type[C], data: dict, what: str) -> C:
    """A model's config dataclass from its record's dict; a key it does not know is a ValueError
    naming it."""
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValueError(f"{what} config has unknown fields {unknown}; expected a subset of {sorted(known)}")
    return cls(**data)


def save_weights(model: nn.Module, path: str | Path, config: dict, record: dict | None = None) -> Path:
    """Write the model's tensors (safetensors) and a JSON beside them: `config` and `record`."""
    weights, meta = weight_paths(path)
    weights.parent.mkdir(parents=True, exist_ok=True)
    save_file({k: v.detach().contiguous().cpu() for k, v in model.state_dict().items()}, str(weights))
    meta.write_text(json.dumps({"config": config, **(record or {})}, indent=2) + "\n")
    return weights


def read_record(path: str | Path, what: str) -> dict:
    """The JSON record beside a weight file, checked to hold a 'config' object.

    Raises:
        WeightsError: either file is missing, or the JSON is not a record with a config.
    """
    weights, meta = weight_paths(path)
    for file in (weights, meta):
        if not file.is_file():
            raise WeightsError(f"{file}: {what} file not found; expected {weights.name} with {meta.name} beside it")
    try:
        record = json.loads(meta.read_text())
    except ValueError as exc:
        raise WeightsError(f"{meta}: not JSON ({exc}); expected the {what} config and training record") from None
    if not isinstance(record, dict) or not isinstance(record.get("config"), dict):
        raise WeightsError(f"{meta}: no 'config' object; expected the {what} config and training record")
    return record


def load_model(
    path: str | Path, what: str, build: Callable[[dict, str], M], device: str | torch.device = "cpu"
) -> tuple[M, dict]:
    """A model from NAME.safetensors + NAME.json on `device`, in eval mode without gradients, and its
    record. `build(config, source)` makes the model from the record's config; a config it cannot take
    (ValueError, KeyError or TypeError) becomes a WeightsError naming the JSON file."""
    record = read_record(path, what)
    source = str(weight_paths(path)[1])
    try:
        model = build(record["config"], source)
    except WeightsError:
        raise
    except (ValueError, KeyError, TypeError) as exc:
        raise WeightsError(f"{source}: not a {what} config ({exc})") from None
    return load_tensors(model, path, device).eval().requires_grad_(False), record


def load_tensors(model: nn.Module, path: str | Path, device: str | torch.device = "cpu") -> nn.Module:
    """Fill `model` from the safetensors file, read straight to `device`, checking every tensor's name
    and shape first; the model is moved to `device`."""
    weights, meta = weight_paths(path)
    device = torch.device(device)
    try:
        tensors = load_file(str(weights), device=str(device))
    except Exception as exc:  # safetensors raises its own error types for corrupt files
        raise WeightsError(f"{weights}: cannot read safetensors file ({exc})") from None
    expected = model.state_dict()
    missing, unexpected = sorted(set(expected) - set(tensors)), sorted(set(tensors) - set(expected))
    if missing or unexpected:
        raise WeightsError(
            f"{weights}: tensors missing {missing[:5]}, unexpected {unexpected[:5]} for config {meta.name}"
        )
    for name, tensor in expected.items():
        if tuple(tensors[name].shape) != tuple(tensor.shape):
            raise WeightsError(
                f"{weights}: tensor {name!r} has shape {tuple(tensors[name].shape)}; "
                f"expected {tuple(tensor.shape)} for config {meta.name}"
            )
    model.to(device).load_state_dict(tensors)
    return model


def load_upstream_tensors(model: nn.Module, path: str | Path, device: str | torch.device = "cpu") -> nn.Module:
    """Fill `model` from a file in its upstream format: a `.safetensors` file or a `torch.save`d
    state dict (loaded with weights_only=True, never pickle); keys and shapes checked, other keys
    (a classifier the model does not have) ignored. The model ends on `device`."""
    path = Path(path)
    if not path.is_file():
        raise WeightsError(f"{path}: weight file not found")
    try:
        if path.suffix == ".safetensors":
            state = load_file(str(path))
        else:
            state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise WeightsError(f"{path}: cannot read weights ({type(exc).__name__}: {exc})") from None
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise WeightsError(f"{path}: expected a state dict of tensors, got {type(state).__name__}")
    expected = model.state_dict()
    for key, want in expected.items():
        if key not in state:
            raise WeightsError(f"{path}: missing key {key!r} (expected shape {tuple(want.shape)})")
        got = state[key]
        if not isinstance(got, torch.Tensor) or tuple(got.shape) != tuple(want.shape):
            got_shape = tuple(got.shape) if isinstance(got, torch.Tensor) else type(got).__name__
            raise WeightsError(f"{path}: layer {key!r} expected shape {tuple(want.shape)}, got {got_shape}")
    model.to(device).load_state_dict({key: state[key].float() for key in expected}, strict=True)
    return model

"""Where a model runs: the one place a device name ("auto", "cpu", "cuda", "cuda:N") becomes a
torch device, for every `umad train` verb (`--device`) and every torch operator (`device`).

"auto" is CUDA when torch sees a GPU, else the CPU. Models load, run and train there; what they hand
back (numpy arrays, saved weights) is always on the CPU. Torch is imported when a name is resolved,
not here, so a graph's parameters can be checked without it.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

from pydantic import AfterValidator, Field

if TYPE_CHECKING:
    import torch

DEVICE_PATTERN = re.compile(r"auto|cpu|cuda(:\d+)?")
DEVICE_HELP = "auto (CUDA when present, else the CPU), cpu, cuda or cuda:N"


def check_device_name(name: str) -> str:
    """`name` unchanged when it is a device name; a ValueError naming it and the names expected otherwise."""
    if not isinstance(name, str) or not DEVICE_PATTERN.fullmatch(name):
        raise ValueError(f"device {name!r}: expected {DEVICE_HELP}")
    return name


def device_field(default: str = "auto") -> Any:
    """The `device` parameter of a torch operator or segmenter method."""
    return Field(default, description=f"torch device of the network: {DEVICE_HELP}; results come back to the CPU")


DeviceName = Annotated[str, AfterValidator(check_device_name)]


def resolve_device(name: str) -> torch.device:
    """ "auto" -> cuda when torch sees a GPU, else cpu; "cpu", "cuda" and "cuda:N" as named.

    Raises:
        ValueError: `name` is not a device name, or it asks for CUDA (or a GPU index) this machine
            does not have; the message says what is available.
    """
    import torch

    check_device_name(name)
    available = torch.cuda.is_available()
    if name == "auto":
        return torch.device("cuda" if available else "cpu")
    device = torch.device(name)
    if device.type == "cuda":
        count = torch.cuda.device_count() if available else 0
        if count == 0:
            raise ValueError(
                f"device {name!r}: torch {torch.__version__} sees no CUDA device here (a CPU build or no GPU); "
                "expected 'cpu' or 'auto'"
            )
        if device.index is not None and device.index >= count:
            raise ValueError(f"device {name!r}: this machine has {count} CUDA device(s), cuda:0..cuda:{count - 1}")
    return device


def bf16_supported(device: torch.device) -> bool:
    """Whether bfloat16 autocast is fast and exact enough to train and run in on `device`: a GPU with
    bfloat16 (Ampere and later), or a CPU with bfloat16 instructions (AVX-512 BF16 or AMX on x86, BF16
    on Arm). oneDNN also runs bfloat16 on a plain AVX-512 CPU, by conversion: 3.4x the world model's
    CPU of float32 there (docs/experiments.md), so that CPU counts as without."""
    import torch

    if device.type == "cuda":
        return torch.cuda.is_bf16_supported()
    native = cpu_has_bf16_instructions()
    return torch.ops.mkldnn._is_mkldnn_bf16_supported() and native is not False


def cpu_has_bf16_instructions(cpuinfo: Path = Path("/proc/cpuinfo")) -> bool | None:
    """Whether the CPU's flags (Linux's `cpuinfo`: x86 `flags`, Arm `Features`) name bfloat16
    instructions: `avx512_bf16`, `amx_bf16` or `bf16`; None where the file or its flags are missing."""
    try:
        text = cpuinfo.read_text()
    except OSError:
        return None
    flags: set[str] = set()
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key.strip() in ("flags", "Features"):
            flags.update(value.split())
    return bool(flags & {"avx512_bf16", "amx_bf16", "bf16"}) if flags else None

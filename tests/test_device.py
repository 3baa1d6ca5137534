"""Where the networks run: device names, `--device` on every training verb, the `device` parameter of
every torch operator. Without a GPU the CPU path must give today's results bit for bit; the tests
marked `cuda` run the world model, the perceptual net and MNAD forward and a world-model training
epoch on the GPU, compared with the CPU within a tolerance, and are skipped without one."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from tests.test_world_model import TINY, sensor_frame, tiny_model, write_drive
from umad_common import ASSETS
from umad_common.commands import train_features, train_mnad, train_segmenter, train_world_model
from umad_common.commands.common import resolve_device_or_exit
from umad_common.dataflow import Context, Frame
from umad_common.dataflow.api.messages import Message
from umad_common.differences import MetricOptions, build_metric
from umad_common.models.device import resolve_device
from umad_common.models.mnad import Mnad, MnadConfig, load_mnad, save_mnad, to_input
from umad_common.models.world_model import WorldModelConfig, load_world_model, save_world_model
from umad_operators.mnad import MnadParams, MnadPredictor
from umad_operators.world_model import WorldModelParams, WorldModelPredictor

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
TRAIN_VERBS = (train_world_model, train_features, train_mnad, train_segmenter)


@pytest.fixture
def no_cuda(monkeypatch):
    """This machine as one without a GPU, whatever it has."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


@pytest.fixture
def world_model_file(tmp_path):
    save_world_model(tiny_model(seed=2, ground_flow=True), tmp_path / "wm")
    return tmp_path / "wm.safetensors"


def world_model_outputs(op: WorldModelPredictor, frames: int = 5) -> list[dict[str, np.ndarray]]:
    return [op.process(sensor_frame("run_a", seq, np.random.default_rng(seq)))["frame"].arrays for seq in range(frames)]


def camera_frame(rgb: np.ndarray) -> Frame:
    return Frame("r", 0, 0, inputs={"camera": Message("r", 0, arrays={"rgb": rgb})})


def test_device_names_resolve_and_cuda_without_a_gpu_is_refused_with_what_is_available(no_cuda):
    assert resolve_device("auto") == torch.device("cpu")
    assert resolve_device("cpu") == torch.device("cpu")
    for asked in ("cuda", "cuda:1"):
        with pytest.raises(ValueError, match=rf"device '{asked}': .*no CUDA device.*expected 'cpu' or 'auto'"):
            resolve_device(asked)
    with pytest.raises(ValueError, match=r"device 'gpu': expected auto .*cpu, cuda or cuda:N"):
        resolve_device("gpu")


def test_every_torch_operator_validates_its_device_parameter():
    from umad_common.segmentation.learned import Learned

    for params in (WorldModelParams, MnadParams, Learned.Params):
        assert params().device == "auto"
        assert params(device="cuda:0").device == "cuda:0"
        with pytest.raises(ValidationError, match="expected auto"):
            params(device="gpu")


@pytest.mark.parametrize("verb", TRAIN_VERBS, ids=lambda verb: verb.__name__.rsplit(".", 1)[-1])
def test_every_train_verb_takes_device_and_refuses_cuda_without_a_gpu(verb, no_cuda, capsys):
    parser = argparse.ArgumentParser()
    verb.add_arguments(parser)
    assert parser.parse_args(["data", "--out", "m.safetensors"]).device == "auto"
    assert parser.parse_args(["data", "--out", "m.safetensors", "--device", "cpu"]).device == "cpu"
    with pytest.raises(SystemExit):
        parser.parse_args(["data", "--out", "m.safetensors", "--device", "tpu"])
    assert "device 'tpu': expected auto" in capsys.readouterr().err
    with pytest.raises(SystemExit, match="--device: device 'cuda': .*no CUDA device"):
        resolve_device_or_exit("cuda")


def test_a_recorded_training_command_names_the_device_only_when_it_was_not_auto():
    for verb in (train_world_model, train_segmenter):
        parser = argparse.ArgumentParser()
        verb.add_arguments(parser)
        assert "--device" not in verb.command_line(parser.parse_args(["data", "--out", "m.safetensors"]))
        asked = parser.parse_args(["data", "--out", "m.safetensors", "--device", "cpu"])
        assert "--device cpu" in verb.command_line(asked)


def test_world_model_operator_on_cpu_gives_the_default_path_bit_for_bit(world_model_file, no_cuda):
    on_cpu = world_model_outputs(WorldModelPredictor({"model": str(world_model_file), "device": "cpu"}))
    default = world_model_outputs(WorldModelPredictor({"model": str(world_model_file)}))
    for a, b in zip(on_cpu, default, strict=True):
        for name in a:
            assert np.array_equal(a[name], b[name]), name
    loaded, _ = load_world_model(world_model_file, "cpu")
    for name, tensor in load_world_model(world_model_file)[0].state_dict().items():
        assert torch.equal(tensor, loaded.state_dict()[name]), name


def test_world_model_device_cannot_change_at_runtime(world_model_file, no_cuda):
    op = WorldModelPredictor({"model": str(world_model_file), "device": "cpu"})
    with pytest.raises(ValueError, match="`device` cannot change at runtime"):
        op.update_params(op.params.model_copy(update={"device": "auto"}))


def test_mnad_operator_on_cpu_is_the_model_run_directly_bit_for_bit(tmp_path, no_cuda):
    cfg = MnadConfig(height=32, width=48, widths=(4, 8, 8), feature_dim=16, memory_items=4)
    torch.manual_seed(0)
    save_mnad(Mnad(cfg).eval(), tmp_path / "w.safetensors")
    rgb = np.random.default_rng(0).integers(0, 255, (64, 96, 3), dtype=np.uint8)
    op = MnadPredictor({"weights": "w.safetensors", "device": "cpu"}, Context(base_dir=tmp_path))
    got = op.process(camera_frame(rgb))["map"].arrays["map"]
    model, _ = load_mnad(tmp_path / "w.safetensors")
    assert np.array_equal(got, model.anomaly_map(to_input(rgb, cfg))[0].numpy())


# ---------------------------------------------------------------------------------------------
# On the GPU (skipped without one): the same results as the CPU within a tolerance (TF32 convolutions
# and bfloat16 training differ in the last digits)


@needs_cuda
@pytest.mark.cuda
def test_world_model_forward_on_the_gpu_matches_the_cpu(world_model_file):
    gpu_op = WorldModelPredictor({"model": str(world_model_file), "device": "cuda"})
    assert next(gpu_op.model.parameters()).is_cuda
    gpu = world_model_outputs(gpu_op)
    cpu = world_model_outputs(WorldModelPredictor({"model": str(world_model_file), "device": "cpu"}))
    for a, b in zip(gpu, cpu, strict=True):
        assert np.array_equal(a["pred_valid"], b["pred_valid"]) and np.array_equal(a["target"], b["target"])
        for name in ("recon", "preds"):
            assert a[name].dtype == np.float32 and np.allclose(a[name], b[name], atol=5e-3), name


@needs_cuda
@pytest.mark.cuda
def test_perceptual_and_mnad_forward_on_the_gpu_match_the_cpu():
    rng = np.random.default_rng(0)
    target = rng.random((128, 192, 3), dtype=np.float32)
    recon = np.clip(target + rng.normal(0, 0.05, target.shape), 0, 1).astype(np.float32)
    preds, valid = np.zeros((1, 128, 192, 3), np.float32), np.zeros(1, np.uint8)
    maps = {}
    for device in ("cpu", "cuda"):
        metric = build_metric("perceptual", MetricOptions(features=ASSETS / "feature_net.safetensors", device=device))
        assert metric.device.type == device
        maps[device] = metric(target, recon, preds, valid)
    assert np.allclose(maps["cuda"], maps["cpu"], rtol=1e-2, atol=1e-2 * float(maps["cpu"].max()))

    rgb = rng.integers(0, 255, (512, 768, 3), dtype=np.uint8)
    mnad = {
        device: MnadPredictor({"device": device}).process(camera_frame(rgb))["map"].arrays["map"]
        for device in ("cpu", "cuda")
    }
    assert np.allclose(mnad["cuda"], mnad["cpu"], rtol=1e-2, atol=1e-2 * float(mnad["cpu"].max()))


@needs_cuda
@pytest.mark.cuda
def test_world_model_trains_on_the_gpu_like_on_the_cpu(tmp_path):
    from umad_common.training.train_world_model import train_world_model
    from umad_common.training.world_model_step import TrainConfig

    for i in range(3):
        write_drive(tmp_path / "bench" / "normal" / f"Scenario_n{i}", frames=12, seed=i)
    records = {
        device: train_world_model(
            tmp_path / "bench",
            tmp_path / device,
            epochs=1,
            seed=3,
            threads=1,
            model_config=WorldModelConfig(**TINY),
            train_config=TrainConfig(sequence_length=4, batch_size=2, holdout=1),
            device=device,
        )
        for device in ("cpu", "cuda")
    }
    assert records["cuda"]["device"] == "cuda" and records["cpu"]["device"] == "cpu"
    gpu_loss, cpu_loss = records["cuda"]["history"][0]["loss"], records["cpu"]["history"][0]["loss"]
    assert np.isfinite(gpu_loss) and abs(gpu_loss - cpu_loss) <= 0.05 * abs(cpu_loss), (gpu_loss, cpu_loss)
    trained_on_gpu, _ = load_world_model(tmp_path / "cuda")  # saved from the GPU, loads on the CPU
    assert all(tensor.device.type == "cpu" for tensor in trained_on_gpu.state_dict().values())


def test_a_cpu_counts_as_bfloat16_only_with_bfloat16_instructions(tmp_path):
    """oneDNN runs bfloat16 on any AVX-512 CPU, by conversion, at several times float32's cost: only the
    instructions themselves (AVX-512 BF16, AMX, Arm BF16) make a CPU count; unknown flags leave oneDNN's word."""
    from umad_common.models.device import cpu_has_bf16_instructions

    cpuinfo = tmp_path / "cpuinfo"
    cases = {
        "flags\t\t: fpu sse avx2 avx512f avx512bw avx512vl avx512_vnni\n": False,
        "flags\t\t: fpu avx512f avx512_bf16 avx512_vnni\n": True,
        "flags\t\t: fpu amx_tile amx_bf16\n": True,
        "Features\t: fp asimd bf16 i8mm\n": True,
        "processor\t: 0\n": None,
    }
    for text, expected in cases.items():
        cpuinfo.write_text("processor\t: 0\n" + text + "processor\t: 1\n" + text)
        assert cpu_has_bf16_instructions(cpuinfo) is expected
    assert cpu_has_bf16_instructions(tmp_path / "missing") is None

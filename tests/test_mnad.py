"""MNAD baseline: shapes, losses, memory update, save/load round trip, a tiny deterministic training, the operator."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from umad_common.dataflow import Context, Frame
from umad_common.dataflow.api.messages import Message
from umad_common.models.mnad import Mnad, MnadConfig, load_mnad, save_mnad, to_input
from umad_common.models.weights import WeightsError
from umad_common.training.train_mnad import MnadTrainingConfig, train_mnad
from umad_operators.mnad import MnadPredictor

torch.set_num_threads(1)
TINY = MnadConfig(height=32, width=48, widths=(4, 8, 8), feature_dim=16, memory_items=4)


def test_shapes_and_losses():
    torch.manual_seed(0)
    model = Mnad(TINY)
    x = torch.rand(2, 3, 32, 48) * 2 - 1
    out = model(x)
    assert out.recon.shape == x.shape and out.recon.abs().max() <= 1
    assert out.query.shape == (2 * 4 * 6, 16)
    torch.testing.assert_close(out.query.norm(dim=1), torch.ones(48))
    assert out.compactness.ndim == 0 and out.separateness.ndim == 0
    loss, parts = model.loss(x, out)
    expected = parts["reconstruction"] + 0.1 * parts["compactness"] + 0.1 * parts["separateness"]
    assert float(loss.detach()) == pytest.approx(expected, rel=1e-5)
    assert model.anomaly_map(x).shape == (2, 32, 48)


def test_compactness_is_distance_to_nearest_item():
    model = Mnad(TINY)
    with torch.no_grad():
        out = model(torch.zeros(2, 3, 32, 48))
    nearest = model.memory[(out.query @ model.memory.t()).argmax(dim=1)]
    assert float(out.compactness) == pytest.approx(float(((out.query - nearest) ** 2).mean()), rel=1e-5)


def test_memory_update_moves_items_towards_their_queries_and_stays_normalised():
    model = Mnad(TINY)
    item = model.memory[0].clone()
    query = torch.nn.functional.normalize(item + 0.1 * torch.randn(5, 16), dim=1)
    before = float(model.memory[0] @ query.mean(0))
    model.update_memory(query)
    torch.testing.assert_close(model.memory.norm(dim=1), torch.ones(4))
    assert float(model.memory[0] @ query.mean(0)) >= before


def test_wrong_input_size_is_refused():
    with pytest.raises(ValueError, match="expects input"):
        Mnad(TINY)(torch.zeros(1, 3, 30, 48))
    with pytest.raises(ValueError, match="divisible by 8"):
        MnadConfig(height=30)
    with pytest.raises(ValueError, match="uint8"):
        to_input(np.zeros((32, 48, 3), np.float32), TINY)


def tiny_frames(n=6, seed=0):
    rng = np.random.default_rng(seed)
    frames = np.zeros((n, 32, 48, 3), np.uint8)
    frames[:, 16:, :, :] = 90  # "road"
    frames[:, :16, :, 2] = 200  # "sky"
    return np.clip(frames + rng.integers(0, 20, frames.shape), 0, 255).astype(np.uint8)


def test_tiny_training_is_deterministic_and_learns(tmp_path):
    cfg = MnadTrainingConfig(epochs=3, seed=3, batch_size=3, lr=1e-2)
    model_a, record = train_mnad(tiny_frames(), cfg, TINY, progress=False)
    model_b, _ = train_mnad(tiny_frames(), cfg, TINY, progress=False)
    for (name, a), b in zip(model_a.state_dict().items(), model_b.state_dict().values(), strict=True):
        assert torch.equal(a, b), name
    losses = [e["reconstruction"] for e in record["training"]["losses_per_epoch"]]
    assert losses[-1] < losses[0]
    path = save_mnad(model_a, tmp_path / "mnad.safetensors", record)
    loaded, loaded_record = load_mnad(path)
    assert loaded_record["training"]["steps"] == 6
    x = to_input(tiny_frames(1)[0], TINY)
    torch.testing.assert_close(loaded.anomaly_map(x), model_a.anomaly_map(x))


def test_time_budget_sets_the_epochs_and_the_record_reproduces_them():
    budget = MnadTrainingConfig(seed=3, batch_size=3, minutes=0.02)  # 1.2 s: a few epochs of 2 tiny steps
    model_a, record = train_mnad(tiny_frames(), budget, TINY, progress=False)
    epochs = record["training"]["epochs"]
    history = record["training"]["losses_per_epoch"]
    assert epochs >= 1 and [e["epoch"] for e in history] == list(range(1, epochs + 1))
    seconds = [e["seconds"] for e in history]  # wall time since the start, after each epoch
    assert seconds == sorted(seconds) and record["training"]["minutes"] == 0.02
    again, _ = train_mnad(tiny_frames(), MnadTrainingConfig(epochs=epochs, seed=3, batch_size=3), TINY, progress=False)
    for (name, a), b in zip(model_a.state_dict().items(), again.state_dict().values(), strict=True):
        assert torch.equal(a, b), name


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(WeightsError, match="not found"):
        load_mnad(tmp_path / "missing.safetensors")
    save_mnad(Mnad(TINY), tmp_path / "m.safetensors")
    (tmp_path / "m.json").write_text(
        '{"config": {"height": 32, "width": 48, "widths": [4, 8, 16], "feature_dim": 16, "memory_items": 4}}'
    )
    with pytest.raises(WeightsError, match="shape"):
        load_mnad(tmp_path / "m.safetensors")


def test_operator_outputs_map_at_model_size(tmp_path):
    save_mnad(Mnad(TINY).eval(), tmp_path / "w.safetensors")
    op = MnadPredictor({"weights": "w.safetensors"}, Context(base_dir=tmp_path))
    rgb = np.random.default_rng(0).integers(0, 255, (64, 96, 3), dtype=np.uint8)
    out = op.process(Frame("r", 0, 0, inputs={"camera": Message("r", 0, arrays={"rgb": rgb})}))
    score_map = out["map"].arrays["map"]
    assert score_map.shape == (32, 48) and score_map.dtype == np.float32 and np.all(score_map >= 0)
    with pytest.raises(WeightsError):
        MnadPredictor({"weights": "nope.safetensors"}, Context(base_dir=tmp_path))


def test_train_command_reads_only_normal_drives(tmp_path):
    from umad_common.cli import main as umad_main
    from umad_common.datasets.anovox import write_benchmark_scenario
    from umad_common.datasets.drive import DriveFrame, EgoState

    def drive(n, seed):
        rng = np.random.default_rng(seed)
        for i in range(n):
            rgb = rng.integers(0, 255, (64, 96, 3), dtype=np.uint8)
            yield DriveFrame(100 + i, rgb, None, None, None, np.zeros((64, 96), np.uint8), None, EgoState(), None)

    write_benchmark_scenario(drive(3, 0), tmp_path / "normal", "Scenario_n1")
    write_benchmark_scenario(drive(3, 1), tmp_path / "normal", "Scenario_n2")
    write_benchmark_scenario(drive(5, 2), tmp_path / "anomalous", "Scenario_a1")
    out = tmp_path / "model" / "mnad.safetensors"
    args = ["train", "mnad", str(tmp_path), "--out", str(out), "--epochs", "1", "--batch-size", "3", "--seed", "1"]
    assert umad_main(args) == 0
    model, record = load_mnad(out)
    assert record["training"]["frames"] == 6 and record["training"]["steps"] == 2
    assert model.cfg.height == 128 and model.cfg.width == 192

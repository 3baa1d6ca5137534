"""World model: shapes, determinism, weight files, the predictor operator, one tiny training run."""

from __future__ import annotations

import json
import shlex
from dataclasses import asdict

import numpy as np
import pytest
import torch

from umad_common.dataflow import Frame
from umad_common.dataflow.api.messages import Message
from umad_common.models.weights import WeightsError
from umad_common.models.world_model import (
    MotionWarp,
    Observation,
    State,
    UpsampledConv,
    WorldModel,
    WorldModelConfig,
    lidar_range_image,
    load_world_model,
    save_world_model,
)
from umad_operators.world_model import WorldModelPredictor

torch.set_num_threads(1)

TINY = dict(
    image_height=32,
    image_width=64,
    image_channels=(4, 4, 8),
    decoder_channels=(8, 4, 4, 4),
    lidar_rows=32,
    lidar_width=64,
    lidar_channels=(4, 4, 8, 8, 8),
    lidar_embed=8,
    route_size=16,
    route_channels=(4, 4, 4, 4),
    route_embed=8,
    deter_channels=4,
    stoch_channels=2,
    side_channels=4,
    hidden_channels=8,
    transition_kernel=3,
    motion_channels=4,
)


def tiny_model(seed: int = 0, **overrides) -> WorldModel:
    torch.manual_seed(seed)
    return WorldModel(WorldModelConfig(**{**TINY, **overrides})).eval()


def random_observation(config: WorldModelConfig, b: int, t: int, seed: int = 1) -> tuple[Observation, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    obs = Observation(
        rgb=torch.rand(b, t, 3, config.image_height, config.image_width, generator=g),
        lidar=torch.rand(b, t, 4, config.lidar_rows, config.lidar_width, generator=g),
        route=torch.rand(b, t, 1, config.route_size, config.route_size, generator=g),
        speed=torch.rand(b, t, 1, generator=g),
    )
    return obs, torch.rand(b, t, 2, generator=g) * 2 - 1


def test_observe_and_imagine_shapes():
    model = tiny_model(ground_flow=True)
    c = model.config
    obs, actions = random_observation(c, b=2, t=5)
    result = model.observe(obs, actions)
    assert result.rgb.shape == (2, 5, 3, 32, 64)
    assert result.states.h.shape == (2, 5, c.deter_dim) and result.states.z.shape == (2, 5, c.stoch_dim)
    assert result.prior_std.min() >= c.min_std and result.post_std.min() >= c.min_std
    assert 0.0 <= result.rgb.min() and result.rgb.max() <= 1.0
    last = State(result.states.h[:, -1], result.states.z[:, -1])
    imagined = model.imagine(last, actions[:, :3], 3, speed=obs.speed[:, -1, 0])
    assert imagined.rgb.shape == (2, 3, 3, 32, 64)
    assert imagined.states.h.shape == (2, 3, c.deter_dim)
    with pytest.raises(ValueError, match="at least 4"):
        model.imagine(last, actions[:, :3], 4, speed=obs.speed[:, -1, 0])
    with pytest.raises(ValueError, match="pass `speed`"):
        model.imagine(last, actions[:, :3], 3)


def test_motion_warp_starts_as_the_identity_and_moves_cells_by_its_displacement():
    torch.manual_seed(0)
    config = WorldModelConfig(image_height=24, image_width=32, motion_channels=4, max_shift=4.0, ground_flow=False)
    warp = MotionWarp(in_channels=3, config=config)  # a 6 x 8 grid
    features, maps = torch.randn(2, 3, 6, 8), torch.randn(2, 5, 6, 8)
    assert torch.allclose(warp(features, maps), maps, atol=1e-5)  # zero-initialised head: no motion
    with torch.no_grad():  # a displacement of exactly +1 cell in x (columns) and 0 in y everywhere
        warp.net[-1].bias.copy_(torch.tensor([float(np.arctanh(1 / 4.0)), 0.0]))
    moved = warp(features, maps)
    assert torch.allclose(moved[..., :-1], maps[..., 1:], atol=1e-5)  # each cell takes its right neighbour's content
    assert torch.allclose(moved[..., -1], maps[..., -1], atol=1e-5)  # past the border: the edge repeats


def test_the_road_flow_brings_each_road_cell_from_where_the_camera_saw_it_a_step_before():
    config = WorldModelConfig(ground_flow=True, camera_fov=90.0, camera_height=1.8)  # a 32 x 48 grid of 4 x 4 px cells
    warp = MotionWarp(in_channels=3, config=config)
    travel = 0.9  # metres: 9 m/s for 0.1 s
    shift = warp.ground_source(torch.tensor([travel]))[0]  # (2, rows, cols) in cells
    focal = config.image_width / 2  # px: a 90 degree field of view
    for row, col in ((31, 0), (24, 30), (17, 40)):  # cells below the horizon (row 16 is the first)
        u = (col + 0.5) * 4 - config.image_width / 2  # the cell's centre, px from the image centre
        v = (row + 0.5) * 4 - config.image_height / 2
        depth = focal * config.camera_height / v  # the road point the cell sees now...
        lateral = u * depth / focal
        before = depth + travel  # ...was this far away a step before
        seen = (focal * lateral / before, focal * config.camera_height / before)
        assert shift[0, row, col].item() == pytest.approx((seen[0] - u) / 4, abs=1e-4)
        assert shift[1, row, col].item() == pytest.approx((seen[1] - v) / 4, abs=1e-4)
    assert not shift[:, :16].any()  # above the horizon: no road, no prior flow
    features, maps = torch.randn(1, 3, 32, 48), torch.randn(1, 5, 32, 48)
    assert torch.allclose(warp(features, maps), maps, atol=1e-5)  # standing still: the identity
    moved = warp(features, maps, torch.tensor([travel]))
    assert torch.allclose(moved[:, :, :16], maps[:, :, :16], atol=1e-5)
    assert not torch.allclose(moved[:, :, 20:], maps[:, :, 20:], atol=1e-2)


def test_a_model_saved_before_the_road_flow_loads_without_it():
    saved = WorldModelConfig(ground_flow=True).to_dict()
    assert WorldModelConfig.from_dict(saved).ground_flow is True
    del saved["ground_flow"]
    assert WorldModelConfig.from_dict(saved).ground_flow is False


def test_upsampled_conv_is_upsampling_then_the_convolution():
    torch.manual_seed(0)
    upsample, conv = torch.nn.Upsample(scale_factor=2.0), torch.nn.Conv2d(5, 7, 3, padding=1)
    x = torch.randn(2, 5, 6, 9)
    with torch.no_grad():
        assert torch.allclose(UpsampledConv(upsample, conv)(x), conv(upsample(x)), atol=1e-5)
    with pytest.raises(ValueError, match="nearest x2"):
        UpsampledConv(torch.nn.Upsample(scale_factor=2.0, mode="bilinear"), conv)
    with pytest.raises(ValueError, match="3x3"):
        UpsampledConv(upsample, torch.nn.Conv2d(5, 7, 5, padding=2))


def test_a_folded_decoder_draws_the_same_images():
    model = tiny_model()
    state = State(torch.randn(3, model.config.deter_dim), torch.randn(3, model.config.stoch_dim))
    with torch.no_grad():
        before = model.decode(state)
        model.fold_upsampling()
        assert any(isinstance(layer, UpsampledConv) for layer in model.image_decoder[-1])
        assert torch.allclose(model.decode(state), before, atol=1e-6)


def test_config_rejects_image_size_not_divisible():
    with pytest.raises(ValueError, match="must be divisible by"):
        WorldModelConfig(image_height=102)


def test_same_seed_same_model_and_samples():
    a, b = tiny_model(seed=3), tiny_model(seed=3)
    obs, actions = random_observation(a.config, b=1, t=4)
    torch.manual_seed(7)
    ra = a.observe(obs, actions, sample=True)
    torch.manual_seed(7)
    rb = b.observe(obs, actions, sample=True)
    assert torch.equal(ra.rgb, rb.rgb)
    assert not torch.equal(tiny_model(seed=4).observe(obs, actions).rgb, a.observe(obs, actions).rgb)


def test_observe_in_chunks_equals_one_pass():
    model = tiny_model()
    obs, actions = random_observation(model.config, b=1, t=6)
    whole = model.observe(obs, actions)
    first = model.observe(Observation(*(x[:, :4] for x in obs)), actions[:, :4])
    state = State(first.states.h[:, -1], first.states.z[:, -1])
    second = model.observe(Observation(*(x[:, 4:] for x in obs)), actions[:, 4:], state=state)
    assert torch.allclose(torch.cat([first.rgb, second.rgb], 1), whole.rgb, atol=1e-6)


def test_lidar_projection_puts_points_where_expected():
    config = WorldModelConfig(lidar_rows=64, lidar_width=256)
    # stored as (x, -y, z, i): a point 10 m ahead at the horizon, one 10 m to the left (stored y = +10)
    points = np.array([[10.0, 0.0, 0.0, 1.0], [0.0, 10.0, 0.0, 1.0], [20.0, 0.0, 0.0, 1.0]], np.float32)
    image = lidar_range_image(points, config)
    horizon_row = int(15.0 / 40.0 * 64)
    assert image[3, horizon_row, 128] == pytest.approx(10.0 / 50.0)  # ahead: centre column, nearest wins
    assert image[3, horizon_row, 64] == pytest.approx(10.0 / 50.0)  # left: a quarter turn to the left
    assert image[0, horizon_row, 128] == pytest.approx(0.2) and image[1, horizon_row, 64] == pytest.approx(0.2)
    assert np.count_nonzero(image[3]) == 2
    assert lidar_range_image(None, config).shape == (4, 64, 256)


def test_save_load_round_trip(tmp_path):
    model = tiny_model(seed=5)
    path = save_world_model(model, tmp_path / "wm", {"note": "x"})
    assert path.name == "wm.safetensors" and (tmp_path / "wm.json").is_file()
    loaded, record = load_world_model(tmp_path / "wm.safetensors")
    assert record["note"] == "x" and loaded.config == model.config
    obs, actions = random_observation(model.config, b=1, t=3)
    assert torch.equal(loaded.observe(obs, actions).rgb, model.observe(obs, actions).rgb)


def test_wrong_shape_weights_name_the_tensor(tmp_path):
    save_world_model(tiny_model(), tmp_path / "wm")
    meta = json.loads((tmp_path / "wm.json").read_text())
    meta["config"]["deter_channels"] = 6
    (tmp_path / "wm.json").write_text(json.dumps(meta))
    with pytest.raises(WeightsError, match=r"tensor '[\w.]+' has shape \(\d+(, \d+)*\); expected \(\d+(, \d+)*\)"):
        load_world_model(tmp_path / "wm")
    with pytest.raises(WeightsError, match="not found"):
        load_world_model(tmp_path / "missing")


# ---------------------------------------------------------------------------------------------
# The predictor operator


def sensor_frame(run: str, seq: int, rng: np.random.Generator) -> Frame:
    def msg(arrays):
        return Message(run=run, seq=seq, arrays=arrays)

    points = rng.normal(0, 10, (200, 4)).astype(np.float32)
    ego = np.array([5.0, rng.uniform(0, 1), 0.0, rng.uniform(-0.3, 0.3)], np.float32)
    return Frame(
        run=run,
        seq=seq,
        stamp_ns=seq,
        inputs={
            "camera": msg({"rgb": rng.integers(0, 256, (48, 80, 3), dtype=np.uint8)}),
            "lidar": msg({"points": points}),
            "ego": msg({"ego": ego}),
            "route": msg({"route": rng.integers(0, 2, (192, 192), dtype=np.uint8) * 255}),
        },
    )


@pytest.fixture
def weights(tmp_path):
    save_world_model(tiny_model(seed=2, ground_flow=True), tmp_path / "wm")
    return tmp_path / "wm.safetensors"


def test_predictor_outputs_and_predictions_made_earlier(weights):
    op = WorldModelPredictor({"model": str(weights), "horizon": 3})
    frames = [sensor_frame("run_a", seq, np.random.default_rng(seq)) for seq in range(5)]
    outputs = [op.process(f)["frame"].arrays for f in frames]
    out = outputs[4]
    assert (
        out["target"].shape == (32, 64, 3)
        and out["recon"].shape == (32, 64, 3)
        and out["preds"].shape == (3, 32, 64, 3)
    )
    assert [list(o["pred_valid"]) for o in outputs] == [[0, 0, 0], [1, 0, 0], [1, 1, 0], [1, 1, 1], [1, 1, 1]]
    assert not outputs[0]["preds"].any()

    # independent reference: filter the sequence, then imagine from the state i steps back
    model, _ = load_world_model(weights)
    obs = [op.observation(f) for f in frames]
    seq_obs = Observation(*(torch.cat([o[0][k] for o in obs], 1) for k in range(4)))
    taken = torch.from_numpy(np.stack([o[2] for o in obs]))[None]  # (1, T, 2) action after each frame
    prev = torch.cat([torch.zeros(1, 1, 2), taken[:, :-1]], 1)
    with torch.no_grad():
        result = model.observe(seq_obs, prev)
        assert np.allclose(out["recon"], result.rgb[0, 4].permute(1, 2, 0).numpy(), atol=1e-5)
        for i in (1, 2, 3):
            start = State(result.states.h[:, 4 - i], result.states.z[:, 4 - i])
            speed = seq_obs.speed[:, 4 - i, 0]  # the speed of the frame the rollout started from
            expected = model.imagine(start, taken[:, 4 - i : 4], i, speed=speed).rgb[0, -1].permute(1, 2, 0).numpy()
            assert np.allclose(out["preds"][i - 1], expected, atol=1e-5), f"x̂_(t|t-{i})"


def test_predictor_resets_at_a_new_run_and_honours_stride(weights):
    op = WorldModelPredictor({"model": str(weights), "horizon": 2, "stride": 2})
    first = op.process(sensor_frame("run_a", 0, np.random.default_rng(0)))["frame"]
    outs = [op.process(sensor_frame("run_a", s, np.random.default_rng(s)))["frame"] for s in range(1, 5)]
    assert [o.meta["model_step"] for o in outs] == [False, True, False, True]
    assert [list(o.arrays["pred_valid"]) for o in outs] == [[0, 0], [1, 0], [0, 0], [1, 1]]
    again = op.process(sensor_frame("run_b", 0, np.random.default_rng(0)))["frame"]
    assert np.array_equal(again.arrays["recon"], first.arrays["recon"]) and not again.arrays["pred_valid"].any()


def test_predictor_steps_on_unscored_frames_without_drawing_them(weights):
    frames = [sensor_frame("run_a", seq, np.random.default_rng(seq)) for seq in range(4)]
    every = WorldModelPredictor({"model": str(weights), "horizon": 2})
    expected = [every.process(f)["frame"].arrays for f in frames]
    skipping = WorldModelPredictor({"model": str(weights), "horizon": 2})
    for seq, frame in enumerate(frames):
        if seq % 2:
            frame.inputs["camera"].meta["skip"] = True
        out = skipping.process(frame)["frame"].arrays
        if seq % 2:
            assert not out["recon"].any() and not out["pred_valid"].any()
        else:  # the state moved on through the skipped frame: identical to seeing every frame drawn
            assert np.array_equal(out["recon"], expected[seq]["recon"])
            assert np.array_equal(out["preds"], expected[seq]["preds"])


def test_predictor_bridges_a_gap_with_the_prior_and_restarts_after_a_longer_one(weights):
    """Live mode passes frames over: after frames 3 and 4 never came, frame 5's state is frame 2's
    carried two steps by the prior (frame 2's action held) and then observing frame 5; of the
    predictions only x̂_(5|2) exists. A gap longer than `max_gap_steps` starts the run over."""
    frames = {seq: sensor_frame("run_a", seq, np.random.default_rng(seq)) for seq in (0, 1, 2, 5)}
    op = WorldModelPredictor({"model": str(weights), "horizon": 3, "max_gap_steps": 2})
    for seq in (0, 1, 2):
        op.process(frames[seq])
    out = op.process(frames[5])["frame"]
    assert out.meta["gap_steps"] == 2 and list(out.arrays["pred_valid"]) == [0, 0, 1]
    assert not out.arrays["preds"][:2].any()

    model, _ = load_world_model(weights)  # independent reference, step by step
    obs = {seq: op.observation(frame) for seq, frame in frames.items()}
    seq_obs = Observation(*(torch.cat([obs[s][0][k] for s in (0, 1, 2)], 1) for k in range(4)))
    taken = torch.from_numpy(np.stack([obs[s][2] for s in (0, 1, 2)]))[None]  # (1, 3, 2)
    with torch.no_grad():
        filtered = model.observe(seq_obs, torch.cat([torch.zeros(1, 1, 2), taken[:, :-1]], 1))
        at_2 = State(filtered.states.h[:, 2], filtered.states.z[:, 2])
        held = taken[:, 2]
        state = at_2
        for _ in range(2):  # frames 3 and 4: what the model expects without looking
            hidden = model.transition(state, held, move=False)
            state = State(hidden, model.prior(hidden)[0])
        hidden = model.transition(state, held, move=False)
        at_5 = State(hidden, model.posterior(hidden, model.embed(obs[5][0])[:, 0])[0])
        recon = model.decode(at_5)[0].permute(1, 2, 0).numpy()
        speed = seq_obs.speed[:, 2, 0]
        from_2 = model.imagine(at_2, held[:, None].expand(1, 3, 2), 3, speed=speed).rgb[0, -1].permute(1, 2, 0)
    assert np.allclose(out.arrays["recon"], recon, atol=1e-5)
    assert np.allclose(out.arrays["preds"][2], from_2.numpy(), atol=1e-5)

    restarted = WorldModelPredictor({"model": str(weights), "horizon": 3, "max_gap_steps": 2})
    for seq in (0, 1):
        restarted.process(frames[seq])
    out = restarted.process(frames[5])["frame"]  # 3 steps missed
    fresh = WorldModelPredictor({"model": str(weights), "horizon": 3}).process(frames[5])["frame"]
    assert out.meta["gap_steps"] == 3 and out.meta["steps"] == 1 and not out.arrays["pred_valid"].any()
    assert np.array_equal(out.arrays["recon"], fresh.arrays["recon"])


def test_predictor_in_bfloat16_publishes_float32_images_close_to_float32(weights):
    """`precision: bfloat16` runs the model under bfloat16 autocast along a run (its state included)
    and still publishes float32 images, a few hundredths from the float32 operator's at most; the
    precision cannot change while the state exists."""
    frames = [sensor_frame("run_a", seq, np.random.default_rng(seq)) for seq in range(5)]
    full = WorldModelPredictor({"model": str(weights), "horizon": 2})
    half = WorldModelPredictor({"model": str(weights), "horizon": 2, "precision": "bfloat16"})
    for frame in frames:
        a, b = full.process(frame)["frame"].arrays, half.process(frame)["frame"].arrays
        assert b["recon"].dtype == np.float32 and b["preds"].dtype == np.float32
        assert np.abs(a["recon"] - b["recon"]).max() < 0.05 and np.abs(a["preds"] - b["preds"]).max() < 0.05
        assert list(a["pred_valid"]) == list(b["pred_valid"])
    assert np.abs(a["recon"] - b["recon"]).max() > 0  # bfloat16 did run
    with pytest.raises(ValueError, match="precision"):
        half.update_params(half.Params(model=str(weights), horizon=2, precision="float32"))


@pytest.mark.parametrize("fast_bfloat16", [True, False])
def test_predictor_precision_auto_takes_bfloat16_only_where_the_device_has_fast_kernels(
    weights, monkeypatch, caplog, fast_bfloat16
):
    """`precision: auto` (the live graph's) runs bfloat16 where the device has fast bfloat16 kernels and
    float32 elsewhere, where bfloat16 autocast costs several times the CPU; an explicit `bfloat16` is
    kept there, with a warning; the frame's meta says which ran."""
    import umad_operators.world_model as operator_module

    monkeypatch.setattr(operator_module, "bf16_supported", lambda device: fast_bfloat16)
    frame = sensor_frame("run_a", 0, np.random.default_rng(0))
    ran = {
        precision: WorldModelPredictor({"model": str(weights), "precision": precision}).process(frame)["frame"].meta
        for precision in ("float32", "auto", "bfloat16")
    }
    assert [ran[p]["bfloat16"] for p in ("float32", "auto", "bfloat16")] == [False, fast_bfloat16, True]
    warned = "no fast bfloat16 kernels" in caplog.text
    assert warned is not fast_bfloat16


def test_predictor_fails_early_on_missing_or_mismatched_weights(tmp_path, weights):
    with pytest.raises(WeightsError, match="not found"):
        WorldModelPredictor({"model": str(tmp_path / "nothing.safetensors")})
    meta = json.loads(weights.with_suffix(".json").read_text())
    meta["config"]["stoch_channels"] = 3
    weights.with_suffix(".json").write_text(json.dumps(meta))
    with pytest.raises(WeightsError, match="expected"):
        WorldModelPredictor({"model": str(weights)})
    with pytest.raises(ValueError, match="horizon"):
        WorldModelPredictor({"model": str(weights), "horizon": 0})


# ---------------------------------------------------------------------------------------------
# Training and evaluation on a fabricated AnoVox folder (generator layout, 48x80 camera)


def write_drive(folder, frames: int, seed: int, anomalous: bool = False) -> None:
    """A tiny generator-layout scenario. Normal drives get undecodable label files, so a reader
    that touched a label would fail."""
    import cv2

    from umad_common.datasets.anovox import write_key_values

    rng = np.random.default_rng(seed)
    sensors = {key: folder / f"{key}(0, 0, 1.8)(0, 0, 0)_abc" for key in ("RGB-CAM", "LIDAR", "SEMANTIC-CAM")}
    for path in [*sensors.values(), folder / "ACTION", folder / "ROUTE_MAP"]:
        path.mkdir(parents=True)
    for fid in range(100, 100 + frames):
        rgb = np.zeros((48, 80, 3), np.uint8)
        rgb[:20] = (120, 170, 230)
        rgb[20:] = (90, 90, 90)
        semantic = np.full((48, 80), 11, np.uint8)
        semantic[20:] = 1
        if anomalous:
            rgb[30:40, 30:45] = (250, 20, 200)
            semantic[30:40, 30:45] = 100
        rgb = np.clip(rgb.astype(int) + rng.integers(-8, 9, rgb.shape), 0, 255).astype(np.uint8)
        cv2.imwrite(str(sensors["RGB-CAM"] / f"RGB-CAM_{fid}.png"), rgb[..., ::-1])
        np.save(sensors["LIDAR"] / f"LIDAR_{fid}.npy", rng.normal(0, 10, (300, 4)).astype(np.float32))
        semantic_path = sensors["SEMANTIC-CAM"] / f"SEMANTIC-CAM_{fid}.png"
        if anomalous:
            cv2.imwrite(str(semantic_path), semantic)
        else:
            semantic_path.write_bytes(b"not a png")
        cv2.imwrite(str(folder / "ROUTE_MAP" / f"ROUTE_MAP_{fid}.png"), np.full((192, 192), 255, np.uint8))
        write_key_values(
            folder / "ACTION" / f"ACTION_{fid}.csv",
            {
                "frame_id": fid,
                "speed": 20.0,
                "throttle": rng.uniform(0, 1),
                "steer": rng.uniform(-0.2, 0.2),
                "brake": 0.0,
            },
        )


@pytest.fixture(scope="module")
def tiny_benchmark(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    for i in range(3):
        write_drive(root / "normal" / f"Scenario_n{i}", frames=12, seed=i)
    write_drive(root / "anomalous" / "Scenario_a0", frames=6, seed=9, anomalous=True)
    return root


def test_training_writes_weights_is_deterministic_and_resumes(tiny_benchmark, tmp_path, monkeypatch):
    from umad_common.training import train_world_model as training
    from umad_common.training.train_world_model import train_world_model
    from umad_common.training.world_model_step import TrainConfig

    def train(out, epochs, resume=False):
        return train_world_model(
            tiny_benchmark,
            out,
            epochs=epochs,
            seed=3,
            resume=resume,
            threads=1,
            model_config=WorldModelConfig(**TINY),
            train_config=TrainConfig(sequence_length=4, batch_size=2, holdout=1),
        )

    record = train(tmp_path / "a", epochs=2)
    assert record["heldout_drives"] == ["Scenario_n2"] and record["training_drives"] == ["Scenario_n0", "Scenario_n1"]
    assert len(record["history"]) == 2 and np.isfinite(record["history"][-1]["loss"])
    assert (tmp_path / "a.train.pt").is_file()
    saved = []

    def save_then_stop(*args, **kwargs):  # the process dies while writing epoch 2
        saved.append(1)
        if len(saved) == 2:
            raise KeyboardInterrupt
        return save_world_model(*args, **kwargs)

    monkeypatch.setattr(training, "save_world_model", save_then_stop)
    with pytest.raises(KeyboardInterrupt):
        train(tmp_path / "b", epochs=2)
    monkeypatch.undo()
    train(tmp_path / "b", epochs=2, resume=True)
    a, _ = load_world_model(tmp_path / "a")
    b, _ = load_world_model(tmp_path / "b")
    for name, tensor in a.state_dict().items():
        assert torch.equal(tensor, b.state_dict()[name]), name
    with pytest.raises(ValueError, match="already trained 2 epochs"):
        train(tmp_path / "b", epochs=2, resume=True)


def test_a_mirrored_window_is_the_drive_mirrored_in_the_world():
    """Mirroring a training window equals projecting the mirrored world: the lidar of the cloud with
    y negated, the camera and the route map flipped, the steering negated; twice is the identity."""
    from umad_common.training.world_model_data import mirror_window
    from umad_common.training.world_model_step import TrainConfig

    config = WorldModelConfig(lidar_rows=64, lidar_width=256)
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-40, 40, (3000, 2)), rng.uniform(-3, 2, (3000, 1))], 1).astype(np.float32)
    points = np.concatenate([points, np.ones((3000, 1), np.float32)], 1)
    lidar = lidar_range_image(points, config)[None]
    rgb = rng.integers(0, 255, (1, 8, 12, 3), dtype=np.uint8)
    route = rng.integers(0, 255, (1, 16, 16), dtype=np.uint8)
    actions = np.array([[0.5, 0.25]], np.float32)

    m_rgb, m_lidar, m_route, m_actions = mirror_window(rgb, lidar, route, actions)
    np.testing.assert_array_equal(m_lidar[0], lidar_range_image(points * [1, -1, 1, 1], config))
    np.testing.assert_array_equal(m_rgb[0, :, 0], rgb[0, :, -1])
    np.testing.assert_array_equal(m_route[0, :, 0], route[0, :, -1])
    assert m_actions.tolist() == [[0.5, -0.25]]
    for original, twice in zip(
        (rgb, lidar, route, actions), mirror_window(m_rgb, m_lidar, m_route, m_actions), strict=True
    ):
        np.testing.assert_array_equal(original, twice)
    with pytest.raises(ValueError, match="mirror 1.5"):
        TrainConfig(mirror=1.5)


def test_a_relit_window_keeps_its_scene_and_puts_every_frame_under_the_same_light():
    """Re-lighting maps each colour value through one table per channel for the whole window: the
    identity light changes nothing, equal pixels stay equal across frames, order within a channel is
    kept, brighter gains give brighter frames, and only the camera changes."""
    from umad_common.training.world_model_data import DriveArrays, Light, observation_batch, relight_window
    from umad_common.training.world_model_step import TrainConfig

    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (4, 6, 8, 3), dtype=np.uint8)
    rgb[2] = rgb[0]  # the same picture twice in the window
    np.testing.assert_array_equal(relight_window(rgb, Light(1.0, (1.0, 1.0, 1.0))), rgb)
    light = Light.draw(np.random.default_rng(0))
    assert 0.6 <= light.gamma <= 1.6 and all(0.5 * 0.85 <= g <= 1.6 * 1.15 for g in light.gain)
    relit = relight_window(rgb, light)
    np.testing.assert_array_equal(relit[2], relit[0])
    for c in range(3):
        order = np.argsort(rgb[..., c].ravel(), kind="stable")
        assert np.all(np.diff(relit[..., c].ravel()[order].astype(int)) >= 0)
    assert (
        relight_window(rgb, Light(1.0, (1.5, 1.5, 1.5))).mean()
        > rgb.mean()
        > relight_window(rgb, Light(1.0, (0.5,) * 3)).mean()
    )

    drive = DriveArrays(
        "d",
        rgb,
        rng.random((4, 4, 8, 16)).astype(np.float16),
        rng.integers(0, 256, (4, 16, 16), dtype=np.uint8),
        np.ones(4, np.float32),
        np.zeros((4, 2), np.float32),
    )
    plain, _ = observation_batch([drive], [(0, 0)], 4)
    lit, _ = observation_batch([drive], [(0, 0)], 4, lights=[light])
    np.testing.assert_array_equal(lit.rgb[0].permute(0, 2, 3, 1).mul(255).round().byte().numpy(), relit)
    np.testing.assert_array_equal(lit.lidar, plain.lidar)
    np.testing.assert_array_equal(lit.route, plain.route)
    with pytest.raises(ValueError, match="relight 2"):
        TrainConfig(relight=2.0)


def test_training_rollouts_start_from_consecutive_posterior_states_and_match_their_targets():
    from umad_common.training.world_model_step import (
        TrainConfig,
        open_loop_predictions,
        prediction_targets,
        rollout_starts,
    )

    model = tiny_model(ground_flow=True)
    obs, actions = random_observation(model.config, b=2, t=6)
    train = TrainConfig(sequence_length=6, prediction_steps=2, prediction_starts=3)
    assert list(rollout_starts(6, train)) == [1, 2, 3]  # the last start leaves 2 frames: 4 and 5
    frames = torch.arange(6.0).view(1, 6, 1, 1, 1)
    assert prediction_targets(frames, train).flatten().tolist() == [2, 3, 3, 4, 4, 5]
    with torch.no_grad():
        result = model.observe(obs, actions)
        predicted = open_loop_predictions(model, result, actions, obs.speed, train).rgb
        assert predicted.shape == (2, 6, 3, model.config.image_height, model.config.image_width)
        start = State(result.states.h[:, 2], result.states.z[:, 2])  # the second rollout, on its own
        alone = model.imagine(start, actions[:, 3:5], speed=obs.speed[:, 2, 0]).rgb
    assert torch.allclose(predicted[:, 2:4], alone, atol=1e-6)
    with pytest.raises(ValueError, match="prediction_starts 5"):
        TrainConfig(sequence_length=6, prediction_steps=2, prediction_starts=5)


def test_evaluation_reports_psnr_per_step_and_anomaly_road_ratio(tiny_benchmark):
    from umad_common.training.evaluate_world_model import evaluate_world_model

    record = {"training_drives": ["Scenario_n0", "Scenario_n1"]}
    figures = evaluate_world_model(tiny_model(), tiny_benchmark, record, horizon=3)
    assert figures["normal_drives"] == 1 and figures["normal_frames"] == 12
    assert figures["anomalous_drives"] == 1 and figures["anomaly_pixels"] > 0
    assert all(0 < figures[key] < 60 for key in ("recon_psnr", "pred1_psnr", "pred2_psnr", "pred3_psnr"))
    assert figures["anomaly_road_ratio"] == pytest.approx(figures["anomaly_error"] / figures["road_error"])
    # any folder of normal drives: a model that names none of them as training drives is scored on all
    every = evaluate_world_model(tiny_model(), tiny_benchmark / "normal", {}, horizon=1)
    assert every["normal_drives"] == 3 and len(every["per_drive"]) == 3
    # each drive's PSNRs, pooled over its frames, give the overall ones (the drives are equally long)
    for key in ("recon_psnr", "pred1_psnr"):
        mean_mse = np.mean([10 ** (-drive[key] / 10) for drive in every["per_drive"].values()])
        assert every[key] == pytest.approx(-10 * np.log10(mean_mse), abs=1e-6)


def test_evaluation_predictions_are_the_prior_rolled_from_k_steps_back(tiny_benchmark):
    from umad_common.datasets.formats import label_free_drive
    from umad_common.training.evaluate_world_model import filter_drive, predict_drive
    from umad_common.training.world_model_data import load_drive

    model = tiny_model(ground_flow=True)
    drive = load_drive(label_free_drive(tiny_benchmark / "normal" / "Scenario_n0"), model.config)
    posterior, _ = filter_drive(model, drive, chunk=5)  # chunked filtering = one pass
    actions = torch.from_numpy(drive.action)[None]  # (1, T, 2) the action taken after frame t
    with torch.no_grad():
        for k, frames, predicted, _ in predict_drive(model, drive, posterior, horizon=3, chunk=4):
            assert list(frames) == list(range(k, len(drive)))
            for t in (k, len(drive) - 1):
                start = State(posterior.h[t - k : t - k + 1], posterior.z[t - k : t - k + 1])
                speed = torch.tensor([drive.speed[t - k] / model.config.speed_scale])
                expected = model.imagine(start, actions[:, t - k : t], k, speed=speed).rgb[0, -1]
                expected = expected.permute(1, 2, 0).numpy()
                assert np.allclose(predicted[t - k], expected, atol=1e-5), (k, t)


def test_test_world_model_command_names_data_it_cannot_score(tmp_path):
    import argparse

    from umad_common.commands import test_world_model
    from umad_common.commands.checks import InputError

    write_drive(tmp_path / "data" / "normal" / "Scenario_n0", frames=4, seed=0)
    save_world_model(tiny_model(), tmp_path / "wm", {"training_drives": ["Scenario_n0"]})
    args = argparse.Namespace(
        model=tmp_path / "wm.safetensors", data=tmp_path / "data", horizon=3, normal_limit=None,
        anomalous_limit=None, threads=1, topics=None,
    )  # fmt: skip
    with pytest.raises(SystemExit, match="no normal drive the model did not train on"):
        test_world_model.run(args)
    args.data = tmp_path / "empty"
    args.data.mkdir()
    with pytest.raises(InputError, match="holds no drive"):
        test_world_model.run(args)


def test_readme_recipe_rebuilds_the_shipped_world_model():
    """The README's `umad train world-model` line, parsed as the CLI parses it, asks for exactly the
    configs, epochs, seed and threads the shipped model's JSON records, and is the command it records."""
    from dataclasses import asdict

    from tests.conftest import readme_recipe
    from umad_common import ASSETS
    from umad_common.commands import train_world_model

    args, words = readme_recipe("world-model", train_world_model)
    model_config, train, epochs, seed = train_world_model.configs_of(args)
    shipped = json.loads((ASSETS / "world_model.json").read_text())
    assert {**model_config.to_dict(), "lidar_head": True} == shipped["config"]  # the head: the recipe's next line
    assert asdict(train) == shipped["train_config"]
    assert (epochs, seed, args.threads) == (shipped["epochs"], shipped["seed"], shipped["threads"])
    assert shipped["command"] == train_world_model.command_line(args) == shlex.join(words)


# ---------------------------------------------------------------------------------------------
# The lidar head: the lidar as the camera sees it, reconstructed and predicted

LIDAR_HEAD = dict(lidar_head=True)


def test_lidar_returns_land_where_the_camera_sees_them_nearest_first():
    from umad_common.datasets.sensor_rig import SensorRig
    from umad_common.models.world_model import lidar_returns, lidar_view

    config = WorldModelConfig(**TINY, **LIDAR_HEAD)
    assert config.lidar_view_shape == (64, 128)  # twice the 32 x 64 image: focal 64 view px at FOV 90
    rig = SensorRig(64, 32, 90.0, (0.0, 0.0, 1.8), (0.0, 0.0, 1.8))
    points = np.array(
        [
            [10.0, 0.0, 0.0, 1.0],  # straight ahead: the view's centre (row 32, column 64)
            [5.0, 0.0, 0.0, 1.0],  # the same pixel, nearer: it wins
            [-5.0, 0.0, 0.0, 1.0],  # behind the camera
            [10.0, -20.0, 0.0, 1.0],  # 20 m to the right (AnoVox stores -y): outside the frustum
            [10.0, 4.9, 2.0, 1.0],  # 4.9 m left, 2 m up: column 64 - 64 * 0.49, row 32 - 64 * 0.2
        ],
        np.float32,
    )
    returns = lidar_returns(points, config, rig)
    assert returns.row.tolist() == [19, 32] and returns.col.tolist() == [32, 64]
    assert returns.range.tolist() == pytest.approx([np.sqrt(128.01), 5.0])
    assert returns.rise.tolist() == pytest.approx([2.0 / np.sqrt(128.01), 0.0])  # the beams' climb per metre
    turned = SensorRig(64, 32, 90.0, (0.0, 0.0, 1.8), (0.0, 0.0, 1.8), lidar_axes=((1, 0, 0), (0, 0, -1), (0, 1, 0)))
    assert lidar_returns(np.array([[10.0, 2.0, 0.0, 1.0]], np.float32), config, turned).rise[0] == pytest.approx(
        2.0 / np.sqrt(104.0)
    )  # a lidar rolled 90 degrees: its y axis is the vehicle's up
    view = lidar_view(returns, config)
    assert view[32, 64] == 5.0 and np.count_nonzero(view) == 2
    assert len(lidar_returns(None, config, rig).range) == 0


def test_lidar_head_decodes_the_view_and_folds_like_the_image_decoder():
    model = tiny_model(**LIDAR_HEAD)
    obs, actions = random_observation(model.config, b=2, t=3)
    with torch.no_grad():
        result = model.observe(obs, actions, images=False)
        assert result.rgb is None
        states = State(result.states.h.flatten(0, 1), result.states.z.flatten(0, 1))
        ranges = model.decode_lidar(states)
        assert ranges.shape == (6, 64, 128) and ranges.min() > 0
        model.fold_upsampling()
        assert torch.allclose(model.decode_lidar(states), ranges, rtol=1e-4)
    without = tiny_model()
    assert not hasattr(without, "lidar_decoder")
    with pytest.raises(ValueError, match="no lidar head"):
        without.decode_lidar(states)


def test_a_world_model_saved_before_the_lidar_head_loads_without_one(tmp_path):
    path = save_world_model(tiny_model(), tmp_path / "old")
    meta = tmp_path / "old.json"
    saved = json.loads(meta.read_text())
    for key in ("lidar_head", "lidar_view_scale", "lidar_decoder_channels"):
        del saved["config"][key]  # as the files written before the head existed
    meta.write_text(json.dumps(saved))
    model, _ = load_world_model(path)
    assert not model.config.lidar_head


def test_fitting_a_lidar_head_leaves_every_other_weight_as_it_was(tiny_benchmark, tmp_path):
    from umad_common.training.fit_lidar_head import fit_lidar_head
    from umad_common.training.world_model_step import TrainConfig

    base = tmp_path / "base"
    save_world_model(tiny_model(), base, {"train_config": {"sequence_length": 4, "batch_size": 2, "holdout": 1}})
    fit = fit_lidar_head(tiny_benchmark, base, tmp_path / "with_head", epochs=2, seed=1, threads=1, command="fit")
    assert len(fit["history"]) == 2 and all(np.isfinite(e["lidar_l1"]) for e in fit["history"])
    assert fit["heldout_drives"] == ["Scenario_n2"]
    old, _ = load_world_model(base)
    new, record = load_world_model(tmp_path / "with_head")
    assert new.config.lidar_head and record["lidar_head_fit"]["command"] == "fit"
    assert record["train_config"] == asdict(TrainConfig(sequence_length=4, batch_size=2, holdout=1))
    new_state = new.state_dict()
    for key, tensor in old.state_dict().items():
        assert torch.equal(new_state[key], tensor), key
    assert any(key.startswith("lidar_decoder.") for key in new_state)
    with pytest.raises(ValueError, match="already has a lidar head"):
        fit_lidar_head(tiny_benchmark, tmp_path / "with_head", tmp_path / "again", epochs=1, threads=1)


def test_joint_training_learns_the_lidar_view_and_the_evaluation_reports_its_range_error(tiny_benchmark, tmp_path):
    from umad_common.training.evaluate_world_model import evaluate_world_model
    from umad_common.training.train_world_model import train_world_model
    from umad_common.training.world_model_step import TrainConfig

    record = train_world_model(
        tiny_benchmark,
        tmp_path / "joint",
        epochs=2,
        seed=0,
        threads=1,
        model_config=WorldModelConfig(**TINY, **LIDAR_HEAD),
        train_config=TrainConfig(sequence_length=4, batch_size=2, holdout=1),
    )
    history = record["history"]
    assert all(np.isfinite(e["lidar_l1"]) and np.isfinite(e["pred_lidar_l1"]) for e in history)
    model, saved = load_world_model(tmp_path / "joint")
    figures = evaluate_world_model(model, tiny_benchmark, saved, horizon=2)
    for key in ("recon_range_error_m", "pred1_range_error_m", "pred2_range_error_m"):
        assert 0 <= figures[key] < 100, key
    assert "recon_range_error_m" not in evaluate_world_model(tiny_model(), tiny_benchmark, saved, horizon=1)


def test_predictor_sends_the_returns_and_the_range_its_lidar_view_expects(tmp_path):
    from umad_common.datasets.sensor_rig import SensorRig
    from umad_common.models.world_model import lidar_returns

    model = tiny_model(**LIDAR_HEAD)
    save_world_model(model, tmp_path / "wm")
    predictor = WorldModelPredictor({"model": str(tmp_path / "wm.safetensors"), "horizon": 2})
    rng = np.random.default_rng(0)
    points = np.column_stack([rng.uniform(2, 40, 500), rng.uniform(-20, 20, 500), rng.uniform(-1.8, 3, 500)])
    points = np.column_stack([points, np.ones(500)]).astype(np.float32)
    sensors = {
        "camera": {"width": 64, "height": 32, "fov": 90.0, "location": [0, 0, 1.8], "rotation": [0, 0, 0]},
        "lidar": {"location": [0, 0, 1.8], "rotation": [0, 0, 0]},
    }
    frame = Frame(
        "run",
        0,
        0,
        inputs={
            "camera": Message("run", 0, arrays={"rgb": np.zeros((32, 64, 3), np.uint8)}),
            "lidar": Message("run", 0, meta={"sensors": sensors}, arrays={"points": points}),
            "ego": Message("run", 0, arrays={"ego": np.array([5.0, 0.5, 0.0, 0.0], np.float32)}),
            "route": Message("run", 0, arrays={"route": np.zeros((192, 192), np.uint8)}),
        },
    )
    arrays = predictor.process(frame)["frame"].arrays
    returns = lidar_returns(points, model.config, SensorRig.from_sensors(sensors, "test"))
    assert len(arrays["lidar_range"]) == len(returns.range) > 0
    assert arrays["lidar_pixel"].dtype == np.int32
    assert (arrays["lidar_pixel"] == np.column_stack([returns.row // 2, returns.col // 2])).all()
    np.testing.assert_array_equal(arrays["lidar_range"], returns.range)
    assert arrays["lidar_expected"].dtype == np.float32 and (arrays["lidar_expected"] > 0).all()
    save_world_model(tiny_model(), tmp_path / "camera_only")
    camera_only = WorldModelPredictor({"model": str(tmp_path / "camera_only.safetensors"), "horizon": 2})
    assert "lidar_range" not in camera_only.process(frame)["frame"].arrays


def test_readme_recipe_adds_the_shipped_lidar_head():
    """The README's `umad train lidar-head` line is the command the shipped model's head was fitted with."""
    from tests.conftest import readme_recipe
    from umad_common import ASSETS
    from umad_common.commands import train_lidar_head

    args, words = readme_recipe("lidar-head", train_lidar_head)
    fit = json.loads((ASSETS / "world_model.json").read_text())["lidar_head_fit"]
    assert fit["command"] == train_lidar_head.command_line(args) == shlex.join(words)
    assert (fit["epochs"], fit["seed"], fit["threads"]) == (args.epochs, args.seed, args.threads)

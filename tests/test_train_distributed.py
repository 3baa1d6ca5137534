"""Training across processes (umad_common.training.distributed): two gloo ranks on the CPU train the
windows one process trains, split between them, and resume from rank 0's checkpoint; `--nproc 1`
writes what the training always wrote."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from dataclasses import asdict

import numpy as np
import pytest
import torch

from tests.conftest import REPO, umad_env
from tests.test_world_model import TINY, write_drive
from umad_common.models.world_model import WorldModelConfig, load_world_model, save_world_model
from umad_common.training.distributed import Rank, run_processes
from umad_common.training.train_world_model import train_world_model
from umad_common.training.world_model_step import TrainConfig

TIMING_KEYS = ("train_seconds", "samples_per_second", "command")  # what differs between two runs of one training


@pytest.fixture(scope="module")
def normal_drives(tmp_path_factory):
    root = tmp_path_factory.mktemp("drives")
    for i in range(3):
        write_drive(root / "normal" / f"Scenario_n{i}", frames=12, seed=i)
    return root


def training(data, out, epochs: int, resume: bool = False) -> dict:
    """The tiny model's training, half its windows mirrored and half re-lit."""
    return dict(
        data=data,
        out=out,
        epochs=epochs,
        seed=3,
        resume=resume,
        threads=1,
        model_config=WorldModelConfig(**TINY),
        train_config=TrainConfig(sequence_length=4, batch_size=2, holdout=1, mirror=0.5, relight=0.5),
    )


def weights(path) -> dict[str, torch.Tensor]:
    return load_world_model(path)[0].state_dict()


def test_a_rank_takes_every_world_th_item_so_the_shares_are_the_items_each_once():
    items = list(range(7))
    shares = [Rank(index, 3).share(items) for index in range(3)]
    assert shares == [[0, 3, 6], [1, 4], [2, 5]]
    assert sorted(sum(shares, [])) == items
    assert Rank().share(items) == items and not Rank().distributed


@pytest.mark.slow
def test_two_processes_train_the_windows_of_one_and_resume_from_rank_zero(normal_drives, tmp_path):
    train_world_model(**training(normal_drives, tmp_path / "one", epochs=2))
    run_processes(2, train_world_model, training(normal_drives, tmp_path / "two", epochs=2))
    one = json.loads((tmp_path / "one.json").read_text())
    two = json.loads((tmp_path / "two.json").read_text())
    assert two["processes"] == 2 and "processes" not in one
    # every step trains the same windows with the same augmentations, half in each process: the
    # losses (averaged over the ranks) and the weights are the single process's up to float rounding
    for a, b in zip(one["history"], two["history"], strict=True):
        for key in ("loss", "rgb_l1", "kl"):
            assert b[key] == pytest.approx(a[key], rel=1e-4), key
    single, split = weights(tmp_path / "one"), weights(tmp_path / "two")
    assert max(float((single[k].float() - split[k].float()).abs().max()) for k in single) < 1e-3
    # stopped while writing epoch 2 and resumed in two processes: the uninterrupted run's weights
    with pytest.raises(Exception, match="stopped while writing epoch 2"):
        run_processes(2, stop_while_writing_epoch_2, training(normal_drives, tmp_path / "resumed", epochs=2))
    run_processes(2, train_world_model, training(normal_drives, tmp_path / "resumed", epochs=2, resume=True))
    resumed = weights(tmp_path / "resumed")
    for name, tensor in split.items():
        assert torch.equal(tensor, resumed[name]), name


def stop_while_writing_epoch_2(**kwargs) -> None:
    """`train_world_model` whose writing rank fails as it writes epoch 2's weights (its checkpoint is epoch 1's)."""
    from umad_common.training import train_world_model as module

    written = []

    def save_then_stop(*args, **save_kwargs):
        written.append(1)
        if len(written) == 2:
            raise RuntimeError("stopped while writing epoch 2")
        return save_world_model(*args, **save_kwargs)

    module.save_world_model = save_then_stop
    module.train_world_model(**kwargs)


@pytest.mark.slow
def test_nproc_1_writes_the_bytes_of_a_plain_training_and_nproc_2_trains(normal_drives, tmp_path):
    plain = training(normal_drives, tmp_path / "plain", epochs=1)
    train_world_model(**plain)
    config = tmp_path / "tiny.json"
    config.write_text(
        json.dumps({"config": plain["model_config"].to_dict(), "train_config": asdict(plain["train_config"])})
    )
    for nproc in ("1", "2"):
        out = tmp_path / f"nproc{nproc}"
        args = ["train", "world-model", str(normal_drives), "--out", str(out), "--config", str(config)]
        args += ["--epochs", "1", "--seed", "3", "--threads", nproc, "--device", "cpu", "--nproc", nproc]
        done = subprocess.run(
            [sys.executable, "-m", "umad_common.cli", *args],
            capture_output=True,
            text=True,
            env=umad_env(),
            cwd=REPO,
            timeout=300,
        )
        assert done.returncode == 0, done.stderr[-2000:]
        assert json.loads(done.stdout.strip().splitlines()[-1])["out"] == str(out)
    assert (tmp_path / "nproc1.safetensors").read_bytes() == (tmp_path / "plain.safetensors").read_bytes()
    plain_record, one, two = (
        json.loads((tmp_path / f"{name}.json").read_text()) for name in ("plain", "nproc1", "nproc2")
    )
    assert without_timing(one) == without_timing(plain_record) and "processes" not in one
    assert two["processes"] == 2 and two["threads"] == 1  # --threads 2 split over the two processes
    assert np.isfinite(two["history"][-1]["loss"]) and two["samples_per_second"] > 0


def without_timing(record: dict) -> dict:
    return {key: value for key, value in record.items() if key not in TIMING_KEYS}


def test_nproc_names_what_does_not_fit(monkeypatch):
    from umad_common.commands.train_world_model import processes_of

    for name in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "LOCAL_WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT"):
        monkeypatch.delenv(name, raising=False)
    assert processes_of(argparse.Namespace(nproc=None), 4) == 1
    assert processes_of(argparse.Namespace(nproc=2), 4) == 2
    with pytest.raises(SystemExit, match="--batch-size 3 does not split over 2 processes"):
        processes_of(argparse.Namespace(nproc=2), 3)
    with pytest.raises(SystemExit, match="--nproc 0: expected at least 1"):
        processes_of(argparse.Namespace(nproc=0), 4)
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("WORLD_SIZE", "4")
    monkeypatch.setenv("LOCAL_RANK", "1")
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    monkeypatch.setenv("MASTER_ADDR", "10.0.0.1")
    monkeypatch.setenv("MASTER_PORT", "29500")
    assert processes_of(argparse.Namespace(nproc=None), 4) == 2
    with pytest.raises(SystemExit, match="under torchrun the processes are torchrun's"):
        processes_of(argparse.Namespace(nproc=2), 4)
    with pytest.raises(SystemExit, match="--batch-size 2 does not split over 4 processes"):
        processes_of(argparse.Namespace(nproc=None), 2)

"""The in-package trainer (smdm_plugin.training.trainer, smdm train: smdm_plugin.apps.train) in one process: data, batch order, the
per-sample randomness, one step against a hand-written reference step, checkpoints that reload,
torch.compile, and the ``smdm train`` command's arguments and output folder."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from smdm_plugin.apps import train as train_cli
from smdm_plugin.io.humanml3d import load_humanml3d
from smdm_plugin.training import trainer as T
from smdm_plugin.training.data import MotionSet
from smdm_plugin.core.config import SparseConfig

TINY_MODEL = {"latent_dim": 32, "num_layers": 2, "num_heads": 4, "ff_size": 64, "dropout": 0.0}


@pytest.fixture(scope="module")
def data(hml_dir):
    return MotionSet.from_split(load_humanml3d(str(hml_dir), "train"))


# ----------------------------------------------------------------------------------------- data
def test_load_humanml3d_matches_the_files(hml_dir, data):
    mean, std = np.load(hml_dir / "Mean.npy"), np.load(hml_dir / "Std.npy")
    names = [n for n in (hml_dir / "train.txt").read_text().split()
             if len(np.load(hml_dir / "new_joint_vecs" / f"{n}.npy")) >= 40]
    assert data.ids == names and data.feature_dim == 263 and data.max_frames == 196
    x, lengths = data.padded([0, len(data) - 1])
    for row, i in enumerate([0, len(data) - 1]):
        raw = np.load(hml_dir / "new_joint_vecs" / f"{names[i]}.npy")[:196]
        assert int(lengths[row]) == len(raw)
        np.testing.assert_allclose(x[row, :len(raw)].numpy(), (raw - mean) / std, rtol=1e-6, atol=1e-6)
        assert float(x[row, len(raw):].abs().sum()) == 0.0


def test_motionset_rejects_bad_shapes():
    m = [np.zeros((10, 4), np.float32)]
    with pytest.raises(ValueError, match=r"motions must be \[L, D\] and mean \[D\]"):
        MotionSet.from_motions(m, np.zeros(3), np.ones(4))
    with pytest.raises(ValueError, match="lengths must be in"):
        MotionSet.from_motions([np.zeros((1, 4))], np.zeros(4), np.ones(4))
    with pytest.raises(FileNotFoundError, match="not a HumanML3D-format folder"):
        load_humanml3d("/nonexistent")


def test_global_batches_walk_epoch_permutations():
    n, G, seed = 10, 4, 3
    stream = torch.cat([T.global_batch_indices(s, G, n, seed) for s in range(10)])  # 40 = 4 epochs
    for e in range(4):  # each epoch is a permutation of the data set
        assert sorted(stream[e * n:(e + 1) * n].tolist()) == list(range(n))
    assert not torch.equal(stream[:n], stream[n:2 * n])  # a new order each epoch
    # the same stream whatever the batch size (a global batch of 2 runs through it too)
    small = torch.cat([T.global_batch_indices(s, 2, n, seed) for s in range(20)])
    assert torch.equal(small, stream)
    # rank slices of a global batch concatenate to it
    g = T.global_batch_indices(5, 6, n, seed)
    assert torch.equal(torch.cat([g[r * 3:(r + 1) * 3] for r in range(2)]), g)


def test_diffusion_draws_depend_on_the_global_index_only():
    dev = torch.device("cpu")
    t_all, n_all = T.diffusion_draws(0, 5, range(8, 12), 50, (3, 1, 7), dev)
    t_a, n_a = T.diffusion_draws(0, 5, range(8, 10), 50, (3, 1, 7), dev)
    t_b, n_b = T.diffusion_draws(0, 5, range(10, 12), 50, (3, 1, 7), dev)
    assert torch.equal(t_all, torch.cat([t_a, t_b])) and torch.equal(n_all, torch.cat([n_a, n_b]))
    assert t_all.min() >= 0 and t_all.max() < 50 and n_all.shape == (4, 3, 1, 7)
    _, other_step = T.diffusion_draws(0, 6, range(8, 12), 50, (3, 1, 7), dev)
    _, other_seed = T.diffusion_draws(1, 5, range(8, 12), 50, (3, 1, 7), dev)
    assert not torch.equal(n_all, other_step) and not torch.equal(n_all, other_seed)
    assert len({T.mix_seed(0, 2, s, i) for s in range(50) for i in range(50)}) == 2500


# ----------------------------------------------------------------------------------------- config
def test_train_config_validates_and_round_trips():
    with pytest.raises(ValueError, match=r"TrainConfig.batch=0: expected an int >= 1"):
        T.TrainConfig(batch=0)
    with pytest.raises(ValueError, match="TrainConfig.lr"):
        T.TrainConfig(lr=float("nan"))
    with pytest.raises(ValueError, match="unknown TinyMDM option"):
        T.TrainConfig(model={"latent": 3})
    with pytest.raises(TypeError, match="SparseConfig"):
        T.TrainConfig(sparse={"reduction": 0.5})
    cfg = T.TrainConfig(steps=3, sparse=SparseConfig(reduction=0.7, fsq=True))
    back = T.TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert back == cfg


# ----------------------------------------------------------------------------------------- one step
@pytest.mark.parametrize("sparse", [False, True], ids=["dense", "sparse"])
def test_step_equals_a_hand_written_step(data, sparse):
    """Trainer.step() against the plain loop: same weights, batch, t and noise, AdamW."""
    from smdm_plugin import SimpleDiffusion, TinyMDM, sparsify

    sc = SparseConfig(mask_noise=0.0) if sparse else None
    cfg = T.TrainConfig(steps=2, batch=3, lr=1e-3, diffusion_steps=10, seed=5, model=dict(TINY_MODEL), sparse=sc)
    tr = T.Trainer(cfg, data, device="cpu")
    torch.manual_seed(5)
    ref = TinyMDM(njoints=263, nfeats=1, cond_mode="no_cond", **TINY_MODEL)
    diffusion = SimpleDiffusion(10)
    if sparse:
        sparsify(ref, sc, diffusion=diffusion, mean=data.mean, std=data.std)
    ref.train()
    opt = torch.optim.AdamW(ref.parameters(), lr=1e-3, weight_decay=0.0)
    for step in range(2):
        idx = T.global_batch_indices(step, 3, len(data), 5)
        x, lengths = data.padded(idx)
        x = x.permute(0, 2, 1).unsqueeze(2)
        mask = (torch.arange(196) < lengths[:, None]).view(3, 1, 1, 196)
        t, noise = T.diffusion_draws(5, step, range(step * 3, step * 3 + 3), 10, (263, 1, 196), torch.device("cpu"))
        loss = diffusion.training_losses(ref, x, t, {"y": {"mask": mask, "lengths": lengths}}, noise=noise)["loss"]
        opt.zero_grad()
        loss.mean().backward()
        opt.step()
        got = tr.step()
        assert got == float(loss.mean().detach())
    for (k, a), (_, b) in zip(tr.model.state_dict().items(), ref.state_dict().items()):
        assert torch.equal(a, b), k
    assert tr.step_count == 2 and tr.losses == [pytest.approx(v) for v in tr.losses]


def test_train_result_and_progress(data, capsys):
    cfg = T.TrainConfig(steps=5, batch=2, diffusion_steps=10, model=dict(TINY_MODEL), sparse=SparseConfig())
    tr = T.Trainer(cfg, data, device="cpu")
    seen = []
    res = tr.train(steps=3, callback=lambda trainer, loss: seen.append((trainer.step_count, loss)))
    assert [s for s, _ in seen] == [1, 2, 3] and res.losses == [v for _, v in seen]
    rest = tr.train(progress=True)  # up to config.steps
    assert rest.steps == 2 and rest.total_steps == 5 and tr.losses == res.losses + rest.losses
    assert "5/5" not in capsys.readouterr().out  # the bar counts this call's steps (2)
    assert rest.world_size == 1 and rest.global_batch == 2 and rest.max_divergence == 0.0
    assert np.isfinite(rest.final_loss) and rest.best_loss <= max(rest.losses)
    d = rest.to_dict()
    assert d["steps"] == 2 and d["steps_per_s"] > 0 and d["losses"] == rest.losses


def test_compile_gives_the_eager_losses(data):
    """torch.compile traces the model with the sparse hooks (backend "eager": Dynamo only, quick;
    the inductor backend compiles the same graphs to kernels)."""
    pytest.importorskip("torch._dynamo")
    from torch._dynamo.utils import counters

    losses = {}
    counters.clear()
    for compiled in ("none", "default"):
        cfg = T.TrainConfig(steps=2, batch=2, diffusion_steps=10, model=dict(TINY_MODEL),
                            sparse=SparseConfig(mask_noise=0.0), compile=compiled, compile_backend="eager")
        losses[compiled] = T.Trainer(cfg, data, device="cpu").train().losses
    assert counters["stats"]["unique_graphs"] > 0  # Dynamo did capture graphs
    assert losses["default"] == pytest.approx(losses["none"], rel=1e-5)


# ----------------------------------------------------------------------------------------- checkpoints
@pytest.mark.parametrize("sparse", [False, True], ids=["dense", "sparse"])
def test_saved_folder_reloads(data, tmp_path, sparse):
    from smdm_plugin import load_checkpoint

    cfg = T.TrainConfig(steps=2, batch=2, diffusion_steps=10, model=dict(TINY_MODEL),
                        sparse=SparseConfig(reduction=0.7) if sparse else None)
    tr = T.Trainer(cfg, data, device="cpu")
    tr.train()
    path = tr.save(str(tmp_path))
    assert os.path.basename(path) == "model000000002.pt"
    assert (tmp_path / "sparse_config.json").exists() == sparse
    model, config = T.load_trained(str(tmp_path))
    assert (config is not None) == sparse and (not sparse or config.reduction == 0.7)
    ref = tr.model.state_dict()
    assert sorted(model.state_dict()) == sorted(ref)
    assert all(torch.equal(model.state_dict()[k], ref[k]) for k in ref)
    # the public loader too (mean/std passed by the caller)
    again, _ = load_checkpoint(path, mean=data.mean, std=data.std)
    x, lengths = data.padded([0, 1])
    x = x[:, :60].permute(0, 2, 1).unsqueeze(2)
    y = {"mask": torch.ones(2, 1, 1, 60, dtype=torch.bool), "lengths": torch.tensor([60, 60])}
    tr.model.eval(), model.eval(), again.eval()
    t = torch.tensor([3, 7])
    with torch.no_grad():
        want = tr.model(x, t, dict(y))
        assert torch.equal(model(x, t, dict(y)), want) and torch.equal(again(x, t, dict(y)), want)
    saved = json.loads((tmp_path / "train_config.json").read_text())
    assert saved["step"] == 2 and saved["world_size"] == 1 and saved["model"] == TINY_MODEL


# ----------------------------------------------------------------------------------------- CLI
def _cli(args, hml_dir, out):
    return train_cli.main(["--data", str(hml_dir), "--out", str(out), "--latent-dim", "32", "--layers", "1",
                   "--ff-size", "64", "--steps", "3", "--batch", "2", "--diffusion-steps", "10",
                   "--no-progress", *args])


def test_cli_writes_a_checkpoint_folder_and_never_overwrites(hml_dir, tmp_path, capsys):
    out = tmp_path / "run"
    assert _cli(["--sparse", "--save-every", "2"], hml_dir, out) == 0
    names = set(os.listdir(out))
    assert {"model000000002.pt", "model000000003.pt", "backbone.json", "sparse_config.json", "Mean.npy",
            "Std.npy", "train_config.json", "losses.csv", "loss.png", "result.json"} <= names
    assert not any(n.startswith(".") for n in names - {".smdm-manifest.json"})  # no temporary file left behind
    assert not any(n.startswith(".run.") for n in os.listdir(tmp_path))  # no lock or partial folder beside it
    result = json.loads((out / "result.json").read_text())
    lines = (out / "losses.csv").read_text().split()
    assert lines[0] == "step,loss" and [float(v.split(",")[1]) for v in lines[1:]] == pytest.approx(result["losses"])
    before = (out / "model000000003.pt").read_bytes()
    assert _cli([], hml_dir, out) == 2
    assert "holds a run of smdm train (interrupted or finished); pass --resume to continue it, --overwrite to " \
        "start over" in capsys.readouterr().err
    assert (out / "model000000003.pt").read_bytes() == before
    (out / "notes.txt").write_text("mine")
    assert _cli(["--overwrite", "--steps", "1"], hml_dir, out) == 0  # dense now: the old run's files go
    assert sorted(n for n in os.listdir(out) if n.startswith("model")) == ["model000000001.pt"]
    assert not (out / "sparse_config.json").exists() and (out / "notes.txt").read_text() == "mine"
    model, config = T.load_trained(str(out))
    assert config is None


@pytest.mark.parametrize("args,message", [
    (["--batch", "0"], "argument --batch: must be an integer >= 1, got 0"),
    (["--lr", "0"], "argument --lr: must be a finite number > 0, got 0"),
    (["--dropout", "1"], "argument --dropout: must be a finite number in [0, 1), got 1"),
    (["--latent-dim", "30", "--heads", "4"], "--latent-dim (30) must be a multiple of --heads (4)"),
    (["--min-frames", "50", "--max-frames", "40"], "--min-frames (50) must be <= --max-frames (40)"),
    (["--sparse", "--sparse_reduction", "1.5"], "argument --sparse_reduction: must be a finite number in [0, 1), got 1.5"),
    (["--sparse_text_encoder", "x"], "--sparse_text_encoder: not an option of smdm train"),
    (["--device", "nonsense"], "argument --device"),
    # settings that cannot apply (0.10.5 trained dense and dropped them)
    (["--sparse_reduction", "0.5"], "--sparse_reduction: applies only with --sparse (this run is dense)"),
    (["--sparse_fsq", "false"], "--sparse_fsq: applies only with --sparse"),
    (["--sparse", "--init-amplitude", "0.1"], "--init-amplitude: applies only with --init-from and --sparse"),
])
def test_cli_bad_arguments_exit_2_with_one_line(args, message, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        train_cli.main(["--data", str(tmp_path), "--out", str(tmp_path / "o"), *args])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "o").exists()


def test_cli_missing_data_exit_2(tmp_path, capsys):
    assert train_cli.main(["--data", str(tmp_path / "nope"), "--out", str(tmp_path / "o")]) == 2
    assert "not a HumanML3D-format folder" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_smdm_dispatches_train():
    from helpers.paths import ROOT as repo
    env = dict(os.environ, PYTHONPATH=str(repo) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    proc = subprocess.run([sys.executable, "-m", "smdm_plugin", "--help"], capture_output=True, text=True,
                          env=env, cwd=str(repo), timeout=120)
    assert proc.returncode == 0 and "train " in proc.stdout
    proc = subprocess.run([sys.executable, "-m", "smdm_plugin", "train", "--help"], capture_output=True,
                          text=True, env=env, cwd=str(repo), timeout=120)
    assert proc.returncode == 0 and "torchrun --nproc_per_node" in proc.stdout and "--sparse_reduction" in proc.stdout

#!/usr/bin/env python
"""Time one MDM training step, dense vs sparse (sMDM), with the real upstream model.

    SMDM_MDM_ROOT=/path/to/motion-diffusion-model python scripts/time_mdm_step.py [options]

Builds MDM with upstream's own ``create_model_and_diffusion`` (default size: 512-D, 8 layers,
trans_enc, 1000 diffusion steps) and CLIP ViT-B/32 (random weights unless
``~/.cache/clip/ViT-B-32.pt`` exists; see tests/integration/mdm_harness.py), takes a batch of real
motions (HumanML3D format, padded to 196 frames, normalised with the data set's Mean/Std), and
times ``diffusion.training_losses`` + backward + AdamW step, for the dense model and for the same
model after ``smdm_plugin.sparsify`` (default ``SparseConfig``: 80% of frames dropped, Lipschitz
MLPs). Two variants: the full MDM step (text encoded by CLIP every step, as ``train_mdm`` does)
and the denoiser only (text embedding precomputed, ``y['text_embed']``), which is where sparse
mode saves compute. Prints a JSON line with the times and the dense/sparse ratios.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(HERE)


def load_batch(data_dir: str, batch: int, frames: int):
    import numpy as np
    import torch

    mean = np.load(os.path.join(data_dir, "Mean.npy"))
    std = np.load(os.path.join(data_dir, "Std.npy"))
    ids = [l.strip() for l in open(os.path.join(data_dir, "train.txt")) if l.strip()]
    motions, lengths, texts = [], [], []
    i = 0
    while len(motions) < batch:  # cycle through the (small) train split
        mid = ids[i % len(ids)]
        i += 1
        m = np.load(os.path.join(data_dir, "new_joint_vecs", mid + ".npy"))[:frames]
        m = (m - mean) / std
        lengths.append(len(m))
        motions.append(np.concatenate([m, np.zeros((frames - len(m), m.shape[1]), m.dtype)]))
        with open(os.path.join(data_dir, "texts", mid + ".txt")) as f:
            texts.append(f.readline().split("#")[0])
    x = torch.tensor(np.stack(motions), dtype=torch.float32).permute(0, 2, 1).unsqueeze(2)  # [B,263,1,N]
    lengths = torch.tensor(lengths)
    mask = (torch.arange(frames)[None] < lengths[:, None]).view(batch, 1, 1, frames)
    return x, {"mask": mask, "lengths": lengths, "text": texts}, mean, std


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--root", default=os.environ.get("SMDM_MDM_ROOT"), help="MDM checkout (SMDM_MDM_ROOT)")
    p.add_argument("--data", default=None, help="HumanML3D-format data (default: cmu-humanml3d)")
    p.add_argument("--batch_size", type=int, default=64)
    p.add_argument("--frames", type=int, default=196)
    p.add_argument("--latent_dim", type=int, default=512)
    p.add_argument("--layers", type=int, default=8)
    p.add_argument("--arch", default="trans_enc", choices=["trans_enc", "trans_dec"])
    p.add_argument("--steps", type=int, default=3, help="timed steps per variant (after 1 warm-up)")
    p.add_argument("--reduction", type=float, default=0.8)
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    p.add_argument("--no_text_encoder_variant", action="store_true",
                   help="only time the denoiser variant (text embedding precomputed)")
    a = p.parse_args()
    if not a.root or not os.path.isfile(os.path.join(a.root, "model", "mdm.py")):
        p.error("set SMDM_MDM_ROOT (or --root) to an MDM checkout")
    sys.path.insert(0, os.path.join(REPO, "tests", "integration"))
    sys.path.insert(0, REPO)
    if a.data is None:
        from _upstream import find_humanml3d

        a.data = find_humanml3d()
    root = os.path.abspath(a.root)
    os.chdir(root)
    sys.path.insert(0, root)

    import torch
    import mdm_harness

    if a.threads:
        torch.set_num_threads(a.threads)
    mdm_harness.install_clip_stub()
    mdm_harness.install_smpl_stub()
    from utils import parser_util
    from utils.model_util import create_model_and_diffusion
    from smdm_plugin import SparseConfig, sparsify

    x, y, mean, std = load_batch(a.data, a.batch_size, a.frames)

    class _Data:
        class dataset:  # noqa: N801 - what get_model_args reads
            pass

    ap = argparse.ArgumentParser()
    for add in (parser_util.add_base_options, parser_util.add_data_options,
                parser_util.add_model_options, parser_util.add_diffusion_options):
        add(ap)
    args = parser_util.apply_rules(ap.parse_args(
        ["--dataset", "humanml", "--latent_dim", str(a.latent_dim), "--layers", str(a.layers),
         "--arch", a.arch]))

    def build(sparse: bool):
        torch.manual_seed(0)
        model, diffusion = create_model_and_diffusion(args, _Data)
        if sparse:
            sparsify(model, SparseConfig(reduction=a.reduction), diffusion=diffusion, mean=mean, std=std)
        model.train()
        opt = torch.optim.AdamW([q for q in model.parameters() if q.requires_grad], lr=1e-4)
        return model, diffusion, opt

    def time_steps(model, diffusion, opt, precomputed_text: bool) -> float:
        yy = dict(y)
        if precomputed_text:
            with torch.no_grad():
                yy["text_embed"] = model.encode_text(y["text"])
        g = torch.Generator().manual_seed(0)
        times = []
        for i in range(a.steps + 1):
            t = torch.randint(0, diffusion.num_timesteps, (a.batch_size,), generator=g)
            start = time.perf_counter()
            opt.zero_grad(set_to_none=True)
            losses = diffusion.training_losses(model, x, t, model_kwargs={"y": dict(yy)})
            losses["loss"].mean().backward()
            opt.step()
            if i > 0:  # first step is warm-up
                times.append(time.perf_counter() - start)
        return sum(times) / len(times)

    result = {"batch_size": a.batch_size, "frames": a.frames, "latent_dim": a.latent_dim,
              "layers": a.layers, "arch": a.arch, "reduction": a.reduction,
              "threads": torch.get_num_threads(), "steps": a.steps, "torch": torch.__version__}
    variants = [("denoiser", True)] + ([] if a.no_text_encoder_variant else [("full_step", False)])
    for name, pre in variants:
        for mode in ("dense", "sparse"):
            model, diffusion, opt = build(mode == "sparse")
            sec = time_steps(model, diffusion, opt, pre)
            result[f"{name}_{mode}_s"] = round(sec, 3)
            print(f"{name:9s} {mode:6s}: {sec:.3f} s/step", file=sys.stderr, flush=True)
            del model, diffusion, opt
        result[f"{name}_dense_over_sparse"] = round(result[f"{name}_dense_s"] / result[f"{name}_sparse_s"], 3)
    print(json.dumps(result))


if __name__ == "__main__":
    main()

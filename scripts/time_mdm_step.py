#!/usr/bin/env python
"""Time one MDM training step, dense vs sparse (sMDM), with the real upstream model.

    SMDM_MDM_ROOT=/path/to/motion-diffusion-model python scripts/time_mdm_step.py [options]

Builds MDM with upstream's own ``create_model_and_diffusion`` (default size: 512-D, 8 layers,
trans_enc, 1000 diffusion steps) and CLIP ViT-B/32 (random weights unless
``~/.cache/clip/ViT-B-32.pt`` exists; see tests/integration/mdm_harness.py), takes a batch of real
motions (HumanML3D format, padded to 196 frames, normalised with the data set's Mean/Std), and
times ``diffusion.training_losses`` + backward + AdamW step, for the dense model and for the same
model after ``smdm_plugin.sparsify`` (default ``SparseConfig``: 80% of frames dropped, Lipschitz
MLPs). Three variants:

* ``denoiser``: the text embedding precomputed (``y['text_embed']``), i.e. the part sparse mode
  makes cheaper;
* ``full_step``: the MDM step as ``train_mdm`` runs it, CLIP encoding the captions every step;
* ``full_step_cache``: the same with the opt-in text-embedding cache
  (``smdm_plugin.adapters.text_cache``, what ``SMDM_TEXT_CACHE=on`` installs), warm: the warm-up
  step fills it, so the timed steps are the steady state once every caption of the data set has
  been seen (the default capacity holds all of HumanML3D's captions).

The variants and the dense/sparse models are timed in interleaved rounds (one step of each per
round, after a warm-up round) so that load changes on a shared machine affect all alike; medians.
Prints a JSON line with the times and the dense/sparse ratios. CLIP has random weights (the
architecture of ViT-B/32's text tower, 12 layers) unless the real weights are cached: the timing
does not depend on the values. Upstream converts CLIP to float16 (``load_and_freeze_clip``), which
is slow on a CPU; ``--clip_fp32`` keeps it in float32 (what a CPU user would do).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from dataclasses import dataclass
from typing import Any, Dict, List

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
    p.add_argument("--steps", type=int, default=3,
                   help="timed rounds (after 1 warm-up round); each round times every variant and mode once")
    p.add_argument("--reduction", type=float, default=0.8)
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch default)")
    p.add_argument("--no_text_encoder_variant", action="store_true",
                   help="only time the denoiser variant (text embedding precomputed)")
    p.add_argument("--clip_fp32", action="store_true",
                   help="keep CLIP in float32 (upstream's load_and_freeze_clip converts it to float16, "
                        "which is slow on a CPU); the default times upstream's step as it is")
    p.add_argument("--variants", nargs="+", default=["denoiser", "full_step", "full_step_cache"],
                   choices=["denoiser", "full_step", "full_step_cache"], help="what to time")
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
    if a.clip_fp32:
        import clip.model

        clip.model.convert_weights = lambda model: None
    from utils import parser_util
    from utils.model_util import create_model_and_diffusion
    from smdm_plugin import SparseConfig, sparsify
    from smdm_plugin.adapters.text_cache import install_text_cache, remove_text_cache

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
        upstream_encode = model.encode_text
        cached = install_text_cache(model)  # what SMDM_TEXT_CACHE=on installs...
        remove_text_cache(model)  # ...switched on only for the full_step_cache variant
        with torch.no_grad():
            text_embed = upstream_encode(y["text"])
        return Setup(model, diffusion, opt, upstream_encode, cached, text_embed)

    setups = {mode: build(mode == "sparse") for mode in ("dense", "sparse")}
    names = ["denoiser"] if a.no_text_encoder_variant else a.variants
    g = torch.Generator().manual_seed(0)

    def one_step(su: "Setup", name: str) -> float:
        yy = dict(y)
        su.model.encode_text = su.cached if name == "full_step_cache" else su.upstream_encode
        if name == "denoiser":
            yy["text_embed"] = su.text_embed
        t = torch.randint(0, su.diffusion.num_timesteps, (a.batch_size,), generator=g)
        start = time.perf_counter()
        su.opt.zero_grad(set_to_none=True)
        losses = su.diffusion.training_losses(su.model, x, t, model_kwargs={"y": yy})
        losses["loss"].mean().backward()
        su.opt.step()
        return time.perf_counter() - start

    # Interleaved rounds (every variant and mode once per round) so that a change of machine load
    # hits all of them alike; round 0 is the warm-up (and fills the cache). Medians are reported.
    times: Dict[tuple, List[float]] = {(n, m): [] for n in names for m in setups}
    load = [os.getloadavg()[0]]
    for r in range(a.steps + 1):
        for name in names:
            for mode, su in setups.items():
                sec = one_step(su, name)
                if r > 0:
                    times[(name, mode)].append(sec)
                print(f"round {r} {name:15s} {mode:6s}: {sec:.3f} s", file=sys.stderr, flush=True)
    load.append(os.getloadavg()[0])
    result = {"batch_size": a.batch_size, "frames": a.frames, "latent_dim": a.latent_dim,
              "layers": a.layers, "arch": a.arch, "reduction": a.reduction,
              "threads": torch.get_num_threads(), "steps": a.steps, "torch": torch.__version__,
              "clip_text_layers": len(setups["dense"].model.clip_model.transformer.resblocks),
              "clip_dtype": str(setups["dense"].model.clip_model.text_projection.dtype),  # (convert_weights)
              "loadavg_1min_start_end": [round(v, 2) for v in load]}
    for name in names:
        for mode, su in setups.items():
            result[f"{name}_{mode}_s"] = round(statistics.median(times[(name, mode)]), 3)
        result[f"{name}_dense_over_sparse"] = round(result[f"{name}_dense_s"] / result[f"{name}_sparse_s"], 3)
    for mode, su in setups.items():
        result[f"cache_{mode}_hit_rate"] = round(su.cached.cache.stats()["hit_rate"], 3)
    print(json.dumps(result))


@dataclass
class Setup:
    """One model (dense or sparse) with its diffusion, optimiser, upstream ``encode_text``, the
    cached wrapper of it, and the precomputed text embedding of the batch."""

    model: Any
    diffusion: Any
    opt: Any
    upstream_encode: Any
    cached: Any
    text_embed: Any


if __name__ == "__main__":
    main()

"""The work in the graphs ``--compile`` captures, dense against sparse, counted on a CPU.

    python scripts/graph_work.py [--variants trans_enc trans_dec dip motiondiffuse] [--precisions fp32 bf16]
                                 [--calls sample train] [--quick]

Each variant at MDM's size (``--quick``: the tiny one), batch 4, 60 frames, built as ``smdm bench``
builds it, compiled as ``smdm bench --compile default`` compiles it, but traced to AOTAutograd's graphs
only (no code generation): the guided sampling call (both guidance passes) and the training step's
loss (forward and backward graphs). Counted per graph, views and item access left out: ``ops`` (an
upper bound on a GPU's kernels: inductor fuses pointwise ops), ``matmuls`` (mm, bmm, addmm,
baddbmm, SDPA: one library launch each on a GPU, never fused) and, for a sampling call, ``param-only``:
the ops whose inputs come from parameters, buffers and product stores alone (a call redoes them).
Two things the CPU counts apart from a GPU: sparse attention (8-channel queries and keys,
128-channel values) is the CPU's math SDPA (2 bmm forward, 4 backward, plus softmax ops) where a GPU
runs one kernel; dense MDM's fp32 evaluation layers run PyTorch's fused encoder-layer op, one node
for several kernels. Compare dense and sparse by matmuls and param-only ops, not by ops.
"""
from __future__ import annotations

import argparse
import sys
import warnings
from typing import Dict, List, Optional

import torch

from smdm_plugin.training import workloads
from smdm_plugin.training.benchmark import guided_call, training_loss
from smdm_plugin.training.graphwork import aot_counter

VARIANTS = {"trans_enc": "mdm", "trans_dec": "mdm", "dip": "mdm", "motiondiffuse": "motiondiffuse"}
B, N = 4, 60


def graphs_of(variant: str, sparse: bool, precision: str, call: str, quick: bool) -> List[Dict[str, int]]:
    """The counts of every AOT graph one compiled call of ``variant`` traces (sampling: one forward
    graph; training: forward and backward)."""
    family = VARIANTS[variant]
    torch._dynamo.reset()
    torch.manual_seed(0)
    model, diffusion = workloads.build(variant, 0.8 if sparse else None, torch.device("cpu"), quick, 50,
                                       family=family, frames=N)
    work = workloads.WORKLOADS.get(family)
    data = work.batch(B, N, torch.device("cpu"), quick, variant)
    backend, found = aot_counter(model, with_fixed=call == "sample")
    bf16 = precision == "bf16"
    t = torch.full((B,), 3, dtype=torch.long)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if call == "sample":
            model.eval()
            fn = guided_call(work, model, torch.device("cpu"), "default", backend)
            with torch.no_grad(), torch.autocast("cpu", torch.bfloat16, enabled=bf16):
                for _ in range(2):                       # the first call runs eagerly, the second traces
                    fn(data.x, t, **work.sample_kwargs(data))
        else:
            model.train()
            workloads.without_dropout(model)
            fn = training_loss(work, model, diffusion, torch.device("cpu"), "default", backend)
            noise = torch.randn(data.x.shape, generator=torch.Generator().manual_seed(0))
            for _ in range(2):
                with torch.autocast("cpu", torch.bfloat16, enabled=bf16):
                    loss = fn(data.x, t, work.kwargs(data), noise)
                loss.backward()
    return found


def _total(graphs: List[Dict[str, int]]) -> Dict[str, int]:
    out: Dict[str, int] = {}
    for g in graphs:
        for k, v in g.items():
            out[k] = out.get(k, 0) + v
    return out


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--variants", nargs="+", choices=sorted(VARIANTS), default=list(VARIANTS))
    p.add_argument("--precisions", nargs="+", choices=["fp32", "bf16"], default=["fp32", "bf16"])
    p.add_argument("--calls", nargs="+", choices=["sample", "train"], default=["sample", "train"])
    p.add_argument("--quick", action="store_true", help="the tiny model size (smoke runs)")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    size = "tiny" if a.quick else "MDM's (latent 512, 8 layers)"
    print(f"AOT graph work per compiled call (size {size}, batch {B}, {N} frames; torch {torch.__version__})\n")
    print("| variant | precision | call | dense ops | dense matmuls | dense param-only | sparse ops | "
          "sparse matmuls | sparse param-only |")
    print("| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: |")
    for variant in a.variants:
        for precision in a.precisions:
            for call in a.calls:
                d = _total(graphs_of(variant, False, precision, call, a.quick))
                s = _total(graphs_of(variant, True, precision, call, a.quick))
                cells = [str(c.get(k, "—")) for c in (d, s) for k in ("ops", "matmuls", "param-only")]
                print(f"| {variant} | {precision} | {call} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

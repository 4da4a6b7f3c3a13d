"""Host time per call on this CPU, dense against sparse: the table of docs/gpu.md ("Host time").

    python scripts/host_time.py [--variants trans_enc trans_dec dip doubletake motiondiffuse] [--repeats 100]
                                [--triton NAME ...] [--no-triton NAME ...]

Each variant at MDM's depth and heads on tiny tensors, the static (GPU) code path; what CUDA runs
as one kernel charged one launch (SDPA forward and backward, dropout, foreach ops), fused ops that
CUDA runs as Triton kernels TRITON_LAUNCH_OPS (smdm_plugin/training/hosttime.py); one thread. ``--triton`` / ``--no-triton`` switch Triton
kernels (by name: smdm_plugin.core.kernels.dispatch.TRITON_KERNELS) on or off for the run, as
``use_triton_kernels`` does (``--triton "FSQ code" "FSQ code gradient"``: 0.9.1's routing).
Prints a markdown table: host ms per call and sparse / dense, and the counted host work (aten ops,
Python frames: ``host_work``, the same on any machine) sparse / dense.
"""
from __future__ import annotations

import argparse
import sys
from typing import List, Optional

import torch

from smdm_plugin.core.checks import static_mode
from smdm_plugin.core.kernels.dispatch import TRITON_KERNELS, use_triton_kernels
from smdm_plugin.training.hosttime import HOST_SIZE, HOST_VARIANTS, host_cells, host_times, host_work


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--variants", nargs="+", choices=HOST_VARIANTS, default=list(HOST_VARIANTS))
    p.add_argument("--repeats", type=int, default=100, help="interleaved repeats per cell (default 100)")
    p.add_argument("--triton", nargs="+", default=[], choices=sorted(TRITON_KERNELS), metavar="NAME",
                   help="Triton kernels to switch on for the run (names: " + ", ".join(sorted(TRITON_KERNELS)) + ")")
    p.add_argument("--no-triton", nargs="+", default=[], choices=sorted(TRITON_KERNELS), metavar="NAME",
                   help="Triton kernels to switch off for the run")
    a = p.parse_args(argv)
    if a.repeats < 1:
        p.error(f"argument --repeats: must be >= 1, got {a.repeats}")
    if set(a.triton) & set(a.no_triton):
        p.error(f"arguments --triton/--no-triton: a kernel named in both: {sorted(set(a.triton) & set(a.no_triton))}")
    use_triton_kernels(True, a.triton)
    use_triton_kernels(False, a.no_triton)
    on = sorted(n for n, k in TRITON_KERNELS.items() if k.enabled)
    torch.set_num_threads(1)
    print(f"host time per call (ms, thread CPU time; size {HOST_SIZE}; torch {torch.__version__}; "
          f"Triton kernels on: {', '.join(on) or 'none'})\n")
    print("| variant | precision | call | dense ms | sparse ms | sparse / dense | ops sparse / dense | "
          "frames sparse / dense |")
    print("| --- | --- | --- | ---: | ---: | ---: | ---: | ---: |")
    for variant in a.variants:
        for precision in ("fp32", "bf16"):
            with static_mode():
                dense, sparse = host_cells(variant, False, precision), host_cells(variant, True, precision)
                for call in ("train", "sample"):
                    r = host_times({"dense": dense[call], "sparse": sparse[call]}, repeats=a.repeats)
                    w = host_work(sparse[call]).ratio(host_work(dense[call]))
                    print(f"| {variant} | {precision} | {call} | {r.ms['dense']:.2f} | {r.ms['sparse']:.2f} | "
                          f"{r.ratio('sparse', 'dense'):.2f} | {w['ops']:.2f} | {w['calls']:.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

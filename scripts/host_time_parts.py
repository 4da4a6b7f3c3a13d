"""What the sparse trans_enc's host time is made of: the meter's cells with the paper's recipe, without
FSQ keys, without Lipschitz layers, without either (docs/gpu.md, "Host time"); ``--optimizer``: a
training step and its optimizer step alone, dense and sparse, Python frames and time (docs/gpu.md,
"0.10.5")."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from smdm_plugin.core.config import SparseConfig  # noqa: E402
from smdm_plugin.core.checks import static_mode  # noqa: E402
from smdm_plugin.training import hosttime  # noqa: E402

PARTS = {"the recipe": {}, "no FSQ keys": {"fsq": False}, "no Lipschitz layers": {"lipschitz": False},
         "neither": {"fsq": False, "lipschitz": False}}


def optimizer_rows(variant: str, repeats: int) -> None:
    """fp32: the training step and its optimizer step (``AdamW(foreach=True)``, as upstream builds it)
    alone, dense and sparse: Python frames (``host_work``) and milliseconds (the meter)."""
    print(f"{variant} fp32: the optimizer's share of a training step (torch {torch.__version__})\n")
    print("| call | dense frames | sparse frames | dense ms | sparse ms |")
    print("| --- | ---: | ---: | ---: | ---: |")
    with static_mode():
        cells = {side: hosttime.host_cells(variant, side == "sparse", "fp32") for side in ("dense", "sparse")}
        for c in cells.values():
            c["train"]()                                      # the gradients the optimizer step reads
        for call, name in (("train", "training step"), ("step", "its optimizer step")):
            fns = {side: c[call] for side, c in cells.items()}
            frames = {side: hosttime.host_work(fn).calls for side, fn in fns.items()}
            ms = hosttime.host_times(fns, repeats=repeats).ms
            print(f"| {name} | {frames['dense']} | {frames['sparse']} | {ms['dense']:.2f} | {ms['sparse']:.2f} |")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--variant", default="trans_enc", choices=hosttime.HOST_VARIANTS)
    p.add_argument("--repeats", type=int, default=60)
    p.add_argument("--optimizer", action="store_true", help="the optimizer's share of a training step instead")
    args = p.parse_args()
    torch.set_num_threads(1)
    if args.optimizer:
        optimizer_rows(args.variant, args.repeats)
        return 0
    if args.variant not in hosttime.HOST_VARIANTS[:3]:
        p.error(f"argument --variant: the parts apply to {', '.join(hosttime.HOST_VARIANTS[:3])}; "
                f"got {args.variant!r} (--optimizer takes every variant)")
    print(f"{args.variant}: sparse / dense host time (the meter, torch {torch.__version__})\n")
    print("| sparse | fp32 train | fp32 sample | bf16 train | bf16 sample |")
    print("| --- | ---: | ---: | ---: | ---: |")
    rows = {name: [] for name in PARTS}
    for precision in ("fp32", "bf16"):
        ms = {}
        for call in ("train", "sample"):   # apart: a training step between sampling calls would refold FSQ
            with static_mode():
                fns = {f"dense.{call}": hosttime.host_cells(args.variant, False, precision)[call]}
                for name, changes in PARTS.items():
                    config = SparseConfig(**changes)
                    fns[f"{name}.{call}"] = hosttime.host_cells(args.variant, True, precision, config)[call]
                ms.update(hosttime.host_times(fns, repeats=args.repeats).ms)
        for name in PARTS:
            rows[name] += [ms[f"{name}.{k}"] / ms[f"dense.{k}"] for k in ("train", "sample")]
    for name, r in rows.items():
        print(f"| {name} | " + " | ".join(f"{v:.2f}" for v in r) + " |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""What the sparse trans_enc's host time is made of: the meter's cells with the paper's recipe, without
FSQ keys, without Lipschitz layers, without either (docs/gpu.md, "Host time")."""
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


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--variant", default="trans_enc", choices=hosttime.HOST_VARIANTS[:3])
    p.add_argument("--repeats", type=int, default=60)
    args = p.parse_args()
    torch.set_num_threads(1)
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

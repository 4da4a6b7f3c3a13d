#!/usr/bin/env python
"""Compile every Triton kernel of smdm-plugin ahead of time for sm_90 (H100/H200) without a GPU:
Triton's real code generation and ptxas; prints each kernel's registers and spills. Needs
``triton`` (the ``[gpu]`` extra); no GPU. Run: ``python scripts/check_kernels_sm90.py``."""
import os
import subprocess
import tempfile

import triton
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource

from smdm_plugin.core.kernels import (fsq_triton, lipschitz_triton, perturb_triton, plan_triton, vw_perturb_triton,
                                     vw_triton)

CUOBJDUMP = os.path.join(os.path.dirname(triton.__file__), "backends/nvidia/bin/cuobjdump")
CUBIN = os.path.join(tempfile.mkdtemp(prefix="smdm_sm90_"), "k.cubin")


def resources(fn, signature: dict, constexprs: dict, warps: int = 4) -> str:
    src = ASTSource(fn=fn, signature={**signature, **{k: "constexpr" for k in constexprs}}, constexprs=constexprs)
    k = triton.compile(src, target=GPUTarget("cuda", 90, 32), options={"num_warps": warps, "enable_fp_fusion": False})
    with open(CUBIN, "wb") as f:
        f.write(k.asm["cubin"])
    out = subprocess.run([CUOBJDUMP, "--dump-resource-usage", CUBIN], capture_output=True, text=True).stdout
    return [line.strip() for line in out.splitlines() if "REG" in line][0].split(" CONSTANT")[0]


def main() -> None:
    i32, f32 = "i32", "fp32"
    for dt in ("fp32", "bf16"):
        print(f"fsq_code ({dt}):", resources(fsq_triton._code_kernel, {"Z": f"*{dt}", "NEG": "*fp32", "HALF": "*fp32",
              "OUT": f"*{dt}", "n": i32, "C": i32, "zs": i32}, {"BLOCK": fsq_triton.BLOCK}))
        print(f"fsq_code_backward ({dt}):", resources(fsq_triton._grad_kernel, {"G": f"*{dt}", "Z": f"*{dt}",
              "HALF": "*fp32", "OUT": f"*{dt}", "n": i32, "C": i32, "gs": i32, "zs": i32}, {"BLOCK": fsq_triton.BLOCK}))
    for ncols in (263, 512):
        block = lipschitz_triton._block(ncols)
        print(f"lipschitz_weight (in {ncols}):", resources(lipschitz_triton._weight_kernel, {"W": "*fp32", "C": "*fp32",
              "OUT": "*fp32", "ncols": i32, "ws": i32}, {"BLOCK": block}))
        print(f"lipschitz_weight_backward (in {ncols}):", resources(lipschitz_triton._grad_kernel, {"G": "*fp32",
              "W": "*fp32", "C": "*fp32", "DW": "*fp32", "ROWS": "*fp32", "ncols": i32, "gs": i32, "ws": i32, "eps": f32},
              {"BLOCK": block}))
    for N in (60, 196, 1024):
        print(f"keyframe_plan (N {N}):", resources(plan_triton._plan_kernel, {"MASK": "*i1", "INDEX": "*i64",
              "VALID": "*i1", "COUNT": "*i64", "SLOTS": "*i64", "WEIGHT": "*fp32", "ROWS": "*i64", "BIAS": "*fp32",
              "B": i32, "N": i32, "K": i32, "ms": i32}, {"BLOCK": triton.next_power_of_2(N)}))
        for prot in (False, True):
            print(f"perturb_mask (N {N}, protected {prot}):", resources(perturb_triton._perturb_kernel, {"MASK": "*i1",
                  "LEN": "*i64", "U": "*fp32", "PROT": "*i1", "OUT": "*i1", "N": i32, "amount": f32},
                  {"HAS_PROT": prot, "BLOCK_N": triton.next_power_of_2(N),
                   "BLOCK_J": max(1, min(triton.next_power_of_2(N), 4096 // triton.next_power_of_2(N)))}))
    vw_sig = {"X": "*fp32", "KEYBUF": "*fp64", "LEN": "*i64", "KEEP": "*i64", "FORCED": "*u8", "ACTIVE": "*u8",
              "OUT": "*i8", "N": i32, "F": i32, "sxb": i32, "sxn": i32, "sxf": i32}
    for (N, F) in ((196, 64), (60, 64), (196, 264), (1024, 64)):
        bn, bf, rows, warps = vw_triton.launch_config(N, F)
        for hf in (False, True):
            for ha in (False, True):
                print(f"vw_keyframes (N {N}, F {F}, blocks ({bn}, {bf}), rows {rows}, warps {warps}, forced {hf}, "
                      f"active {ha}):", resources(vw_triton._vw_kernel, vw_sig, {"HAS_FORCED": hf, "HAS_ACTIVE": ha,
                                                                                 "BLOCK_N": bn, "BLOCK_F": bf, "ROWS": rows}, warps))
        fused_sig = {"X": "*fp32", "KEYBUF": "*fp64", "LEN": "*i64", "KEEP": "*i64", "FORCED": "*u8", "U": "*fp32",
                     "OUT": "*i8", "PMASK": "*i8", "INDEX": "*i64", "VALID": "*i1", "COUNT": "*i64", "SLOTS": "*i64",
                     "WEIGHT": "*fp32", "ROWS": "*i64", "BIAS": "*fp32", "B": i32, "N": i32, "F": i32, "sxb": i32,
                     "sxn": i32, "sxf": i32, "amount": f32, "P": i32, "K": i32}
        block_j = vw_perturb_triton.rank_block(bn, warps)
        for hf, plan in ((False, False), (True, False), (False, True)):
            print(f"vw_perturb (N {N}, F {F}, blocks ({bn}, {bf}, {block_j}), warps {warps}, forced {hf}, plan {plan}):",
                  resources(vw_perturb_triton._vw_perturb_kernel, fused_sig, {
                      "HAS_FORCED": hf, "BLOCK_N": bn, "BLOCK_F": bf, "KEY_ROWS": rows, "BLOCK_J": block_j, "PLAN": plan,
                      "BLOCK_P": triton.next_power_of_2(N + 20) if plan else 1}, warps))

if __name__ == "__main__":
    main()

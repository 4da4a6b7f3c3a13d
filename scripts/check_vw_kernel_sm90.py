#!/usr/bin/env python
"""Compile the VW kernel ahead of time for sm_90 (H100/H200) without a GPU: real codegen, ptxas,
resource usage."""
import os, subprocess, tempfile, triton
from triton.compiler import ASTSource
from triton.backends.compiler import GPUTarget
from smdm_plugin.core.kernels.vw_triton import _vw_kernel, launch_config
sig = {"X": "*fp32", "KEYBUF": "*fp64", "LEN": "*i64", "KEEP": "*i64", "FORCED": "*u8", "ACTIVE": "*u8", "OUT": "*i8",
       "N": "i32", "F": "i32", "sxb": "i32", "sxn": "i32", "sxf": "i32",
       "HAS_FORCED": "constexpr", "HAS_ACTIVE": "constexpr", "BLOCK_N": "constexpr", "BLOCK_F": "constexpr", "ROWS": "constexpr"}
cuobj = os.path.join(os.path.dirname(triton.__file__), "backends/nvidia/bin/cuobjdump")
cubin = os.path.join(tempfile.mkdtemp(prefix="vw_sm90_"), "k.cubin")
for (N, F) in ((196, 64), (60, 64), (196, 264), (1024, 64)):
    bn, bf, rows, warps = launch_config(N, F)
    for hf in (False, True):
        for ha in (False, True):
            src = ASTSource(fn=_vw_kernel, signature=sig, constexprs={"HAS_FORCED": hf, "HAS_ACTIVE": ha, "BLOCK_N": bn, "BLOCK_F": bf, "ROWS": rows})
            k = triton.compile(src, target=GPUTarget("cuda", 90, 32), options={"num_warps": warps, "enable_fp_fusion": False})
            open(cubin, "wb").write(k.asm["cubin"])
            out = subprocess.run([cuobj, "--dump-resource-usage", cubin], capture_output=True, text=True).stdout
            res = [l.strip() for l in out.splitlines() if "REG" in l][0]
            print(f"N={N} F={F} blocks=({bn},{bf}) rows={rows} warps={warps} forced={hf} active={ha}: {res.split(' CONSTANT')[0]}")

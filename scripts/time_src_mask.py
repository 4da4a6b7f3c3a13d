"""Host time of MotionDiffuse's padding mask, upstream's against the flag's (docs/modules.md).

    python scripts/time_src_mask.py --repo PATH/TO/MotionDiffuse [--batch 32] [--frames 196] [--repeats 20]

Upstream's ``MotionTransformer.generate_src_mask`` is read from the checkout's
``text2motion/models/transformer.py`` (that function alone, so nothing else of the checkout needs to
import); lengths drawn uniformly in 40..frames (seed 0), on the CPU, one thread; thread CPU time,
the 20th percentile of the repeats. Prints one markdown table; both masks are checked equal.
"""
from __future__ import annotations

import argparse
import ast
import os
import sys
import time
from typing import Callable, List, Optional

import torch

from smdm_plugin.families.motiondiffuse.upstream_loop import src_mask


def upstream_mask(repo: str) -> Callable:
    """``generate_src_mask`` of the checkout's ``MotionTransformer``, as a plain function."""
    path = os.path.join(repo, "text2motion", "models", "transformer.py")
    if not os.path.isfile(path):
        raise ValueError(f"argument --repo: no text2motion/models/transformer.py under {repo}")
    tree = ast.parse(open(path).read())
    for cls in (n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "MotionTransformer"):
        for fn in (n for n in cls.body if isinstance(n, ast.FunctionDef) and n.name == "generate_src_mask"):
            scope: dict = {"torch": torch}
            exec(compile(ast.Module(body=[fn], type_ignores=[]), path, "exec"), scope)
            return lambda T, length: scope["generate_src_mask"](None, T, length)
    raise ValueError(f"argument --repo: no MotionTransformer.generate_src_mask in {path}")


def ms(fn: Callable, repeats: int) -> float:
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.thread_time()
        fn()
        ts.append(time.thread_time() - t0)
    return sorted(ts)[len(ts) // 5] * 1e3


def main(argv: Optional[List[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repo", required=True, help="a MotionDiffuse checkout")
    p.add_argument("--batch", type=int, default=32, help="MotionDiffuse's default batch (32)")
    p.add_argument("--frames", type=int, default=196)
    p.add_argument("--repeats", type=int, default=20)
    a = p.parse_args(argv)
    if a.batch < 1 or a.frames < 40 or a.repeats < 1:
        p.error("arguments --batch/--frames/--repeats: need batch >= 1, frames >= 40, repeats >= 1")
    torch.set_num_threads(1)
    try:
        up = upstream_mask(a.repo)
    except ValueError as e:
        p.error(str(e))
    lengths = torch.randint(40, a.frames + 1, (a.batch,), generator=torch.Generator().manual_seed(0))
    if not torch.equal(up(a.frames, lengths), src_mask(a.frames, lengths)):
        print("the flag's src_mask differs from the checkout's generate_src_mask", file=sys.stderr)
        return 1
    writes = int((a.frames - lengths).sum())
    t_up, t_new = ms(lambda: up(a.frames, lengths), a.repeats), ms(lambda: src_mask(a.frames, lengths), a.repeats)
    print(f"padding mask, B = {a.batch}, T = {a.frames}, lengths 40..{a.frames} ({writes} padded frames); "
          f"torch {torch.__version__}, CPU, one thread\n")
    print("| mask | host ms per call |\n| --- | ---: |")
    print(f"| upstream's `generate_src_mask` | {t_up:.2f} |\n| the flag's `src_mask` | {t_new:.3f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The padding mask MotionDiffuse's ``MotionTransformer.generate_src_mask`` makes, written here from
its definition (1.0 before each sample's length, 0.0 from it on; ``[B, T]`` float32 on the CPU), one
element at a time: the slow reference of ``families/motiondiffuse/upstream_loop.src_mask`` (CI has no
MotionDiffuse checkout); and a stand-in ``models/transformer.py`` carrying it as that method, which
``scripts/time_src_mask.py`` reads as it reads a checkout's."""
import inspect
import textwrap

import torch


def generate_src_mask(self, T, length):
    rows = [[1.0 if frame < int(n) else 0.0 for frame in range(T)] for n in length]
    return torch.tensor(rows, dtype=torch.float32).reshape(len(rows), T)


def stand_in_module(owner: str = "MotionTransformer") -> str:
    """A stand-in ``text2motion/models/transformer.py``: a class named ``owner`` (the name the script
    looks up) holding :func:`generate_src_mask` as its method; nothing else of upstream's file."""
    method = textwrap.indent(inspect.getsource(generate_src_mask), " " * 4)
    return f"class {owner}:\n{method}"


#: the stand-in with the method on the class the script reads
TRANSFORMER_SOURCE = stand_in_module()

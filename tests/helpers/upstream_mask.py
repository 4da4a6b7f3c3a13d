"""MotionDiffuse's ``MotionTransformer.generate_src_mask`` as upstream writes it: the slow reference
of ``families/motiondiffuse/upstream_loop.src_mask`` (CI has no MotionDiffuse checkout), and the
source of a checkout's ``models/transformer.py`` as far as ``scripts/time_src_mask.py`` reads it."""
import inspect
import textwrap

import torch


def generate_src_mask(self, T, length):
    B = len(length)
    src_mask = torch.ones(B, T)
    for i in range(B):
        for j in range(length[i], T):
            src_mask[i, j] = 0
    return src_mask


#: ``text2motion/models/transformer.py`` with that method on ``MotionTransformer``
TRANSFORMER_SOURCE = ("import torch.nn as nn\n\n\nclass MotionTransformer(nn.Module):\n"
                      + textwrap.indent(inspect.getsource(generate_src_mask), "    "))

"""The work in a compiled call's AOTAutograd graphs, counted (``scripts/graph_work.py``, the capture
tests): ``ops`` (compute nodes: views and item access left out; an upper bound on a GPU's kernels,
inductor fuses pointwise ops), ``matmuls`` (one library launch each on a GPU, never fused) and
``param-only``: the ops whose every input comes from the model's parameters, buffers, product stores
and weight casts alone — work a call redoes that could be done once."""
from __future__ import annotations

from typing import Callable, Dict, List, Optional, Sequence, Set

import torch
from torch import nn

__all__ = ["VIEWS", "MATMULS", "count", "fixed_ids", "aot_counter"]

#: aten ops that compute nothing (views, aliases, copies of layout)
VIEWS = ("view", "reshape", "unsqueeze", "squeeze", "expand", "permute", "transpose", "t.default", "split",
         "unbind", "select", "slice", "alias", "detach", "_unsafe_view", "as_strided", "clone")
#: aten ops a GPU runs as one library kernel each
MATMULS = ("aten.mm.", "aten.bmm.", "aten.addmm.", "aten.baddbmm.", "scaled_dot_product", "aten.matmul")


def _compute(node: torch.fx.Node) -> bool:
    name = str(node.target)
    return node.op == "call_function" and "getitem" not in name and not any(v in name for v in VIEWS)


def count(graph: torch.fx.Graph, fixed: Optional[Sequence[bool]] = None) -> Dict[str, int]:
    """``ops``, ``matmuls`` of ``graph``; ``param-only`` when ``fixed`` tells which placeholders hold
    parameters, buffers, products or casts."""
    nodes = list(graph.nodes)
    ops = [n for n in nodes if _compute(n)]
    out = {"ops": len(ops), "matmuls": sum(any(m in str(n.target) for m in MATMULS) for n in ops)}
    if fixed is not None:
        const = {n for n, f in zip([n for n in nodes if n.op == "placeholder"], fixed) if f}
        for n in nodes:
            if n.op == "call_function" and n.all_input_nodes and all(a in const for a in n.all_input_nodes):
                const.add(n)
        out["param-only"] = sum(n in const for n in ops)
    return out


def fixed_ids(model: nn.Module) -> Set[int]:
    """``id`` of every tensor a call reads that depends on ``model``'s state alone: its parameters and
    buffers, its modules' product stores (:mod:`~smdm_plugin.core.products`) and its weight casts
    (:mod:`~smdm_plugin.core.weight_casts`)."""
    ids = {id(t) for t in (*model.parameters(), *model.buffers())}
    stores = [m.__dict__.get("_products") for m in model.modules()] + [model.__dict__.get("_smdm_cast_store")]
    return ids | {id(t) for store in stores if store is not None for held in store.tensors.values() for t in held}


def aot_counter(model: nn.Module, with_fixed: bool = True) -> "tuple[Callable, List[Dict[str, int]]]":
    """``(backend, found)``: a ``torch.compile`` backend that traces each Dynamo graph to AOTAutograd's
    graphs (no code generation) and appends each one's :func:`count` to ``found`` (forward graphs
    with ``param-only`` when ``with_fixed``; backward graphs without: their inputs are no placeholders
    of the call)."""
    from torch._dynamo.backends.common import aot_autograd

    found: List[Dict[str, int]] = []
    fixed: List[List[bool]] = []

    def forward(gm: torch.fx.GraphModule, example_inputs) -> object:
        found.append(count(gm.graph, fixed[-1] if with_fixed else None))
        return gm.forward

    def backward(gm: torch.fx.GraphModule, example_inputs) -> object:
        found.append(count(gm.graph))
        return gm.forward

    aot = aot_autograd(fw_compiler=forward, bw_compiler=backward)

    def backend(gm: torch.fx.GraphModule, example_inputs) -> object:
        ids = fixed_ids(model)
        fixed.append([id(t) in ids for t in example_inputs])
        return aot(gm, example_inputs)

    return backend, found

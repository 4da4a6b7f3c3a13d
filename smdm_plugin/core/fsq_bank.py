"""The FSQ key maps of a stack's attention layers held as stacked parameters (:class:`KeyMapBank`).

Each layer's ``key_down`` / ``key_up`` becomes a :class:`KeyMapView`: ``nn.Linear``'s interface on one
row of the bank's ``[G, ...]`` tensors. The folded path reads the bank as it is: a training step
stacks no per-layer tensors, autograd accumulates one gradient per role instead of one per layer and
role, and an optimizer steps 4 tensors instead of 4·G (host time: docs/gpu.md). State dicts hold the
bank's tensors under their parameter names (upstream loops pair ``named_parameters()`` with
``state_dict()``); a state dict of per-layer key maps (0.9's) loads into the bank.
"""
from __future__ import annotations

from typing import Any, Dict, List, Optional, Sequence, Tuple

import torch
from torch import Tensor, nn

__all__ = ["KeyMapBank", "KeyMapView", "bank_key_maps", "shared_bank", "key_map_tensors", "remove_banks",
           "upgrade_optimizer_state"]

#: the bank's parameter of each (key map, tensor)
_NAMES = {("key_down", "weight"): "down_weight", ("key_down", "bias"): "down_bias",
          ("key_up", "weight"): "up_weight", ("key_up", "bias"): "up_bias"}


class KeyMapBank(nn.Module):
    """``down_weight [G, d, hd]``, ``down_bias [G, d]``, ``up_weight [G, hd, d]``, ``up_bias [G, hd]``:
    the key maps of ``G`` FSQ attention layers (``requires_grad`` as each layer's had: ``key_up.bias``
    is frozen), registered once, on the module that holds the layers (after them: a state dict of
    per-layer key maps loads through the views first, :meth:`_load_from_state_dict`)."""

    def __init__(self, attns: Sequence[nn.Module]) -> None:
        super().__init__()
        for (module, tensor), pname in _NAMES.items():
            parts = [getattr(getattr(a, module), tensor) for a in attns]
            with torch.no_grad():
                stacked = torch.stack([p.detach() for p in parts])
            self.register_parameter(pname, nn.Parameter(stacked, requires_grad=parts[0].requires_grad))
        self.size = len(attns)
        self._rows_loaded: set = set()                # (module, tensor, row) a view loaded in this load

    def tensor(self, module: str, tensor: str) -> nn.Parameter:
        """The stacked parameter of ``module`` (``key_down`` / ``key_up``)'s ``tensor`` (``weight`` / ``bias``)."""
        return self._parameters[_NAMES[module, tensor]]

    def _load_from_state_dict(self, state_dict: Dict[str, Any], prefix: str, local_metadata: Any, strict: bool,
                              missing_keys: List[str], unexpected_keys: List[str], error_msgs: List[str]) -> None:
        """Its own keys as any module's; a tensor whose key is absent is not missing when every row
        came from its layer's own key (0.9's layout: the views, loaded before the bank, copied them)."""
        rows, self._rows_loaded = self._rows_loaded, set()
        absent = []
        super()._load_from_state_dict(state_dict, prefix, local_metadata, strict, absent, unexpected_keys,
                                      error_msgs)
        done = {prefix + _NAMES[module, tensor] for module, tensor in _NAMES
                if all((module, tensor, i) in rows for i in range(self.size))}
        missing_keys.extend(k for k in absent if k not in done)

    def extra_repr(self) -> str:
        w = self.down_weight
        return f"layers={self.size}, head_dim={w.shape[2]}, fsq_dim={w.shape[1]}"


class KeyMapView(nn.Module):
    """``nn.Linear``'s interface (``weight [out, in]``, ``bias [out]``, ``in_features``, ``out_features``,
    ``forward``) on row ``index`` of ``bank``'s tensors of ``module`` (``key_down`` / ``key_up``):
    views, read at each access (autograd reaches the bank). No parameters and no state-dict entries
    of its own."""

    def __init__(self, bank: KeyMapBank, module: str, index: int) -> None:
        super().__init__()
        self.__dict__["_bank"] = bank                 # not a child: the bank is registered once
        self.module_name, self.index = module, int(index)
        self.out_features, self.in_features = bank.tensor(module, "weight").shape[1:]

    @property
    def bank(self) -> KeyMapBank:
        return self.__dict__["_bank"]

    @property
    def weight(self) -> Tensor:
        return self.bank.tensor(self.module_name, "weight")[self.index]

    @property
    def bias(self) -> Tensor:
        return self.bank.tensor(self.module_name, "bias")[self.index]

    def forward(self, x: Tensor) -> Tensor:
        return nn.functional.linear(x, self.weight, self.bias)

    def grad_of(self, name: str) -> Optional[Tensor]:
        """The accumulated gradient of ``weight`` / ``bias`` (``nn.Linear``'s ``weight.grad``): the
        row of the bank's, or None."""
        grad = self.bank.tensor(self.module_name, name).grad
        return None if grad is None else grad[self.index]

    def _save_to_state_dict(self, destination: Dict[str, Any], prefix: str, keep_vars: bool) -> None:
        return None                                   # the bank writes the values

    def _load_from_state_dict(self, state_dict: Dict[str, Any], prefix: str, local_metadata: Any, strict: bool,
                              missing_keys: List[str], unexpected_keys: List[str], error_msgs: List[str]) -> None:
        """0.9's per-layer ``weight`` / ``bias``, where given, copied into the bank's row (today's
        state dicts hold the bank's tensors: the bank loads them after); any other key is unexpected."""
        for name in ("weight", "bias"):
            key = prefix + name
            if key not in state_dict:
                continue
            value, target = state_dict[key], getattr(self, name)
            if not isinstance(value, Tensor) or value.shape != target.shape:
                error_msgs.append(f"size mismatch for {key}: copying a param with shape "
                                  f"{tuple(getattr(value, 'shape', ()))} from checkpoint, the shape in current "
                                  f"model is {tuple(target.shape)}.")
                continue
            with torch.no_grad():
                target.copy_(value)
            self.bank._rows_loaded.add((self.module_name, name, self.index))
        if strict:
            unexpected_keys.extend(k for k in state_dict if k.startswith(prefix) and k[len(prefix):]
                                   not in ("weight", "bias"))

    def extra_repr(self) -> str:
        return f"in_features={self.in_features}, out_features={self.out_features}, bank row {self.index}"


def _groups(attns: Sequence[nn.Module]) -> List[List[nn.Module]]:
    """``attns`` grouped by what one bank can hold: the same key-map shapes, dtype, device and frozen
    tensors (first-seen order)."""
    groups: Dict[tuple, List[nn.Module]] = {}
    for a in attns:
        ts = [getattr(getattr(a, m), t) for m, t in _NAMES]
        groups.setdefault(tuple((x.shape, x.dtype, x.device, x.requires_grad) for x in ts), []).append(a)
    return list(groups.values())


def bank_key_maps(owner: nn.Module, attns: Sequence[nn.Module], name: str = "fsq_key_maps") -> List[str]:
    """In place: the key maps of ``attns`` (FSQ attention layers with their own ``nn.Linear``
    ``key_down`` / ``key_up``) moved into banks registered on ``owner`` (one per group of two or
    more alike layers, named ``name``, ``name_1``, ...; ``attns`` inside ``owner``, registered before
    it), each layer's maps replaced by views. The values are unchanged. Returns the names registered."""
    names = []
    for group in _groups([a for a in attns if isinstance(a.key_down, nn.Linear)]):
        if len(group) < 2:
            continue
        registered, k = name, 0
        while hasattr(owner, registered):
            k += 1
            registered = f"{name}_{k}"
        bank = KeyMapBank(group)
        owner.add_module(registered, bank)
        names.append(registered)
        for i, a in enumerate(group):
            a.key_down = KeyMapView(bank, "key_down", i)
            a.key_up = KeyMapView(bank, "key_up", i)
    return names


def shared_bank(attns: Sequence[nn.Module]) -> Optional[KeyMapBank]:
    """The bank whose rows are exactly the key maps of ``attns``, in order, else None."""
    first = attns[0]._modules.get("key_down") if attns else None
    bank = first.__dict__.get("_bank") if isinstance(first, KeyMapView) else None
    if bank is None or bank.size != len(attns):
        return None
    for i, a in enumerate(attns):
        down, up = a._modules.get("key_down"), a._modules.get("key_up")
        if not (isinstance(down, KeyMapView) and isinstance(up, KeyMapView) and down.bank is bank
                and up.bank is bank and down.index == i and up.index == i):
            return None
    return bank


def key_map_tensors(attn: nn.Module) -> Tuple[Tensor, Tensor, Tensor, Tensor]:
    """What ``attn``'s key maps read — ``(down weight, down bias, up weight, up bias)``: its own
    parameters, or its bank's stacked ones (for caches keyed on storage and version; no op)."""
    down, up = attn._modules["key_down"], attn._modules["key_up"]
    if isinstance(down, KeyMapView):
        bank = down.bank
        return tuple(bank._parameters[n] for n in _NAMES.values())  # type: ignore[return-value]
    return down._parameters["weight"], down._parameters["bias"], up._parameters["weight"], up._parameters["bias"]


def remove_banks(module: nn.Module) -> int:
    """Unregister every :class:`KeyMapBank` inside ``module`` (after its layers left it). Returns how many."""
    found = [(parent, name) for parent in module.modules() for name, child in parent._modules.items()
             if isinstance(child, KeyMapBank)]
    for parent, name in found:
        del parent._modules[name]
    return len(found)


def _unbanked_order(model: nn.Module) -> List[Any]:
    """``model.parameters()`` as a model whose key maps were each layer's own ``nn.Linear`` s lists
    them (0.9's layout): parameters, and ``(bank tensor, row)`` where a view's ``weight`` / ``bias``
    stood."""
    out: List[Any] = []
    seen = set()
    for m in model.modules():
        if isinstance(m, KeyMapBank):
            continue
        if isinstance(m, KeyMapView):
            out += [(m.bank.tensor(m.module_name, name), m.index) for name in ("weight", "bias")]
            continue
        for p in m._parameters.values():
            if p is not None and id(p) not in seen:
                seen.add(id(p))
                out.append(p)
    return out


def upgrade_optimizer_state(state_dict: Dict[str, Any], model: nn.Module, optimizer: torch.optim.Optimizer
                            ) -> Dict[str, Any]:
    """An optimizer state saved for ``model`` with per-layer key maps (before the banks: each
    layer's tensors apart) as ``optimizer`` (over the banked ``model``) loads it: each bank tensor's
    state the rows' states stacked (``step`` shared), the others as saved. A state that already fits
    ``optimizer``, or one this cannot map (sizes that do not add up, rows with different steps or
    some without state), comes back as it is (``load_state_dict`` then says what is wrong)."""
    groups, saved = optimizer.param_groups, state_dict.get("param_groups")
    if (not any(isinstance(m, KeyMapBank) for m in model.modules()) or not isinstance(saved, list)
            or len(saved) != len(groups)
            or all(len(s.get("params", ())) == len(g["params"]) for s, g in zip(saved, groups))):
        return state_dict
    order = _unbanked_order(model)
    state, new_state, new_groups, index = state_dict.get("state", {}), {}, [], 0
    for s, g in zip(saved, groups):
        ids = {id(p) for p in g["params"]}
        old = [e for e in order if id(e[0] if isinstance(e, tuple) else e) in ids]
        if len(old) != len(s["params"]):
            return state_dict
        plain: Dict[int, Any] = {}
        rows_of: Dict[int, Dict[int, Any]] = {}                 # a bank tensor's rows' states
        for entry, key in zip(old, s["params"]):
            if isinstance(entry, tuple):
                rows_of.setdefault(id(entry[0]), {})[entry[1]] = state.get(key)
            else:
                plain[id(entry)] = state.get(key)
        params = []
        for p in g["params"]:
            st = plain.get(id(p))
            if id(p) in rows_of:
                rows = [rows_of[id(p)].get(i) for i in range(p.shape[0])]
                if all(r is None for r in rows):
                    st = None
                elif any(r is None for r in rows):
                    return state_dict
                else:
                    st = _stack_states(rows)
                    if st is None:
                        return state_dict
            if st is not None:
                new_state[index] = st
            params.append(index)
            index += 1
        new_groups.append({**s, "params": params})
    return {**state_dict, "state": new_state, "param_groups": new_groups}


def _stack_states(rows: List[Dict[str, Any]]) -> Optional[Dict[str, Any]]:
    """One state of the rows' states: tensors of a row's shape stacked, the rest (``step``) equal in
    every row and kept; None when they differ."""
    out: Dict[str, Any] = {}
    for key, first in rows[0].items():
        values = [r.get(key) for r in rows]
        if isinstance(first, Tensor) and first.dim() > 0:
            if any(not isinstance(v, Tensor) or v.shape != first.shape for v in values):
                return None
            out[key] = torch.stack(values)
        elif all(isinstance(v, Tensor) and torch.equal(v, first) if isinstance(first, Tensor) else v == first
                 for v in values):
            out[key] = first
        else:
            return None
    return out

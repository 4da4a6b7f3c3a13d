"""The keyframe plan of one model call: where the keyframes are, with static shapes."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional, Tuple, Union

import torch

from .checks import require
from .kernels.plan_op import keyframe_plan
from .kernels.plan_tensors import Plan


@dataclass(frozen=True)
class KeyframePlan:
    """Keyframes of one call. ``B`` samples, ``N`` frames, ``K`` = :attr:`capacity` slots.

    Attributes:
        mask: ``[B, N]`` bool, True = keyframe (over the model's frame tokens).
        index: ``[B, K]`` long, the frame held by each slot (distinct within a sample).
        valid: ``[B, K]`` bool, slot holds a keyframe.
        count: ``[B]`` long, keyframes per sample (``1 <= count <= K``).
        prev_slot, next_slot: ``[B, N]`` long, slots of the keyframes around each frame.
        weight: ``[B, N]`` float32 in [0, 1], the interpolation weight of each frame.
        rows: ``[K, B]`` long, contiguous: the row ``frame * B + b`` of each slot's frame in a
            frame-major ``[N * B, ...]`` tensor (made once per call, read by the input embedding
            and the compact backend).
        cubic: ``[B]`` bool, ``True`` (every sample) or None: samples whose output frames are filled by
            C¹ Catmull-Rom curves through the output at the keyframes
            (:func:`~smdm_plugin.core.interpolation.catmull_rom_refill`; sampling with
            ``sample_interpolation="cubic"``); None = the paper's linear fill only.
        taps: ``(frames [B, N, 4] long, weights [B, N, 4] float32)`` of that C¹ fill when they were
            looked up in a table (the sampling schedule's uniform masks), else None (computed from
            the plan's slots by :func:`~smdm_plugin.core.interpolation.catmull_rom_taps`).
        key_bias: ``[B, 1 + K]`` float32 or None: the additive key padding mask of one lead token
            and the slots (0 kept, -inf empty slots; column 0 is a lead token's 0), made with the plan
            (:meth:`build`, :meth:`PlanTables.lookup`); ``key_bias[:, 1 - lead:]`` serves ``lead <= 1``.
        slots: ``[B, 2N]`` long or None: ``prev_slot | next_slot`` side by side (those two are its
            views), so the fill gathers both ends at once.
    """

    mask: torch.Tensor
    index: torch.Tensor
    valid: torch.Tensor
    count: torch.Tensor
    prev_slot: torch.Tensor
    next_slot: torch.Tensor
    weight: torch.Tensor
    slot_rows: Optional[torch.Tensor]
    cubic: Union[None, bool, torch.Tensor] = None
    taps: Optional[Tuple[torch.Tensor, torch.Tensor]] = None
    key_bias: Optional[torch.Tensor] = None
    slots: Optional[torch.Tensor] = None
    rows_from: Optional[Tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = None

    @property
    def rows(self) -> torch.Tensor:
        """``[K, B]`` long, contiguous (see the class docstring). A looked-up plan makes it when it
        is read (2 ops; the static sampling path never reads it): ``rows_from`` = ``(arange(B),
        index table transposed [K, N+1], lengths [B])``."""
        if self.slot_rows is not None:
            return self.slot_rows
        batch_index, index_t, lengths = self.rows_from
        return torch.add(batch_index, index_t.index_select(1, lengths), alpha=lengths.shape[0])

    @property
    def capacity(self) -> int:
        return self.index.shape[1]

    @property
    def batch(self) -> int:
        return self.mask.shape[0]

    @property
    def frames(self) -> int:
        return self.mask.shape[1]

    @classmethod
    def build(cls, mask: torch.Tensor, capacity: Optional[int] = None, check: bool = True,
              cubic: Optional[torch.Tensor] = None,
              taps: Optional[Tuple[torch.Tensor, torch.Tensor]] = None) -> "KeyframePlan":
        """The plan of bool ``mask [B, N]`` with ``capacity`` slots (None: ``N``, always enough).
        Every sample needs between 1 and ``capacity`` keyframes (checked without a host sync;
        ``check=False`` for masks that hold it by construction, e.g. the sampling schedule's).
        ``cubic``: bool ``[B]``, samples whose output is filled by C¹ interpolation (True: all, None:
        none)."""
        if mask.dim() != 2:
            raise ValueError(f"KeyframePlan: mask must be bool [B, N], got shape {tuple(mask.shape)}")
        mask = mask.to(torch.bool)
        B, N = mask.shape
        K = N if capacity is None else int(capacity)
        if not 1 <= K <= N:
            raise ValueError(f"KeyframePlan: capacity must be in [1, N={N}], got {capacity}")
        tensors = keyframe_plan(mask, K)
        if check:
            count = tensors[2]
            require((count >= 1) & (count <= K),
                    f"KeyframePlan: every sample needs 1..{K} keyframes (capacity {K}); a keyframe mask "
                    "(KeyframeRequest.mask with its forced frames, or a training mask) has more than the capacity "
                    "(KeyframeRequest.capacity) or none")
        if cubic is not None and cubic is not True:
            cubic = torch.as_tensor(cubic, device=mask.device).to(torch.bool).reshape(-1).expand(B)
        return cls.of_tensors(mask, tensors, cubic, taps)

    @classmethod
    def of_tensors(cls, mask: torch.Tensor, tensors: Plan, cubic: Union[None, bool, torch.Tensor] = None,
                   taps: Optional[Tuple[torch.Tensor, torch.Tensor]] = None) -> "KeyframePlan":
        """The plan of bool ``mask [B, N]`` from its plan op's ``tensors`` (``keyframe_plan(mask, K)``'s,
        or a fused op's with the same values), unchecked."""
        index, valid, count, slots, weight, rows, key_bias = tensors
        N = mask.shape[1]
        return cls(mask, index, valid, count, slots[:, :N], slots[:, N:], weight, rows, cubic, taps, key_bias,
                   slots)


def _packed(t: torch.Tensor) -> torch.Tensor:
    """``[R, n]`` of any dtype as int64 columns ``[R, ceil(n·size / 8)]`` (zero padded): the same
    bytes, to share one int64 table row; ``.view(dtype)[:, :n]`` of the columns gives ``t`` back."""
    R, n = t.shape
    per = 8 // t.element_size()
    pad = (-n) % per
    if pad:
        t = torch.cat([t, t.new_zeros(R, pad)], 1)
    return t.contiguous().view(torch.int64)


@dataclass(frozen=True)
class PlanTables:
    """The plans of a fixed mask per length, as lookup tables (the sampling schedule's uniform
    masks): row ``L`` belongs to a sample of ``L`` valid frames. A call looks its plan up with 3
    ops (one row lookup; the slot rows, when read: a lookup and an add) instead of building it (~25).

    ``table [N+1, C]`` int64: per length, side by side, ``index [K] | count [1] | prev_slot [N] |
    next_slot [N]`` as int64, then the bytes of ``weight [N]`` float32, ``key bias [1+K]`` float32
    and bfloat16, ``mask [N] | valid [K]`` bool (``column`` holds where each starts, in int64
    columns; the other dtypes are views of the looked-up row, no copy). ``index_t [K, N+1]``: the
    index transposed (the slot rows come out ``[K, B]`` contiguous).
    """

    table: torch.Tensor
    index_t: torch.Tensor
    frames: int
    capacity: int

    @classmethod
    def build(cls, masks: torch.Tensor, capacity: int) -> "PlanTables":
        """Tables of bool ``masks [N+1, N]`` (row ``L``: the mask of length ``L``; every row needs
        1..capacity keyframes) with ``capacity`` slots; on the masks' device."""
        p = KeyframePlan.build(masks, capacity, check=False)
        bias = p.key_bias
        parts = [torch.cat([p.index, p.count[:, None], p.slots], 1), _packed(p.weight), _packed(bias),
                 _packed(bias.to(torch.bfloat16)), _packed(torch.cat([p.mask, p.valid], 1))]
        return cls(torch.cat(parts, 1), p.index.t().contiguous(), p.frames, p.capacity)

    def to(self, device: torch.device) -> "PlanTables":
        return PlanTables(self.table.to(device), self.index_t.to(device), self.frames, self.capacity)

    def lookup(self, lengths: torch.Tensor, batch_index: torch.Tensor, cubic=None,
               taps: Optional[Tuple[torch.Tensor, torch.Tensor]] = None,
               dtype: torch.dtype = torch.float32) -> KeyframePlan:
        """The plan of samples with ``lengths [B]`` (long, validated, on the tables' device);
        ``batch_index``: ``arange(B)`` on that device (a per-call constant the caller keeps);
        ``dtype``: of the key bias (float32 or bfloat16 are stored; others cast). Values equal
        :meth:`KeyframePlan.build` on the looked-up masks."""
        N, K = self.frames, self.capacity
        B = lengths.shape[0]
        row = self.table[lengths]                                                         # [B, C]
        c = K + 1 + 2 * N                                   # where the weights start (int64 columns)
        w_cols, b_cols = -(-N // 2), -(-(1 + K) // 2)
        h_cols = -(-(1 + K) // 4)
        weight = row[:, c:c + w_cols].view(torch.float32)[:, :N]
        c += w_cols
        bias32 = row[:, c:c + b_cols].view(torch.float32)[:, :1 + K]
        c += b_cols
        bias16 = row[:, c:c + h_cols].view(torch.bfloat16)[:, :1 + K]
        c += h_cols
        flags = row[:, c:].view(torch.bool)
        bias = bias16 if dtype == torch.bfloat16 else bias32 if dtype == torch.float32 else bias32.to(dtype)
        if cubic is not None and cubic is not True:
            cubic = torch.as_tensor(cubic, device=lengths.device).to(torch.bool).reshape(-1).expand(B)
        return KeyframePlan(flags[:, :N], row[:, :K], flags[:, N:N + K], row[:, K], row[:, K + 1:K + 1 + N],
                            row[:, K + 1 + N:K + 1 + 2 * N], weight, None, cubic, taps, bias,
                            row[:, K + 1:K + 1 + 2 * N], (batch_index, self.index_t, lengths))

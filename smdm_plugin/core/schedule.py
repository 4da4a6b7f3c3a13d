"""When and how keyframes are chosen: from x0 during training, from (x_t, t) during sampling.

Sampling follows the paper's schedule with its step count: diffusion steps are numbered
``t = T-1 … 0`` here (as in MDM's code) and ``T … 1`` in the paper, so the paper's last ``γT``
steps (``t_paper <= γT``) are exactly the ``round(γ·T)`` steps with ``t < round(γ·T)``: 5 of 50,
1 of 10, 100 of 1000. Those steps re-select keyframes by VW on ``x_t`` (when the dynamic update is
on); the earlier ones use the uniform mask. Both masks are computed without a host sync and with
static shapes (the late/early choice is a per-sample ``torch.where``; VW does no work for samples
that are not late).
"""
from __future__ import annotations

from typing import Dict, Optional, Sequence, Tuple, Union

import numpy as np
import torch

from .checks import as_lengths, as_mask, compiling
from .config import SparseConfig
from .selection_features import KINDS, SelectionConstants, apply_selection_constants, selection_constants
from .interpolation import catmull_rom_taps
from .noise import CounterNoise, default_noise_salt, default_noise_seed, noise_table
from .plan import KeyframePlan, PlanTables
from .selection import (SELECTORS, keyframe_capacity, keyframe_count_table, select_checked,
                        select_perturbed_checked, select_perturbed_plan_checked, uniform_table)

ArrayLike = Union[torch.Tensor, np.ndarray, Sequence[float], None]


def resolve_lengths(lengths, B: int, N: int, device: torch.device) -> torch.Tensor:
    """``lengths`` (tensor, list or None) as a long tensor ``[B]`` on ``device``, validated
    (``2 <= L <= N``; no host sync on accelerators)."""
    return as_lengths(lengths, B, N, device, "MaskSchedule")


def late_steps(gamma: float, diffusion_steps: int) -> int:
    """How many final sampling steps re-select keyframes on ``x_t``: ``round(γ·T)`` (the paper's
    ``t <= γT`` with ``t`` counted ``T … 1``)."""
    return int(round(float(gamma) * int(diffusion_steps)))


class MaskSchedule:
    """Keyframe masks for training and sampling.

    Args:
        config: the sparse config (reduction, selector, feature, gamma, dynamic_update, ...).
        mean, std: ``[D]`` dataset statistics to de-normalise features before VW (optional).
        noise_seed: the seed of the mask noise's table (:mod:`~smdm_plugin.core.noise`); None =
            torch's seed now (``torch.initial_seed()``); each rank of a distributed run starts
            its windows elsewhere in it (:attr:`noise_salt`). The table is made
            here, before any traced call, when the config draws (mask noise, random selector):
            :attr:`noise_table` (``sparsify`` puts it on the model as a buffer).
    """

    def __init__(self, config: SparseConfig, mean: ArrayLike = None, std: ArrayLike = None,
                 noise_seed: Optional[int] = None) -> None:
        self.config = config
        self.noise_seed = default_noise_seed() if noise_seed is None else int(noise_seed)
        self.noise_salt = default_noise_salt()
        draws = config.mask_noise > 0 or config.selector == "random"
        #: float32 ``[TABLE_SIZE]`` uniforms on the CPU, or None when the config draws nothing
        self.noise_table: Optional[torch.Tensor] = noise_table(self.noise_seed) if draws else None
        self._noise: Dict[torch.device, torch.Tensor] = {}
        self.mean = None if mean is None else torch.as_tensor(np.asarray(mean), dtype=torch.float32)
        self.std = None if std is None else torch.as_tensor(np.asarray(std), dtype=torch.float32)
        # per (frames, device[, dtype]) constants, made once: a host-to-device copy on every call
        # would synchronise with the GPU. The config is fixed for the schedule's lifetime.
        self._tables: Dict[Tuple[int, torch.device], Tuple[torch.Tensor, torch.Tensor]] = {}
        self._consts: Dict[tuple, SelectionConstants] = {}
        self._taps: Dict[Tuple[int, torch.device], Tuple[torch.Tensor, torch.Tensor]] = {}
        self._plans: Dict[Tuple[int, int, torch.device], PlanTables] = {}
        self._batch_index: Dict[Tuple[int, torch.device], torch.Tensor] = {}

    @property
    def late_steps(self) -> int:
        """Number of final sampling steps that use VW on ``x_t`` (0 when the update is off)."""
        c = self.config
        return late_steps(c.gamma, c.diffusion_steps) if c.dynamic and c.reduction > 0 else 0

    def cubic_samples(self, t, B: int, device: torch.device, D: int) -> Union[None, bool, torch.Tensor]:
        """bool ``[B]``: the samples at step ``t`` (``[B]`` or a scalar) of motions with ``D``
        features whose non-keyframes are filled by C¹ Catmull-Rom interpolation (``sample_interpolation``
        resolved to ``cubic`` by :meth:`SparseConfig.sample_fill`, in the last
        ``sample_interpolation_steps`` steps); ``True`` when every sample is (no tensor, no op);
        None when every sample is linear (the paper). No host sync."""
        c = self.config
        if c.sample_fill(D) != "cubic" or c.reduction == 0:
            return None
        if c.sample_interpolation_steps is None:
            return True
        return torch.as_tensor(t, device=device).reshape(-1).expand(B) < int(c.sample_interpolation_steps)

    def capacity(self, n_frames: int, training: bool, forced: int = 0) -> int:
        """The most keyframes any sample of ``n_frames`` frames gets from this schedule (mask noise
        in training; ``forced`` = the most protected frames of a sample)."""
        c = self.config
        return keyframe_capacity(n_frames, c.reduction, c.mask_noise if training else 0.0, forced)

    def tables(self, n_frames: int, device: torch.device) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(counts [N+1] long, uniform [N+1, N] bool)`` on ``device``: the keyframe count and the
        uniform mask of every length (index them with ``lengths``)."""
        key = (int(n_frames), torch.device(device))
        if key not in self._tables:
            r = self.config.reduction
            tables = (keyframe_count_table(n_frames, r).to(device), uniform_table(n_frames, r).to(device))
            if compiling():       # constants of the traced graph; filling the cache while tracing
                return tables     # would fail the graph's guard on it and recompile the next call
            self._tables[key] = tables
        return self._tables[key]

    def cubic_taps(self, n_frames: int, device: torch.device) -> Tuple[torch.Tensor, torch.Tensor]:
        """``(frames [N+1, N, 4] long, weights [N+1, N, 4] float32)`` on ``device``: the C¹
        Catmull-Rom taps (:func:`~smdm_plugin.core.interpolation.catmull_rom_taps`) of the uniform
        mask of every length (index them with ``lengths``), made once like :meth:`tables`: a sampling
        call on the uniform mask looks its taps up (2 ops) instead of computing them (~20)."""
        key = (int(n_frames), torch.device(device))
        if key not in self._taps:
            mask = uniform_table(n_frames, self.config.reduction)
            mask[:2, 0] = True    # lengths 0 and 1 are never looked up; one keyframe keeps them well formed
            plan = KeyframePlan.build(mask, None, check=False)
            frames, w = catmull_rom_taps(plan.index, plan.count, plan.prev_slot, plan.next_slot, plan.weight)
            taps = (frames.to(device), w.to(device))
            if compiling():       # (as in tables: no cache write while tracing)
                return taps
            self._taps[key] = taps
        return self._taps[key]

    def uniform_plan(self, lengths: torch.Tensor, n_frames: int, prefix: int = 0, cubic=None,
                     taps: Optional[Tuple[torch.Tensor, torch.Tensor]] = None,
                     dtype: torch.dtype = torch.float32) -> KeyframePlan:
        """The sampling plan of the uniform mask (no forced frames) of samples with ``lengths [B]``
        (long, validated, on the device) over ``n_frames`` frames after ``prefix`` frames that are
        always kept (DiP): looked up in per-length tables made once per ``(frames, prefix,
        device)`` (:class:`~smdm_plugin.core.plan.PlanTables`): 3 ops instead of the mask lookup
        and :meth:`KeyframePlan.build` (~25); the key bias in ``dtype`` (the attention's). Equal to building the plan of :meth:`sampling_mask`'s
        uniform mask with :meth:`capacity` slots."""
        device = lengths.device
        key = (int(n_frames), int(prefix), device)
        tables = self._plans.get(key)
        if tables is None:
            masks = uniform_table(n_frames, self.config.reduction)
            masks[:2, 0] = True   # lengths 0 and 1 are never looked up; one keyframe keeps them well formed
            if prefix:
                masks = torch.cat([masks.new_ones(n_frames + 1, prefix), masks], 1)
            tables = PlanTables.build(masks, self.capacity(n_frames, training=False) + prefix).to(device)
            if not compiling():   # (as in tables: no cache write while tracing)
                self._plans[key] = tables
        B = lengths.shape[0]
        batch_index = None if compiling() else self._batch_index.get((B, device))
        if batch_index is None:
            batch_index = torch.arange(B, device=device)
            if not compiling():
                self._batch_index[(B, device)] = batch_index
        return tables.lookup(lengths, batch_index, cubic, taps, dtype)

    def noise(self, step: torch.Tensor) -> CounterNoise:
        """The counter-based random numbers at ``step`` (int64, 0-d or ``[B]``, on the device
        wanted): windows of :attr:`noise_table` (copied to that device once; training through
        the diffusion wrapper reads the model's own copy instead)."""
        device = step.device
        table = self._noise.get(device)
        if table is None:
            if self.noise_table is None:
                self.noise_table = noise_table(self.noise_seed)
            table = self.noise_table.to(device)
            if not compiling():   # (as in tables: no cache write while tracing)
                self._noise[device] = table
        return CounterNoise(step, table, self.noise_salt)

    def _kind(self, D: int) -> str:
        return self.config.feature_kind(D)

    def features(self, x: torch.Tensor) -> torch.Tensor:
        """What VW measures, ``[B, N, F]``, from motion ``x [B, N, D]``: the joint positions of the
        HumanML3D/KIT layout (de-normalised with ``mean``/``std``) or the raw features, plus the
        frame index times ``frame_index_scale`` (see
        :func:`~smdm_plugin.core.selection_features.extract_selection_features`)."""
        if not isinstance(x, torch.Tensor) or x.dim() != 3:
            shape = tuple(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__
            raise ValueError(f"MaskSchedule.features: x must be [B, N, D], got {shape}")
        return self._features_checked(x)

    def _features_checked(self, x: torch.Tensor) -> torch.Tensor:
        """:meth:`features` for a call's motion ``x [B, N, D]`` (shape known good), from per-device
        constants (:func:`~smdm_plugin.core.selection_features.selection_constants`; ``raw`` features are not
        de-normalised)."""
        B, N, D = x.shape
        kind = self._kind(D)
        x = x.detach()
        x = x if x.dtype in (torch.float32, torch.float64) else x.float()
        key = (kind, N, D, x.device, x.dtype)
        consts = self._consts.get(key)
        if consts is None:
            if kind in KINDS and D != KINDS[kind][0]:
                raise ValueError(f"MaskSchedule: feature={kind!r} needs D={KINDS[kind][0]} features, got D={D}")
            use = kind != "raw"
            consts = selection_constants(kind, N, D, self.mean if use else None, self.std if use else None,
                                         self.config.frame_index_scale, x.device, x.dtype)
            if not compiling():   # (as in tables: no cache write while tracing)
                self._consts[key] = consts
        return apply_selection_constants(x, consts)

    def training_mask(self, x0: torch.Tensor, lengths=None, forced: Optional[torch.Tensor] = None,
                      generator: Optional[torch.Generator] = None, *, checked: bool = False) -> torch.Tensor:
        """bool ``[B, N]`` from the clean motion ``x0 [B, N, D]``: the selector (forced frames
        inside the budget) + mask noise (never dropping forced frames). ``checked=True``: ``lengths``
        is a validated long tensor on ``x0``'s device and ``forced`` a bool ``[B, N]`` or None.

        Random draws (mask noise, the ``random`` selector) come from ``generator``: a
        :class:`~smdm_plugin.core.noise.CounterNoise` (the diffusion wrapper passes the model's:
        its step counter and table; :meth:`noise` makes one), whose step is then advanced by one
        in place — no RNG state touched, traceable, no sync; or a ``torch.Generator``; None:
        torch's global stream."""
        B, N, _ = x0.shape
        lengths, forced = _checked_inputs(x0, lengths, forced, checked)
        c = self.config
        counts, _ = self.tables(N, x0.device)
        with torch.no_grad():
            mask = select_perturbed_checked(self._features_checked(x0), lengths, counts[lengths], c.selector,
                                            c.mask_noise, generator, forced)
            if isinstance(generator, CounterNoise):
                generator.advance()
        return mask

    def training_plan(self, x0: torch.Tensor, lengths, slots: int, prefix: int = 0,
                      generator: Optional[torch.Generator] = None, *, checked: bool = False
                      ) -> Optional[Tuple[torch.Tensor, KeyframePlan]]:
        """``(mask [B, N], plan)``: :meth:`training_mask` without forced frames and the plan that
        ``KeyframePlan.build`` makes of ``prefix`` always-kept frames then that mask with ``slots``
        slots (the prefix's included), in one op (one kernel on CUDA) where the selector has that
        form (VW with mask noise), in eager mode; else None, nothing drawn (the caller builds the
        plan of :meth:`training_mask`'s). ``generator``, ``checked``: as :meth:`training_mask`."""
        c = self.config
        if compiling() or c.mask_noise <= 0 or SELECTORS.get(c.selector).with_noise_plan is None:
            return None
        N = x0.shape[1]
        lengths, _ = _checked_inputs(x0, lengths, None, checked)
        counts, _ = self.tables(N, x0.device)
        with torch.no_grad():
            mask, plan_mask, tensors = select_perturbed_plan_checked(self._features_checked(x0), lengths,
                                                                     counts[lengths], c.selector, c.mask_noise,
                                                                     generator, slots, prefix)
            if isinstance(generator, CounterNoise):
                generator.advance()
        return mask, KeyframePlan.of_tensors(plan_mask, tensors)

    def sampling_mask(self, x_t: torch.Tensor, t: torch.Tensor, lengths=None,
                      forced: Optional[torch.Tensor] = None, *, checked: bool = False) -> torch.Tensor:
        """bool ``[B, N]`` at sampling step ``t [B]`` (or a scalar): uniform for the early steps, the
        selector (VW) on ``x_t`` for the last :attr:`late_steps` steps; forced frames inside the
        budget. No host sync: the choice is made per sample on the device. ``checked``: as
        :meth:`training_mask`."""
        B, N, _ = x_t.shape
        lengths, forced = _checked_inputs(x_t, lengths, forced, checked)
        c = self.config
        counts, uniform = self.tables(N, x_t.device)
        with torch.no_grad():
            k = counts[lengths]
            if forced is None:
                mask = uniform[lengths]
            else:
                mask = select_checked(x_t[..., :1], lengths, k, "uniform", forced=forced)
            n_late = self.late_steps
            if n_late > 0:
                steps = torch.as_tensor(t, device=x_t.device).reshape(-1).expand(B)
                late = steps < n_late
                feats = self._features_checked(x_t)
                if c.selector == "vw":
                    sel = select_checked(feats, lengths, k, "vw", forced=forced, active=late)
                else:   # (the random selector: numbers from the noise table at step t, no RNG state)
                    sel = select_checked(feats, lengths, k, c.selector, self.noise(steps),
                                         forced=forced)
                mask = torch.where(late[:, None], sel, mask)
        return mask


def _checked_inputs(x: torch.Tensor, lengths, forced, checked: bool):
    """``(lengths [B] long, forced [B, N] bool or None)`` on ``x``'s device for ``x [B, N, F]``;
    validated unless ``checked`` (the caller already did)."""
    if checked:
        return lengths, forced
    B, N, _ = x.shape
    return resolve_lengths(lengths, B, N, x.device), as_mask(forced, B, N, x.device, "forced keyframes")

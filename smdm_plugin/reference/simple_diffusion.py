"""A small x0-predicting Gaussian diffusion (DDPM, cosine schedule) for the in-package backbone:
training losses with valid-frame masking, and ancestral sampling with classifier-free guidance.
It has MDM's ``training_losses(model, x_start, t, model_kwargs)`` interface, so the same
:func:`~smdm_plugin.adapters.diffusion_wrapper.attach_diffusion` wraps it."""
from __future__ import annotations

import math
from typing import Any, Callable, Dict, Optional, Tuple

import torch
import torch.nn as nn


def cosine_betas(T: int, s: float = 0.008) -> torch.Tensor:
    """Nichol & Dhariwal's cosine schedule, ``[T]`` float64."""
    steps = torch.arange(T + 1, dtype=torch.float64) / T
    abar = torch.cos((steps + s) / (1 + s) * math.pi / 2) ** 2
    return (1 - abar[1:] / abar[:-1]).clamp(max=0.999)


def masked_mse(a: torch.Tensor, b: torch.Tensor, mask: Optional[torch.Tensor]) -> torch.Tensor:
    """Mean squared error per sample ``[B]`` over valid frames. ``a, b [B, J, F, N]``,
    ``mask [B, 1, 1, N]`` bool or None."""
    err = (a - b) ** 2
    if mask is None or mask.shape[-1] != a.shape[-1]:
        return err.flatten(1).mean(1)
    m = mask.to(err.dtype).expand_as(err)
    return (err * m).flatten(1).sum(1) / m.flatten(1).sum(1).clamp_min(1)


class SimpleDiffusion:
    """``num_timesteps`` steps; the model predicts x0 (as MDM does)."""

    def __init__(self, num_timesteps: int = 50) -> None:
        self.num_timesteps = int(num_timesteps)
        betas = cosine_betas(self.num_timesteps)
        alphas = 1 - betas
        self.abar = torch.cumprod(alphas, 0)
        abar_prev = torch.cat([torch.ones(1, dtype=torch.float64), self.abar[:-1]])
        self.post_var = betas * (1 - abar_prev) / (1 - self.abar)
        self.coef_x0 = betas * abar_prev.sqrt() / (1 - self.abar)
        self.coef_xt = (1 - abar_prev) * alphas.sqrt() / (1 - self.abar)
        #: the per-step tables ``[T]`` (float64, host) that sampling and training read
        self._host: Dict[str, torch.Tensor] = {
            "sqrt_abar": self.abar.sqrt(), "sqrt_one_minus_abar": (1 - self.abar).sqrt(),
            "coef_x0": self.coef_x0, "coef_xt": self.coef_xt, "post_std": self.post_var.sqrt()}
        #: the same tables on a device in a dtype, built once per ``(device, dtype)``
        self._tables: Dict[Tuple[torch.device, torch.dtype], Dict[str, torch.Tensor]] = {}

    def tables(self, device: torch.device, dtype: torch.dtype) -> Dict[str, torch.Tensor]:
        """The schedule tables ``[T]`` on ``device`` in ``dtype`` (copied there on the first call for
        that pair, then reused: no host-to-device copy on the sampling hot path). Cast from the
        float64 tables, so each entry is bit for bit ``table.to(device)[t].to(dtype)``."""
        key = (torch.device(device), dtype)
        cached = self._tables.get(key)
        if cached is None:
            cached = {k: v.to(device=key[0]).to(dtype) for k, v in self._host.items()}
            self._tables[key] = cached
        return cached

    def _at(self, name: str, t: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
        """Table ``name`` at steps ``t [B]``, shaped ``[B, 1, ...]`` to broadcast against ``like``."""
        return self.tables(like.device, like.dtype)[name][t].view(-1, *([1] * (like.dim() - 1)))

    def q_sample(self, x0: torch.Tensor, t: torch.Tensor, noise: Optional[torch.Tensor] = None) -> torch.Tensor:
        noise = torch.randn_like(x0) if noise is None else noise
        return self._at("sqrt_abar", t, x0) * x0 + self._at("sqrt_one_minus_abar", t, x0) * noise

    def training_losses(self, model: nn.Module, x_start: torch.Tensor, t: torch.Tensor,
                        model_kwargs: Optional[Dict[str, Any]] = None, noise: Optional[torch.Tensor] = None
                        ) -> Dict[str, torch.Tensor]:
        """``{'loss': [B]}``: masked MSE between the predicted and the clean motion."""
        model_kwargs = model_kwargs or {}
        x_t = self.q_sample(x_start, t, noise)
        pred = model(x_t, t, **model_kwargs)
        mse = masked_mse(pred, x_start, model_kwargs.get("y", {}).get("mask"))
        return {"loss": mse, "mse": mse.detach()}

    @staticmethod
    def constraint(model_kwargs: Optional[Dict[str, Any]], x: torch.Tensor
                   ) -> Optional[Tuple[torch.Tensor, torch.Tensor]]:
        """``(mask, target)`` from MDM's ``y['inpainting_mask']`` / ``y['inpainted_motion']``
        (mask bool, expanded to ``x``'s shape ``[B, J, F, N]``), or None when they are absent."""
        y = (model_kwargs or {}).get("y") or {}
        if "inpainting_mask" not in y or "inpainted_motion" not in y:
            return None
        mask, target = torch.as_tensor(y["inpainting_mask"]), torch.as_tensor(y["inpainted_motion"])
        if mask.dtype != torch.bool:
            raise TypeError(f"y['inpainting_mask'] must be bool (True = given), got dtype {mask.dtype}")
        if tuple(target.shape) != tuple(x.shape):
            raise ValueError(f"y['inpainted_motion'] must have the motion's shape {list(x.shape)}, "
                             f"got {list(target.shape)}")
        try:
            mask = mask.to(x.device).expand_as(x)
        except RuntimeError:
            raise ValueError(f"y['inpainting_mask'] must broadcast to the motion's shape {list(x.shape)}, "
                             f"got {list(mask.shape)}") from None
        return mask, target.to(device=x.device, dtype=x.dtype)

    def predict_x0(self, model: Callable, x_t: torch.Tensor, tt: torch.Tensor, model_kwargs: Dict[str, Any],
                   impute_x0: bool = True) -> torch.Tensor:
        """The model's clean motion at steps ``tt [B]`` (long, on ``x_t``'s device); with MDM's
        in-painting keys in ``model_kwargs['y']`` and ``impute_x0``, its given entries replaced by
        the target (see docs/modules.md)."""
        x0 = model(x_t, tt, **model_kwargs)
        given = self.constraint(model_kwargs, x0) if impute_x0 else None
        if given is not None:
            x0 = torch.where(given[0], given[1], x0)
        return x0

    def posterior_sample(self, x0: torch.Tensor, x_t: torch.Tensor, tt: torch.Tensor,
                         noise: torch.Tensor) -> torch.Tensor:
        """``x_{t-1}`` drawn from the posterior ``q(x_{t-1} | x_t, x0)`` at steps ``tt [B]`` with
        ``noise`` (the shape of ``x_t``)."""
        mean = self._at("coef_x0", tt, x_t) * x0 + self._at("coef_xt", tt, x_t) * x_t
        return mean + self._at("post_std", tt, x_t) * noise

    @torch.no_grad()
    def p_sample(self, model: Callable, x_t: torch.Tensor, t: int, model_kwargs: Dict[str, Any],
                 generator: Optional[torch.Generator] = None, impute_x0: bool = True) -> torch.Tensor:
        """One ancestral step ``x_t -> x_{t-1}`` (at ``t == 0`` the clean prediction). With MDM's
        in-painting keys in ``model_kwargs['y']`` and ``impute_x0``, the prediction's given entries
        are replaced by the target first (see docs/modules.md)."""
        tt = torch.full((x_t.shape[0],), t, device=x_t.device, dtype=torch.long)
        x0 = self.predict_x0(model, x_t, tt, model_kwargs, impute_x0)
        if t == 0:
            return x0
        noise = torch.randn(x_t.shape, generator=generator, device=x_t.device, dtype=x_t.dtype)
        return self.posterior_sample(x0, x_t, tt, noise)

    def sample_step(self, model: Callable, x_t: torch.Tensor, tt: torch.Tensor, noise: torch.Tensor,
                    model_kwargs: Dict[str, Any]) -> torch.Tensor:
        """:meth:`p_sample` without a host value: steps ``tt [B]`` a tensor, ``noise`` drawn by the
        caller (any values where ``tt == 0``: the clean prediction is taken there), no Python branch
        on ``t``: one graph serves every step of a loop (a compiled or CUDA-graph-captured sampling
        step). Equal to :meth:`p_sample` with the same noise."""
        x0 = self.predict_x0(model, x_t, tt, model_kwargs)
        last = (tt == 0).view(-1, *([1] * (x_t.dim() - 1)))
        return torch.where(last, x0, self.posterior_sample(x0, x_t, tt, noise))

    @torch.no_grad()
    def p_sample_loop(self, model: Callable, shape: tuple, model_kwargs: Optional[Dict[str, Any]] = None,
                      device: Any = "cpu", generator: Optional[torch.Generator] = None,
                      progress: bool = False, imputation: str = "x0") -> torch.Tensor:
        """Sample ``shape`` (``[B, J, F, N]``) from noise in ``num_timesteps`` steps. ``imputation``
        (``"x0"`` | ``"xt"``) says how MDM's in-painting keys in ``model_kwargs['y']``
        are imposed; it has no effect without them."""
        if imputation not in IMPUTATIONS:
            raise ValueError(f"p_sample_loop: imputation must be one of {IMPUTATIONS}, got {imputation!r}")
        model_kwargs = model_kwargs or {}
        x = torch.randn(shape, generator=generator, device=device)
        given = self.constraint(model_kwargs, x)
        steps = range(self.num_timesteps - 1, -1, -1)
        from ..support.progress import bars_on  # stderr a terminal (or --progress)

        if bars_on(progress):
            from tqdm.auto import tqdm

            steps = tqdm(steps, desc="sampling", unit="step")
        for t in steps:
            if given is not None and imputation == "xt":
                noise = torch.randn(x.shape, generator=generator, device=x.device, dtype=x.dtype)
                tt = torch.full((x.shape[0],), t, device=x.device, dtype=torch.long)
                x = torch.where(given[0], self.q_sample(given[1], tt, noise), x)
            x = self.p_sample(model, x, t, model_kwargs, generator,
                              impute_x0=imputation == "x0" or t == 0)
        return x


#: how :meth:`SimpleDiffusion.p_sample_loop` imposes given frames (see docs/modules.md)
IMPUTATIONS = ("x0", "xt")


class ClassifierFreeGuidance(nn.Module):
    """``uncond + scale * (cond - uncond)``: two forward passes per step, as MDM samples."""

    def __init__(self, model: nn.Module, scale: float = 2.5) -> None:
        super().__init__()
        self.model, self.scale = model, scale

    def forward(self, x: torch.Tensor, timesteps: torch.Tensor, y: Optional[Dict[str, Any]] = None
                ) -> torch.Tensor:
        y = y or {}
        cond = self.model(x, timesteps, y)
        uncond = self.model(x, timesteps, {**y, "uncond": True})
        return uncond + self.scale * (cond - uncond)

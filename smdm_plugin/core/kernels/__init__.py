"""Fused operators of the method (:class:`~.dispatch.FusedOp`): ``smdm::vw_keyframes`` (Visvalingam–Whyatt
keyframe selection), the keyframe plan, the mask noise, the Lipschitz weights and the FSQ key codes.
Importing the package imports every op, so that :data:`~.dispatch.TRITON_KERNELS` lists every
Triton kernel (none of them imports ``triton`` before its first CUDA call)."""
from . import fsq_code, lipschitz_op, perturb, plan_op  # noqa: F401  (their Triton kernels register)
from .dispatch import TRITON_KERNELS, use_triton_kernels
from .vw import vw_keyframes

__all__ = ["vw_keyframes", "TRITON_KERNELS", "use_triton_kernels"]

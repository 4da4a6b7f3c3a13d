"""Fused operators of the method, registered with ``torch.library`` so that ``torch.compile`` sees one
op each: ``smdm::vw_keyframes`` (Visvalingam–Whyatt keyframe selection)."""
from .vw import vw_keyframes

__all__ = ["vw_keyframes"]

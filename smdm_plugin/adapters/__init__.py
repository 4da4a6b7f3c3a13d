"""Model surgery: turn a model family's dense model into its sparse keyframe version in place
(``sparsify`` / ``unsparsify``: MDM, DiP, priorMDM DoubleTake, MotionDiffuse) and wrap its
diffusion's training loss."""
from . import checkpoint as _checkpoint  # noqa: E402,F401  (registers the family dispatch with io's loader)

"""Model surgery: turn a model family's dense model into its sparse keyframe version in place
(``sparsify`` / ``unsparsify``: MDM, DiP, priorMDM DoubleTake, MotionDiffuse) and wrap its
diffusion's training loss."""

"""The sparse keyframe method itself, with no knowledge of any upstream model: keyframe selection
(VW and others), selection features, interpolation, the keyframe-only transformer and its attention
backends, Lipschitz sine MLPs, FSQ attention keys, the mask schedule, losses and the config."""

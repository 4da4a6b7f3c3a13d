"""File formats: BVH motion capture, sparse checkpoints (config beside the weights), HumanML3D
feature vectors."""

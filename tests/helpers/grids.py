"""The tiny ``smdm ablate`` grid (three variants, two steps) of the ablate tests."""

#: the grid's settings; ``GRID_HEAD + variants`` makes a grid of other variants
GRID_HEAD = """name: t
seed: 0
steps: 2
batch: 2
max_frames: 64
diffusion_steps: 5
model: {latent_dim: 16, num_layers: 1, num_heads: 2, ff_size: 32}
eval: {samples: 1, frames: 40}
variants:
"""
GRID = GRID_HEAD + """  - {name: dense, dense: true}
  - {name: sparse (VW)}
  - {name: uniform, sparse: {selector: uniform}}
"""

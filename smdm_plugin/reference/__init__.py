"""An in-package reference model: ``TinyMDM`` (MDM's module names and ``forward(x, timesteps, y)``)
and ``SimpleDiffusion`` (x0-predicting DDPM with MDM's ``training_losses`` interface), so that
everything runs without an upstream checkout."""

"""``smdm ablate --resume``: an interrupted variant continues from its checkpoint with the trainer's
mechanism (``smdm train --resume``), to the same result as one uninterrupted run."""
from __future__ import annotations

import pytest
import torch

from smdm_plugin.training import trainer as T
from smdm_plugin.training.data import MotionData

from helpers.paths import ROOT
from helpers.synthetic_data import write_humanml3d


def test_ablate_variant_resumes_with_the_trainers_mechanism(tmp_path):
    """smdm ablate --resume continues an interrupted variant from its checkpoint (the trainer's
    state, as smdm train --resume) instead of starting over, with the same result."""
    from smdm_plugin.apps import ablate
    from smdm_plugin.apps.ablate import grid

    cfg = grid.load_config(str(ROOT / "configs" / "ablations" / "quick.yaml"))
    cfg.update(steps=20, batch=2, model={**cfg["model"], "latent_dim": 16, "ff_size": 32, "num_layers": 1})
    cfg["eval"] = {**cfg["eval"], "samples": 2, "frames": 40}
    data = MotionData(str(write_humanml3d(tmp_path / "d", train=(60, 52, 48, 70), val=(44, 56))), 60, 40)
    variant = next(v for v in cfg["variants"] if v["name"] == "sparse (VW)")
    dev = torch.device("cpu")
    straight = ablate.run_variant(cfg, variant, data, dev)
    ckpt = tmp_path / "ckpt"
    real_step, calls = T.Trainer.step, []

    def interrupted(self):
        if self.step_count == 13:  # after the checkpoint at step 12 (every 2 steps)
            raise KeyboardInterrupt
        calls.append(self.step_count)
        return real_step(self)

    T.Trainer.step = interrupted
    try:
        with pytest.raises(KeyboardInterrupt):
            ablate.run_variant(cfg, variant, data, dev, checkpoint_dir=str(ckpt))
    finally:
        T.Trainer.step = real_step
    assert torch.load(ckpt / T.TRAIN_STATE_FILENAME, weights_only=True)["step"] == 12
    resumed = ablate.run_variant(cfg, variant, data, dev, checkpoint_dir=str(ckpt))
    assert resumed["resumed_at"] == 12 and straight["resumed_at"] == 0
    assert resumed["losses"] == straight["losses"] and resumed["val_loss"] == straight["val_loss"]
    assert resumed["ees"] == straight["ees"]

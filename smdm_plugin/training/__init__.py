"""Training the in-package TinyMDM (dense or sparse): data (:mod:`.data`: ``MotionSet``,
``MotionData``), the trainer (:mod:`.trainer`: ``Trainer``, ``TrainConfig``, ``race_fair``,
``load_trained``) and the held-out measures of a trained model (:mod:`.validation`); and timing
in-package models dense and sparse (:mod:`.workloads`, :mod:`.benchmark`, :mod:`.timing`). The
library behind ``smdm train``, ``smdm demo``, ``smdm ablate``, ``smdm eval`` and ``smdm bench``; it
sits between integrations and apps (docs/architecture.md)."""

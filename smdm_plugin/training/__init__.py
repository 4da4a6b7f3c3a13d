"""Training the in-package TinyMDM (dense or sparse): data (:mod:`.data`: ``MotionSet``,
``MotionData``), the trainer (:mod:`.trainer`: ``Trainer``, ``TrainConfig``, ``race_fair``,
``load_trained``) and the held-out measures of a trained model (:mod:`.validation`). The library
behind ``smdm train``, ``smdm demo``, ``smdm ablate`` and ``smdm eval``; it sits between
integrations and apps (docs/architecture.md)."""

"""What several test modules share, as one package (``import helpers``; tests/conftest.py puts tests/ on
``sys.path``). Test modules import from here and from tests/conftest.py's fixtures, never from each
other.

* ``paths``: the repository root, ../shared/data and the data sets in it.
* ``synthetic_data``: a small synthetic HumanML3D-format folder (``write_humanml3d``).
* ``text_encoder``: tiny random ``transformers`` text encoders built offline (``make_tiny_encoder``).
* ``noise``: the mask-noise cases of the ``smdm::perturb_mask`` tests and the rule written out (also run in a
  fresh interpreter).
* ``vw``: the VW cases and the heap reference on a batch.
* ``commands``: running ``smdm`` / ``torchrun`` in a subprocess, the tiny training options, folder snapshots.
* ``grids``: the tiny ``smdm ablate`` grid.
* ``ddp_worker.py``: the instrumented ``smdm train`` worker run under ``torchrun`` (a script, not imported).
"""

"""Applications on top of the library: the ``smdm`` command (bench, ablate, demo, run)."""

"""``python -m smdm_plugin <command>``: the ``smdm`` CLI (also under ``torchrun -m smdm_plugin``)."""
import sys

from .apps.cli import main

if __name__ == "__main__":
    sys.exit(main())

"""The ``smdm`` command (apps/cli.py ``COMMANDS``): one module or package per command, plus
``common/`` (what several commands share: argparse types, threads, provenance, animation, motion
files, the keyframe study, in-betweening). A command imports ``common`` and the layers below,
never another command (tests/package/test_architecture.py)."""

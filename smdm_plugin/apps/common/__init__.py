"""What several ``smdm`` commands share and no command owns: argparse types (:mod:`.args`), the
CPU thread default (:mod:`.threads`), result provenance, GIF rendering, motion files, the keyframe
study of motion capture, in-betweening of a model bundle. Commands import this; it imports no command."""

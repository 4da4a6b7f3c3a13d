"""What the method's config needs that is not the method: atomic file writes, config text (JSON /
YAML), argparse types and value ranges. Imports nothing of the package."""

"""Paired differences (sparse − dense, per seed) of a quality-versus-compute study, with 95% Student-t
intervals, family-corrected for the endpoints a config pre-registered (``primary``).

Reads the ``results.json`` that ``smdm ablate --config <study> --out DIR`` (or ``--resume
--report-only``) writes in each folder and prints one markdown block per folder: the primary
endpoints (Bonferroni simultaneous intervals, Holm-adjusted p), then every other (snapshot, metric)
cell with its own 95% interval and a Holm adjustment over those cells
(:mod:`smdm_plugin.apps.ablate.paired`). A seed only one variant finished is left out of the pairs.

    python scripts/decisive_paired.py results/decisive_t50 results/decisive_t10

A folder without ``results.json``, or one whose file is not a study's results (``{}``, a list, a
metric that is null), is one line on stderr naming the file and what was expected, exit status 2.
"""
from __future__ import annotations

import argparse
import sys
from typing import List, Optional, Sequence

from smdm_plugin.apps.ablate.paired import ResultsError, markdown_tables, read_results


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(prog="decisive_paired.py", description=__doc__.splitlines()[0])
    p.add_argument("folders", nargs="+", help="study results folders (each with results.json)")
    a = p.parse_args(argv)
    out: List[str] = []
    for folder in a.folders:
        try:
            out += markdown_tables(read_results(folder))
        except ResultsError as e:
            print(f"decisive_paired.py: error: {e}", file=sys.stderr)
            return 2
    sys.stdout.write("\n".join(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Whether a progress bar shows: the one decision every tqdm bar of the package asks.

A bar redraws its line with ``\\r``: on a terminal that is a moving bar, in a log file one line per
redraw. So a bar shows only when asked for (``progress``) and when the stream tqdm writes to
(stderr) is a terminal or a notebook; :data:`ALWAYS` (``--progress``) shows it whatever the stream."""
from __future__ import annotations

import sys
from typing import Any, Optional, Union

#: a ``progress`` value that shows bars whatever the stream is (``--progress``)
ALWAYS = "always"


def bars_on(progress: Union[bool, str], stream: Optional[Any] = None) -> bool:
    """Whether a bar shows: never when ``progress`` is false, always when it is :data:`ALWAYS`,
    else only when ``stream`` (default ``sys.stderr``, where tqdm writes) is a terminal or the
    process runs in a notebook (tqdm's widget)."""
    if not progress:
        return False
    if progress == ALWAYS:
        return True
    stream = sys.stderr if stream is None else stream
    try:
        if stream.isatty():
            return True
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False
    from tqdm.autonotebook import tqdm

    return tqdm.__module__ == "tqdm.notebook"

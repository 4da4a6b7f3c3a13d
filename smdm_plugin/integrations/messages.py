"""The plugin's warnings inside an upstream run: each reaches the terminal (stderr) and upstream's log
as one ``smdm: ...`` line, whatever logging upstream sets up."""
from __future__ import annotations

import logging
import sys
import warnings
from types import FrameType
from typing import Any, Callable, List, Optional

from ._hooks import wrap_once

PACKAGE = "smdm_plugin"
PREFIX = "smdm: "
#: the logger ``logging.captureWarnings(True)`` sends warnings to
WARNINGS_LOGGER = "py.warnings"
_SKIP = ("warnings", "_py_warnings", __name__)   # frames between the issuing code and the hook


def one_line(message: Any) -> str:
    """``smdm: <message>`` on one line (a message that already names smdm keeps its words:
    ``smdm compile: x`` -> ``smdm: compile: x``)."""
    text = " ".join(str(message).split("\n")).strip()
    if text.startswith("smdm:"):
        text = text[len("smdm:"):]
    elif text.startswith("smdm "):
        text = text[len("smdm "):]
    return PREFIX + text.strip()


def _issuer(frame: Optional[FrameType]) -> str:
    """The module name of the first frame outside ``warnings`` and this module."""
    while frame is not None and frame.f_globals.get("__name__") in _SKIP:
        frame = frame.f_back
    return "" if frame is None else str(frame.f_globals.get("__name__", ""))


def _in_package(module: str) -> bool:
    return module == PACKAGE or module.startswith(PACKAGE + ".")


def is_plugin_warning(msg: "warnings.WarningMessage", frame: Optional[FrameType] = None) -> bool:
    """Whether ``msg`` was issued by the plugin: by code of the ``smdm_plugin`` package (``frame``:
    the frame that issued it; default the caller's), or with a category defined there."""
    category = getattr(msg, "category", None)
    if _in_package(getattr(category, "__module__", "") or ""):
        return True
    return _in_package(_issuer(frame if frame is not None else sys._getframe(1)))


def _recording() -> bool:
    """Whether ``warnings.catch_warnings(record=True)`` is collecting warnings (it sets the
    implementation to a list's ``append``)."""
    return isinstance(getattr(warnings._showwarnmsg_impl, "__self__", None), list)  # type: ignore[attr-defined]


def _captured_by_logging() -> bool:
    """Whether ``logging.captureWarnings(True)`` is on (its ``showwarning`` is installed)."""
    return warnings.showwarning is getattr(logging, "_showwarning", None)


def _shown_elsewhere() -> bool:
    """Whether someone else's ``showwarning`` is installed (neither Python's nor logging's)."""
    sw = warnings.showwarning
    return sw is not getattr(warnings, "_showwarning_orig", sw) and not _captured_by_logging()


def _handlers(logger: logging.Logger, level: int) -> List[logging.Handler]:
    """The handlers a record of ``level`` from ``logger`` reaches (parents while propagating;
    ``NullHandler`` aside)."""
    out: List[logging.Handler] = []
    current: Optional[logging.Logger] = logger
    while current is not None:
        out += [h for h in current.handlers if not isinstance(h, logging.NullHandler) and level >= h.level]
        current = current.parent if current.propagate else None
    return out


def _writes_to_stderr(handler: logging.Handler) -> bool:
    return isinstance(handler, logging.StreamHandler) and getattr(handler, "stream", None) in (sys.stderr,
                                                                                              sys.__stderr__)


def show(msg: "warnings.WarningMessage") -> None:
    """Show a plugin warning as :func:`one_line` on stderr and, when logging captures warnings, in
    the handlers of ``py.warnings`` (see docs/modules.md)."""
    line = one_line(msg.message)
    on_stderr = False
    if _captured_by_logging():
        logger = logging.getLogger(WARNINGS_LOGGER)
        handlers = _handlers(logger, logging.WARNING) if logger.isEnabledFor(logging.WARNING) else []
        if handlers:
            logger.handle(logger.makeRecord(logger.name, logging.WARNING, str(msg.filename), int(msg.lineno or 0),
                                            line, None, None))
            on_stderr = any(_writes_to_stderr(h) for h in handlers)
    if not on_stderr:
        stream = sys.stderr
        if stream is not None:
            stream.write(line + "\n")
            stream.flush()


def _make_hook(original: Callable[[Any], None]) -> Callable[[Any], None]:
    def _showwarnmsg(msg: "warnings.WarningMessage") -> None:
        if _recording() or _shown_elsewhere() or not is_plugin_warning(msg, sys._getframe(1)):
            return original(msg)
        show(msg)
    return _showwarnmsg


def show_plugin_warnings() -> bool:
    """Install the hook (idempotent; see docs/modules.md). Returns whether it installed now."""
    return wrap_once(warnings, "_showwarnmsg", _make_hook)

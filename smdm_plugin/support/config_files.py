"""Config text in and out: JSON / YAML read (UTF-8, a BOM allowed) and parsed with errors naming the
file, the ``sparse:`` section of a file that has one, atomic writes. Knows no config field."""
from __future__ import annotations

import json
import os
from typing import Any, Collection, Dict, Mapping, Optional, Union

from .atomic import atomic_write_text
from .values import ConfigTypeError

PathLike = Union[str, "os.PathLike[str]"]
#: the file a sparse config is saved as beside a checkpoint
CONFIG_FILENAME = "sparse_config.json"


def read_mapping(src: PathLike, fmt: str, is_path: bool = False, fields: Collection[str] = ()
                 ) -> "tuple[Dict[str, Any], Optional[str]]":
    """``(the config mapping, the file it came from or None)`` from JSON / YAML text or a file
    (``fmt``: ``json`` or ``yaml``; a string that looks like a path is read as one); ``fields``:
    :func:`config_section`'s."""
    where: Optional[str] = None
    if is_path or not isinstance(src, str) or looks_like_path(src, fmt):
        where = os.fspath(src)
        text = read_text(where)
    else:
        text = src
    return config_section(parse(text, fmt, where), where, fields), where


def config_path(path: PathLike) -> str:
    """``path``, or ``sparse_config.json`` inside it when it is a folder."""
    path = os.fspath(path)
    return os.path.join(path, CONFIG_FILENAME) if os.path.isdir(path) else path


def dump(data: Mapping[str, Any], fmt: str, path: Optional[PathLike] = None) -> str:
    """``data`` as JSON (indented, sorted) or YAML text; also written to ``path`` (atomically,
    replacing it) if given."""
    if fmt == "json":
        text = json.dumps(dict(data), indent=2, sort_keys=True)
        if path is not None:
            atomic_write_text(path, text + "\n")
        return text
    import yaml

    text = yaml.safe_dump(dict(data), sort_keys=True)
    if path is not None:
        atomic_write_text(path, text)
    return text


def looks_like_path(s: str, fmt: str) -> bool:
    if "\n" in s:
        return False
    if os.path.exists(s) or s.strip().endswith((".json", ".yaml", ".yml")):
        return True
    return fmt == "json" and not s.lstrip().startswith(("{", "["))


def read_text(path: str) -> str:
    if not os.path.exists(path):
        raise FileNotFoundError(f"SparseConfig: no such config file: {path!r}")
    if os.path.isdir(path):
        raise IsADirectoryError(f"SparseConfig: {path!r} is a folder without {CONFIG_FILENAME}")
    with open(path, "rb") as f:
        raw = f.read()
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as e:
        raise ValueError(f"{path}: not UTF-8 text (byte {e.start}: {e.reason})") from None


def parse(text: str, fmt: str, where: Optional[str]) -> Any:
    label = where or f"SparseConfig.from_{fmt}"
    if fmt == "json":
        try:
            return json.loads(text)
        except json.JSONDecodeError as e:
            raise ValueError(f"{label}: not valid JSON: {e}") from None
    import yaml

    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise ValueError(f"{label}: not valid YAML: {' '.join(str(e).split())}") from None


def config_section(data: Any, where: Optional[str] = None, fields: Collection[str] = ()) -> Dict[str, Any]:
    """The config mapping of a parsed file: its top-level ``sparse:`` section when there is one
    (other top-level sections are then allowed, but not a top-level key among ``fields``, the config's
    own: which of the two would apply is not clear), else the whole mapping (empty file: {})."""
    label = where or "SparseConfig"
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise ConfigTypeError(f"{label}: expected a mapping of SparseConfig options, got {type(data).__name__}")
    if "sparse" in data:
        beside = [k for k in data if k in fields]
        if beside:
            raise ConfigTypeError(f"{label}: option(s) {', '.join(map(repr, beside))} at the top level beside "
                                  "the 'sparse' section; put them inside it (the section is the config)")
        section = data["sparse"]
        if section is None:
            return {}
        if not isinstance(section, Mapping):
            raise ConfigTypeError(f"{label}: the 'sparse' section must be a mapping of SparseConfig "
                                  f"options, got {type(section).__name__}")
        return dict(section)
    return dict(data)



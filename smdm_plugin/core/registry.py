"""One small registry type for every extension point (selectors, attention backends, model families).

A :class:`Registry` maps names to entries. The built-in entries are registered by the module that
defines the registry (or one that imports every built-in), so that reading a registry never depends
on what happened to be imported before. :meth:`Registry.choices` is a live view of the names for
validation (``SparseConfig`` checks ``selector`` / ``attention_backend`` against it, argparse uses it
as ``choices``): a newly registered entry is a valid value at once.
"""
from __future__ import annotations

from typing import Callable, Dict, Generic, Iterator, List, Mapping, Optional, Tuple, TypeVar

T = TypeVar("T")

#: what an entry's attribute may hold (a :class:`Registry`'s ``fields``), by the words its errors use
KINDS: Dict[str, Callable[[object], bool]] = {
    "callable": callable,
    "callable or None": lambda v: v is None or callable(v),
    "a bool": lambda v: isinstance(v, bool),
}


class Registry(Generic[T]):
    """Entries of one kind (``what``, for messages) by name. ``fill()``, when given, runs before
    every read: it adds the entries that come from elsewhere (the model families' registrations).
    What an entry holds, checked when it is registered: an instance of ``holds`` whose attributes
    ``fields`` maps to a kind of :data:`KINDS` (e.g. ``{"fn": "callable"}``); ``reserved``: names
    that mean something else where the names are used (e.g. ``auto``)."""

    def __init__(self, what: str, fill: Optional[Callable[[], None]] = None, *, holds: Optional[type] = None,
                 fields: Optional[Mapping[str, str]] = None, reserved: Tuple[str, ...] = ()) -> None:
        self.what, self.holds, self.fields, self.reserved = what, holds, dict(fields or {}), tuple(reserved)
        self._items: Dict[str, T] = {}
        self._fill = fill
        self._filling = False

    def _filled(self) -> Dict[str, T]:
        if self._fill is not None and not self._filling:
            self._filling = True
            try:
                self._fill()
            finally:
                self._filling = False
        return self._items

    def register(self, name: str, entry: T, *, replace: bool = False) -> T:
        """Add ``entry`` under ``name`` (a taken name is a ``ValueError`` unless ``replace``), checked."""
        if not isinstance(name, str) or not name or name != name.strip():
            raise ValueError(f"register {self.what}: name must be a non-empty string without surrounding "
                             f"spaces, got {name!r}")
        if name in self.reserved:
            raise ValueError(f"register {self.what}: {name!r} is a reserved name")
        if name in self._items and not replace:   # (not filled: registering loads nothing)
            raise ValueError(f"register {self.what}: {name!r} is already registered (pass replace=True)")
        if self.holds is not None and not isinstance(entry, self.holds):
            raise TypeError(f"register {self.what} {name!r}: expected a {self.holds.__name__}, "
                            f"got {type(entry).__name__}")
        for field, kind in self.fields.items():
            value = getattr(entry, field)
            if not KINDS[kind](value):
                raise TypeError(f"register {self.what} {name!r}: {field} must be {kind}, got {value!r}")
        self._items[name] = entry
        return entry

    def unregister(self, name: str) -> None:
        self._items.pop(name, None)

    def get(self, name: str) -> T:
        """The entry named ``name``; an unknown name is a ``ValueError`` listing the registered ones."""
        items = self._filled()
        if name not in items:
            raise ValueError(f"unknown {self.what} {name!r}; registered: {', '.join(items)}")
        return items[name]

    def names(self) -> Tuple[str, ...]:
        return tuple(self._filled())

    def entries(self) -> List[T]:
        return list(self._filled().values())

    def __contains__(self, name: object) -> bool:
        return name in self._filled()

    def choices(self, *extra: str) -> "Choices":
        """A live tuple-like view of ``extra`` + the registered names (for validation)."""
        return Choices(self.names, extra)


class Choices:
    """Tuple-like, always current: ``extra`` names (e.g. ``auto``) then ``names()``."""

    def __init__(self, names: Callable[[], Tuple[str, ...]], extra: Tuple[str, ...] = ()) -> None:
        self.names, self.extra = names, tuple(extra)

    def _names(self) -> Tuple[str, ...]:
        return self.extra + tuple(n for n in self.names() if n not in self.extra)

    def __iter__(self) -> Iterator[str]:
        return iter(self._names())

    def __len__(self) -> int:
        return len(self._names())

    def __getitem__(self, i):
        return self._names()[i]

    def __contains__(self, name: object) -> bool:
        return name in self._names()

    def __bool__(self) -> bool:
        return True

    def __eq__(self, other: object) -> bool:
        return tuple(self) == tuple(other) if isinstance(other, (tuple, list, Choices)) else NotImplemented

    def __hash__(self) -> int:
        return id(self)

    def __repr__(self) -> str:
        return repr(self._names())

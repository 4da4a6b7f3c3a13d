"""One small registry type for every extension point (selectors, attention backends, model families).

A :class:`Registry` maps names to entries. The built-in entries are registered by the module that
defines the registry (or one that imports every built-in), so that reading a registry never depends
on what happened to be imported before. :meth:`Registry.choices` is a live view of the names for
validation (``SparseConfig`` checks ``selector`` / ``attention_backend`` against it, argparse uses it
as ``choices``): a newly registered entry is a valid value at once.
"""
from __future__ import annotations

from typing import Callable, Dict, Generic, Iterator, List, Optional, Tuple, TypeVar

T = TypeVar("T")


class Registry(Generic[T]):
    """Entries of one kind (``what``, for messages) by name. ``fill()``, when given, runs before
    every read: it adds the entries that come from elsewhere (the model families' registrations)."""

    def __init__(self, what: str, fill: Optional[Callable[[], None]] = None) -> None:
        self.what = what
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
        """Add ``entry`` under ``name`` (a taken name is a ``ValueError`` unless ``replace``)."""
        if not isinstance(name, str) or not name.strip():
            raise ValueError(f"register {self.what}: name must be a non-empty string, got {name!r}")
        if name in self._items and not replace:   # (not filled: registering loads nothing)
            raise ValueError(f"register {self.what}: {name!r} is already registered (pass replace=True)")
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

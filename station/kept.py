"""Results kept by the content of their inputs, the station's one such store: a computation that is a
function of arrays and settings only is not done again in a process for the same content (a step's
sine fits, ``ident/response``; the model gap's decomposition of a recording, ``discrepancy/data``; the
paper's swarm runs, ``ident/paper/identify``).  A key is the SHA-256 of the arrays (dtype, shape,
bytes) and of the settings' repr; a store keeps its last ``size`` results (least recently used dropped
first)."""

from __future__ import annotations

import hashlib
import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import numpy as np

T = TypeVar("T")


def content_key(*arrays: Any, settings: tuple[Any, ...] = ()) -> bytes:
    """Digest of arrays (each as a contiguous array: dtype, shape, bytes) and of ``settings``' repr."""
    h = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.data)
    h.update(repr(settings).encode())
    return h.digest()


class Kept(Generic[T]):
    """The last ``size`` results by key; ``copy`` gives the caller a result it may change (arrays
    copied) and is applied on the way in and out.  Thread-safe; a computation that raises keeps nothing."""

    def __init__(self, size: int, copy: Callable[[T], T]) -> None:
        self.size, self._copy = size, copy
        self._kept: OrderedDict[bytes, T] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, key: bytes, compute: Callable[[], T]) -> T:
        """The result kept under ``key``, else ``compute()`` kept."""
        with self._lock:
            kept = self._kept.get(key)
            if kept is not None:
                self._kept.move_to_end(key)
        if kept is not None:
            return self._copy(kept)
        value = compute()
        with self._lock:
            self._kept[key] = self._copy(value)
            while len(self._kept) > self.size:
                self._kept.popitem(last=False)
        return value

    def clear(self) -> None:
        """Drop every kept result."""
        with self._lock:
            self._kept.clear()

    def __len__(self) -> int:
        return len(self._kept)

"""
The buffer directories this process holds open for writing (one :class:`~sb3_lifelong.buffers.rowstore.RowStore`
each, the holder of the directory's writer lock), and what a child made by ``os.fork()`` may not do with the copies
of them it inherits (:class:`ForkedWriterError`). Like the rest of the store, it imports only the standard library.
"""

import os
import weakref
from typing import Any, Optional

#: a RowStore (not imported: the store imports this module)
RowStore = Any

# writer stores of this process by directory, so that unpickling can take a directory over from a stale object
_WRITERS: "weakref.WeakValueDictionary[str, RowStore]" = weakref.WeakValueDictionary()


def writer_of(path: str) -> Optional[RowStore]:
    """:return: the store of this process that holds ``path`` open for writing (its directory's lock), or None"""
    return _WRITERS.get(path)


def register(path: str, store: RowStore) -> None:
    """``store`` took the writer lock of the directory ``path``."""
    _WRITERS[path] = store


def forget(path: str, store: RowStore) -> None:
    """``store`` released the writer lock of ``path`` (another store that holds it since stays registered)."""
    if _WRITERS.get(path) is store:
        del _WRITERS[path]


class ForkedWriterError(RuntimeError):
    """
    A directory buffer opened for writing in one process was used to write (``add``, ``flush``, ``close``, a commit)
    in another one: a child made by ``os.fork()`` (or a ``multiprocessing`` "fork" worker) holds a copy of the
    writer, whose pending rows and committed state the parent goes on changing. The child's writes would be
    overwritten by the parent's next commit, and its exit would commit the parent's pending rows: they are refused.
    Reading and sampling in the child work as before.
    """


def _forget_writers_in_child() -> None:
    """
    ``os.fork()``, in the child: the child's copies of this process's writers do not own their directories. Their
    lock files are closed without unlocking (``flock`` locks belong to the open file, which the parent keeps locked:
    the lock is the parent's until the parent releases it, however long the child lives), and they are forgotten as
    writers of this process.
    """
    for store in list(_WRITERS.values()):
        lock_file = store._state.lock_file
        store._state.lock_file = None
        if lock_file is not None:
            try:
                lock_file.close()  # close(2) of the child's descriptor only: the parent's lock stays
            except OSError:  # pragma: no cover
                pass
    _WRITERS.clear()


if hasattr(os, "register_at_fork"):  # POSIX
    os.register_at_fork(after_in_child=_forget_writers_in_child)

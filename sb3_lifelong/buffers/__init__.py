"""
The lifelong replay buffer: every transition of a robot's life, in memory or in a crash-safe directory.

Layers, from the bottom:

- the row store, which knows nothing of SB3 and imports only numpy and the standard library:
  :mod:`~sb3_lifelong.buffers.files` (writing, fsync, the atomic JSON write), :mod:`~sb3_lifelong.buffers.manifest`
  (the on-disk format: the manifest, its validation, the format's constants), :mod:`~sb3_lifelong.buffers.layouts`
  (where rows live: in memory, one file per field, one file per chunk), :mod:`~sb3_lifelong.buffers.readers` (memory
  maps or positioned reads) and :mod:`~sb3_lifelong.buffers.rowstore` (``RowStore``: the commit protocol, the source
  table and the stream ids).
- :mod:`~sb3_lifelong.buffers.interop`: d4rl-style dicts, ``.npz`` files and Minari datasets, in and out, over any
  buffer's public methods; :mod:`~sb3_lifelong.buffers.schema`: the store's fields for the spaces, and the spaces'
  description in the manifest.
- :mod:`~sb3_lifelong.buffers.sampling`: the read side shared by buffers and views (sampling with per-source weights
  and reward scales, n-step returns, next actions, exports); :mod:`~sb3_lifelong.buffers.lifelong`:
  :class:`LifelongReplayBuffer`, the SB3 ``ReplayBuffer`` over a store (``add`` from SB3's collection loop, sources,
  commits), with :mod:`~sb3_lifelong.buffers.add_checks`, what ``add`` accepts.
- :mod:`~sb3_lifelong.buffers.views`: several buffers as one, read-only (:class:`LifelongBufferView`) or merged
  into a new buffer (:func:`merge_buffers`); :mod:`~sb3_lifelong.buffers.loading`: the one way in of offline data.

A buffer directory holds one file per field and chunk (``observations``, ``actions``, ``rewards``, ``flags``,
``sources``, ``streams``, ...) and a ``manifest.json`` that is replaced atomically at every commit: what the manifest
lists is on disk, checksummed; rows written after the last commit are dropped when the directory is reopened. The
full description (format, crash guarantees, read modes) is ``docs/modules/buffer.md``.
"""

from sb3_lifelong.buffers.files import CommitNotDurableError
from sb3_lifelong.buffers.lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers.manifest import BufferFormatError
from sb3_lifelong.buffers.views import LifelongBufferView, merge_buffers
from sb3_lifelong.buffers.writers import ForkedWriterError

__all__ = [
    "BufferFormatError",
    "CommitNotDurableError",
    "ForkedWriterError",
    "LifelongBufferView",
    "LifelongReplayBuffer",
    "merge_buffers",
]

"""
The lifelong replay buffer: every transition of a robot's life, in memory or in a crash-safe directory.

Layers, from the bottom:

- :mod:`~sb3_lifelong.buffers.storage`: the on-disk format and the crash-safe row store (fields, chunks, the
  manifest and its atomic commits, checksums, the source table and the stream ids). It knows nothing of SB3.
- :mod:`~sb3_lifelong.buffers.lifelong`: :class:`LifelongReplayBuffer`, the SB3 ``ReplayBuffer`` over a store
  (``add`` from SB3's collection loop, sampling with per-source weights and reward scales, n-step returns).
- :mod:`~sb3_lifelong.buffers.views`: several buffers as one, read-only (:class:`LifelongBufferView`) or merged
  into a new buffer (:func:`merge_buffers`).
- :mod:`~sb3_lifelong.buffers.interop`: d4rl-style dicts, ``.npz`` files and Minari datasets, in and out.

A buffer directory holds one file per field and chunk (``observations``, ``actions``, ``rewards``, ``flags``,
``sources``, ``streams``, ...) and a ``manifest.json`` that is replaced atomically at every commit: what the manifest
lists is on disk, checksummed; rows written after the last commit are dropped when the directory is reopened. The
full description (format, crash guarantees, read modes) is ``docs/modules/buffer.md``.
"""

from sb3_lifelong.buffers.lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers.storage import BufferFormatError, CommitNotDurableError
from sb3_lifelong.buffers.views import LifelongBufferView, merge_buffers

__all__ = ["BufferFormatError", "CommitNotDurableError", "LifelongBufferView", "LifelongReplayBuffer", "merge_buffers"]

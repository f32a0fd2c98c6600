"""
Older import path of the lifelong buffer, kept so that existing imports and buffers pickled by earlier versions
(``save_replay_buffer``) still load. The buffer lives in :mod:`sb3_lifelong.buffers`.
"""

from sb3_lifelong.buffers import (
    BufferFormatError,
    CommitNotDurableError,
    LifelongBufferView,
    LifelongReplayBuffer,
    merge_buffers,
)
from sb3_lifelong.buffers.lifelong import _LifelongSampler, _RunIndex  # noqa: F401  (names in older pickles)

__all__ = ["BufferFormatError", "CommitNotDurableError", "LifelongBufferView", "LifelongReplayBuffer", "merge_buffers"]

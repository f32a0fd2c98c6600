"""
Older import path of the buffer's storage engine, kept so that existing imports and pickled buffers still load:
this name is the module :mod:`sb3_lifelong.buffers.storage` itself.
"""

import sys

from sb3_lifelong.buffers import storage

sys.modules[__name__] = storage

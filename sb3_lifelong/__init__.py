import os

from sb3_lifelong.bc import BC
from sb3_lifelong.buffers import LifelongReplayBuffer
from sb3_lifelong.crr import CRR
from sb3_lifelong.mpo import MPO

# Read version from file
version_file = os.path.join(os.path.dirname(__file__), "version.txt")
with open(version_file) as file_handler:
    __version__ = file_handler.read().strip()

__all__ = [
    "BC",
    "CRR",
    "MPO",
    "LifelongReplayBuffer",
]

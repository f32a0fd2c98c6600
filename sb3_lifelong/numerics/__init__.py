"""
The arithmetic of the updates, apart from what they compute: scoring many actions per state in one critic call and its
bf16 copy (``scoring``), elementwise operations torch runs slowly on a CPU (``fast_ops``), loss computations compiled
with ``torch.compile`` and checked against eager (``compiling``), what this machine multiplies fast (``hardware``), and
the settings that choose among them (``settings``: :class:`ComputeSettings`, MPO's and CRR's ``compute``).
"""

from sb3_lifelong.numerics.settings import ComputeSettings

__all__ = ["ComputeSettings"]

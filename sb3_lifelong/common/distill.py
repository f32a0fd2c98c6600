"""
The old home of the Offline Distillation Pipeline, kept as a public import path
(``from sb3_lifelong.common.distill import distill``): it now lives in :mod:`sb3_lifelong.distill`, above the
algorithms.
"""

from sb3_lifelong.distill import DistillSource, distill

__all__ = ["DistillSource", "distill"]

"""
Keeps a pinned study tree's ``scoring_dtype="auto"`` on float32 on a CPU with native bf16 (AVX-512 BF16 or AMX).

The imbalance dose study's seeds 0 and 1 were collected and distilled on a CPU without native bf16, where "auto" is
float32. Its later seeds run the same pinned code; on a CPU with native bf16, "auto" would give them bf16 scoring
passes, an arithmetic the first seeds did not have. Put this folder after the pinned tree on ``PYTHONPATH``
(``STUDY_TREE=/work/study:<repo>/benchmarks/studies/imbalance_dose/study_float32`` for ``collect_in_parts.sh``; the same for
``imbalance_dose.py run``): Python imports ``sitecustomize`` at start-up, and this one makes the pinned tree's
hardware check answer "no native bf16".
"""

import sys

import sb3_lifelong.numerics.hardware as _hardware
import sb3_lifelong.numerics.scoring as _scoring

_hardware.cpu_has_fast_bf16 = lambda: False  # type: ignore[assignment]
_scoring.cpu_has_fast_bf16 = lambda: False  # type: ignore[assignment]
print(f"study_float32: scoring_dtype='auto' is float32 in {_scoring.__file__}", file=sys.stderr)

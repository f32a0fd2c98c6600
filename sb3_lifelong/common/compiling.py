"""
A loss computation compiled with ``torch.compile`` (inductor) once a run is long enough to pay for the compilation,
and eager everywhere else (:class:`LazyCompiled`).

Compiling fuses the elementwise work around the matrix products (the LayerNorm, tanh, softmax, log-likelihood) and
plans the buffers of the forward and backward passes. Measured on one CRR student of the imbalance dose study
(``benchmarks/bench_compiled_losses.py``; AMD EPYC, AVX2, one thread): 1.21x faster updates (rounds 1.16-1.35x), after
31 s of compiling once per process. A short run (the tests, a demo) would spend more on compiling than it saves, so
``"auto"`` compiles only when the ``learn`` call under way has at least :data:`AUTO_MIN_UPDATES` updates to go.
"""

import shutil
import warnings
from typing import Any, Callable, Optional

import torch as th

COMPILE_CHOICES = ("auto", True, False)
#: ``compile_losses="auto"`` compiles when the run under way has at least this many updates left: the compilation
#: (30-60 s on a 2-core machine) is then under 5 % of the run's time at a student's 25 ms per update
AUTO_MIN_UPDATES = 50_000


def can_compile(device: th.device) -> bool:
    """:return: whether inductor can compile for ``device`` here: a CPU needs a C++ compiler, a GPU needs triton"""
    if device.type == "cpu":
        return any(shutil.which(name) for name in ("g++", "c++", "clang++"))
    if device.type == "cuda":
        try:
            import triton  # noqa: F401
        except ImportError:
            return False
        return True
    return False


class LazyCompiled:
    """
    ``function``, compiled with ``torch.compile`` on first use when asked to, eager otherwise. A compilation or a
    first compiled call that fails warns once and leaves the function eager for good (same results, the eager speed).

    :param function: a pure computation of tensors (its inputs' shapes fixed: compiled with ``dynamic=False``)
    :param name: what the warning calls it
    """

    def __init__(self, function: Callable, name: str) -> None:
        self.function = function
        self.name = name
        #: the compiled function once compiled; None before, and for good after a failure
        self.compiled: Optional[Callable] = None
        self.failed = False

    def __call__(self, compile_now: bool, *args: Any) -> Any:
        """
        :param compile_now: whether to run the compiled function (compiling it first when it is not yet)
        :param args: the function's arguments
        :return: the function's result
        """
        if not compile_now or self.failed:
            return self.function(*args)
        first = self.compiled is None
        if first:
            self.compiled = th.compile(self.function, dynamic=False)
        assert self.compiled is not None
        if not first:
            return self.compiled(*args)
        try:
            return self.compiled(*args)
        except Exception as error:  # inductor's failures are of many kinds; the eager function is always right
            self.failed, self.compiled = True, None
            warnings.warn(f"torch.compile of {self.name} failed ({type(error).__name__}: {error}); it runs eagerly")
            return self.function(*args)

"""
A loss computation compiled with ``torch.compile`` (inductor) once a run is long enough to pay for the compilation,
and eager everywhere else (:class:`LazyCompiled`).

Compiling fuses the elementwise work around the matrix products (the LayerNorm, tanh, softmax, log-likelihood) and
plans the buffers of the forward and backward passes. Measured on an AMD EPYC without AMX, one thread
(``benchmarks/results/fast_paths.md``): a CRR student of the imbalance dose study 1.21-1.31x faster per update than
before, MPO 1.09x (0.77x -> 0.84x SAC on Walker2d), after 30-40 s of compiling once per process. A short run (the
tests, a demo) would spend more on compiling than it saves, so ``"auto"`` compiles only when the ``learn`` call under
way has at least :data:`AUTO_MIN_UPDATES` steps to go (environment steps online, updates offline).
"""

import contextlib
import shutil
import warnings
from typing import Any, Callable, ContextManager, Optional, Union

import torch as th

COMPILE_CHOICES = ("auto", True, False)
#: ``compile_losses="auto"`` compiles when the ``learn`` call under way has at least this many steps left (updates
#: offline): the compilation (30-60 s on a 2-core machine) is then under 5 % of the run's time at 25 ms per update
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
    ``function``, compiled with ``torch.compile`` on first use when asked to, eager otherwise. A call of the compiled
    function that fails (the compilation of its forward or backward graph, or a recompilation) warns once and leaves
    the function eager for good: that call runs eagerly, with the same arguments. The backward graph is compiled with
    the forward one (torch compiles it lazily, at the first ``backward``, by default), so that its failure is caught
    here too; a failure later inside ``backward`` itself is not.

    :param function: a pure computation of tensors (its inputs' shapes fixed: compiled with ``dynamic=False``)
    :param name: what the warning calls it
    """

    def __init__(self, function: Callable, name: str) -> None:
        self.function = function
        self.name = name
        #: the compiled function once compiled; None before, and for good after a failure
        self.compiled: Optional[Callable] = None
        self.failed = False

    def wanted(self, setting: Union[bool, str], steps_to_go: int, device: th.device) -> bool:
        """
        :param setting: the algorithm's ``compile_losses``: ``True``, ``False`` or ``"auto"``
        :param steps_to_go: what the ``learn`` call under way has left to do
        :param device: where the function runs
        :return: whether a ``train`` call runs the compiled function: never after a failure; with ``"auto"``, once
            compiled, or when ``steps_to_go`` is at least :data:`AUTO_MIN_UPDATES` and inductor can compile here
        """
        if setting is False or self.failed:
            return False
        if setting is True or self.compiled is not None:
            return True
        return steps_to_go >= AUTO_MIN_UPDATES and can_compile(device)

    def compile(self) -> None:
        """Compile at the next call whatever the setting's rule (e.g. for a run continued from a compiled one)."""
        if self.compiled is None and not self.failed:
            self.compiled = th.compile(self.function, dynamic=False)

    def __call__(self, compile_now: bool, *args: Any) -> Any:
        """
        :param compile_now: whether to run the compiled function (compiling it first when it is not yet)
        :param args: the function's arguments
        :return: the function's result
        """
        if not compile_now or self.failed:
            return self.function(*args)
        self.compile()
        assert self.compiled is not None
        try:
            with _backward_compiled_with_forward():
                return self.compiled(*args)
        except Exception as error:  # inductor's failures are of many kinds; the eager function is always right
            self.failed, self.compiled = True, None
            warnings.warn(f"torch.compile of {self.name} failed ({type(error).__name__}: {error}); it runs eagerly")
            return self.function(*args)


def _backward_compiled_with_forward() -> ContextManager:
    """
    A context in which torch compiles a graph's backward with its forward (``force_non_lazy_backward_lowering``, a
    setting of torch's private ``_functorch.config``); a context that does nothing where this torch has no such
    setting (the backward is then compiled at the first ``backward``).
    """
    config = getattr(getattr(th, "_functorch", None), "config", None)
    if config is None or not hasattr(config, "force_non_lazy_backward_lowering"):
        return contextlib.nullcontext()
    return config.patch(force_non_lazy_backward_lowering=True)

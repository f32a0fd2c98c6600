"""
A loss computation compiled with ``torch.compile`` (inductor) once a run is long enough to pay for the compilation,
and eager everywhere else (:class:`LazyCompiled`).

Compiling fuses the elementwise work around the matrix products (the LayerNorm, tanh, softmax, log-likelihood) and
plans the buffers of the forward and backward passes. Measured on an AMD EPYC without AMX, one thread
(``benchmarks/results/speed/fast_paths.md``): a CRR student of the imbalance dose study 1.21-1.31x faster per update than
before, MPO 1.09x (0.77x -> 0.84x SAC on Walker2d), after 30-40 s of compiling once per process. A short run (the
tests, a demo) would spend more on compiling than it saves, so ``"auto"`` compiles only when the ``learn`` call under
way has at least :data:`AUTO_MIN_UPDATES` steps to go (environment steps online, updates offline).
"""

import contextlib
import shutil
import warnings
from collections.abc import Iterable
from typing import Any, Callable, ContextManager, Optional, Union

import torch as th

COMPILE_CHOICES = ("auto", True, False)
#: ``compile_losses="auto"`` compiles when the ``learn`` call under way has at least this many steps left (updates
#: offline): the compilation (30-60 s on a 2-core machine) is then under 5 % of the run's time at 25 ms per update
AUTO_MIN_UPDATES = 50_000
#: the first compiled call's outputs and gradients must be within this much of the eager call's, relative to the
#: largest of each (float32 rounding is about 1e-6 of it; a wrongly compiled backward has given 0.2)
CHECK_TOLERANCE = 1e-3
#: the check's tolerance where the gradient passes multiply in bfloat16 (``train_dtype``): each product's operands are
#: rounded to 2^-8, and the compiled graph rounds in other places than the eager one (measured: 1.0e-3 to 3.4e-3 of a
#: parameter's largest gradient on an AMX Xeon, 2.9e-3 on an EPYC with AVX-512 BF16), while a wrongly compiled
#: backward is still far above it (0.12-0.28)
LOW_PRECISION_CHECK_TOLERANCE = 2.0**-6
#: a parameter's gradient is compared against its own largest component, or this fraction of the largest of all
#: parameters' if that is more; an output against its own largest value, or this much absolutely if that is more
#: (a logged statistic that is a difference of nearly equal numbers, e.g. a KL of 1e-9, is rounding noise)
GRADIENT_FLOOR = 1e-5
OUTPUT_FLOOR = 1e-6


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

    Before the compiled function is used, its first call is checked against the eager one on the same arguments: the
    outputs, and the gradients of a fixed random projection of the outputs with respect to ``parameters``. Where they
    differ by more than ``tolerance`` of the largest value (a compiler that gets a backward wrong on this
    CPU), it warns, naming the parameters, and the function stays eager for good. Only the first compilation is
    checked, not a recompilation that later arguments may cause (the updates' shapes are fixed).

    :param function: a pure computation of tensors (its inputs' shapes fixed: compiled with ``dynamic=False``)
    :param name: what the warning calls it
    :param parameters: the leaves the function's outputs are differentiated with respect to in training, named (for
        the first call's check); None: outputs only
    :param tolerance: the first call's check's relative tolerance (:data:`CHECK_TOLERANCE`; for a function that
        multiplies in bfloat16 in its gradient passes, :data:`LOW_PRECISION_CHECK_TOLERANCE`)
    """

    def __init__(
        self,
        function: Callable,
        name: str,
        parameters: Optional[Callable[[], Iterable[tuple[str, th.Tensor]]]] = None,
        tolerance: float = CHECK_TOLERANCE,
    ) -> None:
        self.function = function
        self.name = name
        self.parameters = parameters
        self.tolerance = tolerance
        #: whether the compiled function passed the first call's check (:meth:`check`)
        self.checked = False
        #: the compiled function once compiled; None before, and for good after a failure
        self.compiled: Optional[Callable] = None
        self.failed = False
        #: why the compiled function was given up (the warning's text); None while it was not
        self.failure: Optional[str] = None

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
                if not self.checked:
                    self.check(*args)
                return self.compiled(*args)
        except Exception as error:  # inductor's failures are of many kinds; the eager function is always right
            self.failed, self.compiled = True, None
            self.failure = f"torch.compile of {self.name} failed ({type(error).__name__}: {error}); it runs eagerly"
            warnings.warn(self.failure)
            return self.function(*args)

    def check(self, *args: Any) -> None:
        """
        Run the compiled and the eager function on ``args`` and compare their outputs and the gradients of the same
        random projection of the outputs. The global random state is kept; an output written into an argument is
        written twice, the compiled function's last.

        :param args: the function's arguments
        :raises CompiledMismatch: an output or a gradient differs by more than ``tolerance`` of its largest
        """
        assert self.compiled is not None
        named = [(name, p) for name, p in (self.parameters() if self.parameters else []) if p.requires_grad]
        devices = sorted({t.device.index or 0 for t in _tensors(args) if t.device.type == "cuda"})
        with th.random.fork_rng(devices=devices):  # (only the devices in use: forking every GPU would start CUDA)
            eager = [t.clone() for t in _tensors(self.function(*args))]  # kept apart from an output written in place
            compiled = _tensors(self.compiled(*args))
        if len(eager) != len(compiled):
            raise CompiledMismatch(f"{len(compiled)} output tensors, where the eager function gives {len(eager)}")
        for index, (e, c) in enumerate(zip(eager, compiled)):
            _compare(f"output {index}", c.detach(), e.detach(), self.tolerance)
        differentiable = [i for i, e in enumerate(eager) if e.requires_grad and e.is_floating_point()]
        if not named or not differentiable:
            self.checked = True
            return
        generator = th.Generator(device=eager[differentiable[0]].device).manual_seed(0)
        weights = {i: th.randn(eager[i].shape, generator=generator, device=eager[i].device) for i in differentiable}
        leaves = [p for _, p in named]
        gradients = []
        for outputs in (eager, compiled):
            projection = sum((outputs[i] * weights[i]).sum() for i in differentiable)
            grads = th.autograd.grad(projection, leaves, allow_unused=True)  # type: ignore[arg-type]
            gradients.append([th.zeros_like(p) if g is None else g for p, g in zip(leaves, grads)])
        # each parameter against its own largest gradient (a small actor's beside a large critic's is checked too), with
        # a floor of GRADIENT_FLOOR of the largest of all, under which rounding noise is all there is to compare
        scale = max((float(g.abs().max()) for g in gradients[0] if g.numel()), default=0.0)
        wrong = []
        for (name, _), e, c in zip(named, *gradients):
            if e.numel():
                difference, own = float((c - e).abs().max()), float(e.abs().max())
                if not difference <= self.tolerance * max(own, GRADIENT_FLOOR * scale):  # NaN fails too
                    wrong.append(f"{name} (by {difference:.1e}, its largest {own:.1e})")
        if wrong:
            raise CompiledMismatch(
                f"the compiled gradients differ from the eager ones in {len(wrong)} of {len(named)} parameters: "
                f"{', '.join(wrong[:6])}{', ...' if len(wrong) > 6 else ''} (torch {th.__version__})"
            )
        self.checked = True


class CompiledMismatch(RuntimeError):
    """The compiled function's first call disagreed with the eager function's (:meth:`LazyCompiled.check`)."""


def _tensors(output: Any) -> list[th.Tensor]:
    """:return: the tensors of a function's output (nested tuples, lists and dicts), in order"""
    if isinstance(output, th.Tensor):
        return [output]
    if isinstance(output, dict):
        return [t for value in output.values() for t in _tensors(value)]
    if isinstance(output, (tuple, list)):
        return [t for value in output for t in _tensors(value)]
    return []


def _compare(label: str, compiled: th.Tensor, eager: th.Tensor, tolerance: float = CHECK_TOLERANCE) -> None:
    """
    :raises CompiledMismatch: ``compiled`` is not ``eager`` within ``tolerance`` of its largest value (or two of its
        dtype's rounding steps, e.g. for bfloat16)
    """
    if compiled.shape != eager.shape or compiled.dtype != eager.dtype:
        raise CompiledMismatch(f"{label}: {compiled.dtype} {tuple(compiled.shape)}, eager {eager.dtype} {tuple(eager.shape)}")
    if not eager.is_floating_point() or not eager.numel():
        if not th.equal(compiled, eager):
            raise CompiledMismatch(f"{label} differs from the eager function's")
        return
    difference = float((compiled.float() - eager.float()).abs().max())
    scale = float(eager.float().abs().max())
    tolerance = max(tolerance, 2 * th.finfo(eager.dtype).eps)  # a low-precision output may round either way
    if not difference <= tolerance * max(scale, OUTPUT_FLOOR):  # NaN fails too
        raise CompiledMismatch(f"{label} differs from the eager function's by {difference:.1e} (its largest: {scale:.1e})")


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

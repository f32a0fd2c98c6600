"""How an update computes, apart from what: the compute settings that MPO and CRR share (their ``compute`` argument)."""

import dataclasses
from typing import Union

from sb3_lifelong.core.settings import Settings
from sb3_lifelong.numerics.compiling import COMPILE_CHOICES
from sb3_lifelong.numerics.hardware import TRAIN_DTYPES
from sb3_lifelong.numerics.scoring import SCORING_DTYPES

__all__ = ["ComputeSettings"]


@dataclasses.dataclass(frozen=True)
class ComputeSettings(Settings):
    """
    The precision and compilation of MPO's and CRR's updates (their ``compute`` argument: this, or a dict of some
    of its fields, e.g. ``MPO("MlpPolicy", env, compute=dict(train_dtype="bfloat16"))``). None of them changes what
    an update computes, only its arithmetic and speed.

    :param scoring_dtype: precision of the no-grad critic passes over the sampled actions (MPO's target and E-step,
        CRR's advantage baseline and TD target: the largest part of an update): ``"float32"`` (exact),
        ``"bfloat16"`` (a bf16 copy of the critic, refreshed at every target update; Q within about 1 % of float32;
        a categorical critic's hidden layers too, its logits and their softmax stay float32), or ``"auto"``:
        bfloat16 where the hardware multiplies it natively (AVX-512 BF16 / AMX CPUs, CUDA GPUs with bf16) and the
        critic's layers are at least 128 wide, float32 otherwise
    :param train_dtype: precision of the products between two hidden layers in the passes that record gradients
        (the critic's and the actor's losses): ``"float32"`` (the default), ``"bfloat16"`` (mixed precision for
        those layers: bf16 products; float32 parameters, optimizer and everything else;
        :class:`~sb3_lifelong.numerics.fast_ops.HiddenLinear`), ``"simulated_bfloat16"`` (the same numbers from float32
        products, eager: what bf16 does to learning, measured at float32's speed where the hardware has no bf16), or
        ``"auto"``: bfloat16 where the hardware multiplies it natively. The default stays float32 until bf16's
        learning results are measured on such a CPU (``benchmarks/results/speed/fast_paths.md``)
    :param compile_losses: compile the update's forward pass (the targets, the losses) with ``torch.compile``:
        ``True``, ``False``, or ``"auto"``: when the ``learn`` / ``learn_offline`` call under way has at least 50,000
        steps (updates offline) to go and inductor can compile here (a C++ compiler on a CPU); see
        :mod:`sb3_lifelong.numerics.compiling`. The sampling noise is drawn outside the graph, from the same generator
        as the eager update; the arithmetic differs from eager's by rounding. A bf16 scoring pass stays eager but for
        its LayerNorm and tanh, which run as one compiled kernel (:class:`~sb3_lifelong.numerics.scoring.LowPrecisionCopy`).
        A compilation that fails warns once and leaves the update eager. With ``train_dtype="simulated_bfloat16"``
        the update is always eager (``True`` is refused)
    """

    scoring_dtype: str = "auto"
    train_dtype: str = "float32"
    compile_losses: Union[bool, str] = "auto"

    def invalid(self) -> dict[str, str]:
        problems = {
            "scoring_dtype": f"one of {SCORING_DTYPES}" if self.scoring_dtype not in SCORING_DTYPES else "",
            "train_dtype": f"one of {TRAIN_DTYPES}" if self.train_dtype not in TRAIN_DTYPES else "",
            "compile_losses": (
                f"one of {COMPILE_CHOICES}"
                if not (isinstance(self.compile_losses, bool) or self.compile_losses == "auto")
                else ""
            ),
        }
        if self.train_dtype == "simulated_bfloat16" and self.compile_losses is True:
            problems["compile_losses"] = (
                "train_dtype='simulated_bfloat16' runs eagerly (a compiled graph fuses its roundings away): "
                "compile_losses=False or 'auto' (which then stays eager)"
            )
        return {name: rule for name, rule in problems.items() if rule}

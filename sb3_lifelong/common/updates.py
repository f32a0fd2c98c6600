"""
What the algorithms' training steps share: an optimizer step over one backward pass, the target networks' update, the
critics' low-precision scoring copies, the precision of the gradient passes, the compiled forward pass's checks, and
the stop on a loss that is not finite (:class:`UpdateMechanics`, a part of
:class:`~sb3_lifelong.common.base.LifelongOffPolicyAlgorithm`).
"""

from collections.abc import Sequence
from typing import Any, Optional

import torch as th
from stable_baselines3.common.policies import BaseModel
from stable_baselines3.common.utils import polyak_update

from sb3_lifelong.common.losses import sum_of
from sb3_lifelong.numerics.compiling import CHECK_TOLERANCE, LOW_PRECISION_CHECK_TOLERANCE, LazyCompiled
from sb3_lifelong.numerics.fast_ops import HiddenLinear
from sb3_lifelong.numerics.hardware import SIMULATED_BFLOAT16, resolve_train_dtype
from sb3_lifelong.numerics.scoring import LowPrecisionCopy, resolve_scoring_dtype, runs_no_grad_pass
from sb3_lifelong.numerics.settings import ComputeSettings


def optimized_parameters(module: BaseModel) -> list[th.Tensor]:
    """
    :return: the parameters ``module.optimizer`` steps, in its order: a critic's own, without a features extractor it
        shares with the actor (SB3 leaves that one to the actor's optimizer), so that clipping a critic's gradients
        never counts, or scales, the gradients the actor's loss put into the shared extractor
    """
    return [parameter for group in module.optimizer.param_groups for parameter in group["params"]]


class UpdateMechanics:
    """
    The part of the algorithms that runs their updates' mechanics (mixed into
    :class:`~sb3_lifelong.common.base.LifelongOffPolicyAlgorithm` before SB3's ``OffPolicyAlgorithm``).
    """

    device: th.device
    policy: Any
    actor: th.nn.Module
    tau: float
    num_timesteps: int
    _n_updates: int
    # the networks of an algorithm with target networks (MPO, CRR), set by its _setup_model (SB3 declares ``actor``)
    critic: th.nn.Module
    critic_target: th.nn.Module
    actor_target: th.nn.Module
    #: the low-precision copy of ``critic_target`` that scores sampled actions (:meth:`_make_scoring_copy`), or None
    _target_scoring_copy: Optional[LowPrecisionCopy] = None
    #: the update's forward pass, compiled when ``compile_losses`` asks for it (:meth:`_compiles_now`); None for an
    #: algorithm without one
    _forward: Optional[LazyCompiled] = None
    #: the precision and compilation of the updates (MPO's and CRR's ``compute``); an algorithm without the argument
    #: (BC) updates eagerly in float32
    compute: ComputeSettings = ComputeSettings(scoring_dtype="float32", compile_losses=False)

    def _raise_if_not_finite(self, **values: th.Tensor) -> None:
        """
        Stop training, with an error naming the update, as soon as a loss or a dual variable is NaN or infinite (a NaN
        reward in a buffer that does not refuse it, e.g. SB3's ``ReplayBuffer``, would otherwise spread to every
        parameter). Cheap: one ``isfinite`` over the few values concatenated, one device synchronisation per update;
        the values are looked at one by one only to write the message.

        :param values: name -> tensor (a loss, or a dual's raw parameters)
        :raises FloatingPointError: naming the values that are not finite, the update and the timestep
        """
        if bool(th.isfinite(th.cat([value.detach().reshape(-1) for value in values.values()])).all()):
            return
        bad = {
            name: value.detach().reshape(-1).tolist()
            for name, value in values.items()
            if not bool(th.isfinite(value.detach()).all())
        }
        described = ", ".join(f"{name} = {v[0] if len(v) == 1 else v}" for name, v in bad.items())
        raise FloatingPointError(
            f"{type(self).__name__}: {described} at update {self._n_updates} (num_timesteps {self.num_timesteps}): not "
            "finite, training stopped. The parameters this update changed may hold NaN or inf now: go on from the last "
            "checkpoint. Usual causes: a NaN or infinite reward, observation or action in the data (SB3's ReplayBuffer "
            "stores them; LifelongReplayBuffer refuses them at add()), or a learning rate too high"
        )

    @staticmethod
    def _gradient_step(
        *parts: tuple[BaseModel, th.Tensor], max_grad_norm: Optional[float], also_step: Sequence[th.optim.Optimizer] = ()
    ) -> None:
        """
        One step of each module's optimizer down its loss, with one backward pass of the losses' sum: one part is the
        usual step; several are one backward through a compiled graph, with the same gradients when no loss reaches
        another part's module. Each module's gradients' norm is clipped over the parameters its optimizer steps
        (:func:`optimized_parameters`).

        :param parts: ``(module, loss)`` pairs
        :param max_grad_norm: the clip of each module's gradients' norm (None: not clipped)
        :param also_step: optimizers of parameters outside the modules (e.g. MPO's duals), zeroed and stepped with
            them, not clipped
        """
        optimizers = [module.optimizer for module, _ in parts] + list(also_step)
        for optimizer in optimizers:
            optimizer.zero_grad(set_to_none=True)
        sum_of(loss for _, loss in parts).backward()
        if max_grad_norm is not None:
            for module, _ in parts:
                th.nn.utils.clip_grad_norm_(optimized_parameters(module), max_grad_norm, foreach=True)
        for optimizer in optimizers:
            optimizer.step()

    def _compiles_now(self) -> bool:
        """:return: whether this ``train`` call runs the compiled forward pass (see ``compute.compile_losses``)"""
        if self._forward is None or self.compute.train_dtype == SIMULATED_BFLOAT16:
            return False  # a compiled graph fuses the simulation's roundings away (HiddenLinear)
        to_go = getattr(self, "_total_timesteps", 0) - self.num_timesteps
        return self._forward.wanted(self.compute.compile_losses, to_go, self.device)

    def _update_targets(self) -> None:
        """
        Move the target networks towards the online ones (an algorithm with targets calls it every
        ``target_update_interval`` updates): Polyak averaging with ``tau`` (1: a copy), of the critic then of the actor,
        and the target critic's low-precision copy follows.
        """
        polyak_update(self.critic.parameters(), self.critic_target.parameters(), self.tau)
        polyak_update(self.actor.parameters(), self.actor_target.parameters(), self.tau)
        if self._target_scoring_copy is not None:
            self._target_scoring_copy.sync()

    def _make_scoring_copy(self, critic: th.nn.Module) -> Optional[LowPrecisionCopy]:
        """
        A low-precision copy of ``critic`` for the no-grad scoring passes, when ``compute.scoring_dtype`` asks for one
        (see :func:`sb3_lifelong.numerics.scoring.resolve_scoring_dtype`); it is synchronised by
        :meth:`_sync_scoring_copies` after loads and by the algorithm after its updates.

        :return: the copy, or None to score in the critic's own precision (always for a critic that the scoring
            engine does not run, :func:`~sb3_lifelong.numerics.scoring.runs_no_grad_pass`: it is scored by calling it)
        """
        dtype = resolve_scoring_dtype(self.compute.scoring_dtype, critic, self.device)
        if dtype == th.float32 or not runs_no_grad_pass(critic):
            return None
        copy = LowPrecisionCopy(critic, dtype)
        self.__dict__.setdefault("_scoring_copies", []).append(copy)
        return copy

    def _apply_train_dtype(self) -> None:
        """
        Set the precision of the policy's hidden-to-hidden products in the passes that record gradients
        (:class:`~sb3_lifelong.numerics.fast_ops.HiddenLinear`), from ``compute.train_dtype`` (see
        :func:`~sb3_lifelong.numerics.hardware.resolve_train_dtype`). Called at every setup, loads included.
        """
        train_dtype = self.compute.train_dtype
        dtype = resolve_train_dtype(train_dtype, self.device)
        for module in self.policy.modules():
            if isinstance(module, HiddenLinear):
                module.compute_dtype = None if dtype == th.float32 else dtype
                module.simulated = train_dtype == SIMULATED_BFLOAT16

    def _compiled_check_tolerance(self) -> float:
        """
        :return: the relative tolerance of the compiled update's first-call check against the eager one
            (:class:`~sb3_lifelong.numerics.compiling.LazyCompiled`): wider where the gradient passes multiply in
            bfloat16 (:meth:`_apply_train_dtype` first), whose roundings the compiled graph places differently
        """
        low = any(isinstance(m, HiddenLinear) and m.compute_dtype is not None for m in self.policy.modules())
        return LOW_PRECISION_CHECK_TOLERANCE if low else CHECK_TOLERANCE

    def _compile_scoring_copies(self, compiled: bool) -> None:
        """
        Have the scoring copies run their LayerNorm and tanh as one compiled kernel in the ``train`` calls whose update
        is compiled (:attr:`~sb3_lifelong.numerics.scoring.LowPrecisionCopy.compile_layer_norm`), and eagerly in the others.

        :param compiled: whether this ``train`` call runs the compiled update (:meth:`_compiles_now`)
        """
        for copy in self.__dict__.get("_scoring_copies", []):
            copy.compile_layer_norm = compiled

    def _sync_scoring_copies(self) -> None:
        for copy in self.__dict__.get("_scoring_copies", []):
            copy.sync()

    def set_parameters(self, *args: Any, **kwargs: Any) -> None:
        super().set_parameters(*args, **kwargs)  # type: ignore[misc]
        self._sync_scoring_copies()

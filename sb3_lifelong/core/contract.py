"""
The contract between the environments whose dynamics change (:mod:`sb3_lifelong.envs`) and the buffer and
algorithms that learn from them (:mod:`sb3_lifelong.common`, the algorithms). Both sides import these names from
here, and this module imports nothing, so neither side depends on the other.

**Info keys** written by :class:`~sb3_lifelong.envs.DynamicsSchedule` into the ``info`` of every ``reset`` and
``step``, and read by :class:`~sb3_lifelong.buffers.LifelongReplayBuffer` in ``add``:

* :data:`STAGE_KEY` (``"stage"``): the index of the stage in effect (an ``int``). The buffer stores it as the
  transition's *source* id; a transition whose ``info`` has no such key gets the buffer's current source
  (``set_source``). Any env may write it to label its transitions.
* :data:`DYNAMICS_PARAMS_KEY` (``"dynamics_params"``): the true value of every physical parameter in effect
  (``{name: float}``). The buffer records it, once per source, as the metadata of a source it has not named yet.

**The model's timestep.** A schedule switches by SB3's ``model.num_timesteps``. An env (any wrapper in the chain)
that has a method named :data:`SYNC_TIMESTEP_METHOD` is told the model's timestep by
:class:`~sb3_lifelong.common.base.LifelongOffPolicyAlgorithm` at the start of every ``learn`` (before the env is
reset), as ``method(timestep=model.num_timesteps, n_envs=vec_env.num_envs)``; from there the env counts
``n_envs`` per step, as SB3 does during ``learn``. So the caller passes neither ``n_envs`` nor ``start_timestep``.

**One name per environment.** Stage ``i`` is called :func:`stage_name` ``(i)`` (``Env-A``, ``Env-B``, ...) everywhere:
the evaluation copies of :func:`~sb3_lifelong.envs.stage_envs`, the buffer's source of that stage (so its Q-value
curves, CSV columns and ``source_counts(by_name=True)``), the reports.

**Resets as SB3 calls them.** The package's wrappers pass ``options`` on to the wrapped env's ``reset`` only when
it is given (:func:`reset_options`), as SB3's ``VecEnv`` does, so an env whose ``reset`` takes only ``seed`` works.
"""

from typing import Any, Optional

#: ``info`` key of the stage index (the transition's source id in the buffer)
STAGE_KEY = "stage"
#: ``info`` key of the true dynamics parameters in effect (``{name: value}``; the source's metadata in the buffer)
DYNAMICS_PARAMS_KEY = "dynamics_params"
#: name of the env method through which the algorithm tells the env its timestep (``timestep=..., n_envs=...``)
SYNC_TIMESTEP_METHOD = "sb3_lifelong_sync_timestep"


def stage_name(index: int) -> str:
    """
    :param index: a stage's index (its source id in the buffer)
    :return: its name in the logs: ``Env-A`` for stage 0, ``Env-B``, ... ``Env-Z``, then ``Env-26``, ``Env-27``, ...
    """
    if index < 0:
        raise ValueError(f"a stage index is >= 0, got {index}")
    return f"Env-{chr(ord('A') + index)}" if index < 26 else f"Env-{index}"


def reset_options(options: Optional[dict[str, Any]]) -> dict[str, Any]:
    """
    The keyword arguments that carry a wrapper's ``options`` on to the wrapped env's ``reset``, as SB3 passes them:
    none when ``options`` is None, so that an env whose ``reset`` accepts only ``seed`` can be wrapped.

    :param options: the ``options`` the wrapper's ``reset`` was given
    :return: ``{}`` or ``{"options": options}``, for ``env.reset(seed=seed, **reset_options(options))``
    """
    return {} if options is None else {"options": options}


__all__ = ["DYNAMICS_PARAMS_KEY", "STAGE_KEY", "SYNC_TIMESTEP_METHOD", "reset_options", "stage_name"]

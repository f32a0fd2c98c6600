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
"""

#: ``info`` key of the stage index (the transition's source id in the buffer)
STAGE_KEY = "stage"
#: ``info`` key of the true dynamics parameters in effect (``{name: value}``; the source's metadata in the buffer)
DYNAMICS_PARAMS_KEY = "dynamics_params"
#: name of the env method through which the algorithm tells the env its timestep (``timestep=..., n_envs=...``)
SYNC_TIMESTEP_METHOD = "sb3_lifelong_sync_timestep"

__all__ = ["DYNAMICS_PARAMS_KEY", "STAGE_KEY", "SYNC_TIMESTEP_METHOD"]

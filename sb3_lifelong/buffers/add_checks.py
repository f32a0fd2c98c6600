"""
What :meth:`~sb3_lifelong.buffers.LifelongReplayBuffer.add` accepts: real numbers (bool, integer or float arrays) in the
shapes SB3's ``ReplayBuffer.add`` accepts for ``n_envs`` envs (at most :data:`MAX_ENVS_PER_ADD`), converted to the
stored dtypes, with finite values, and only where an integer (or bool) field holds them exactly; anything else is
refused with a ``ValueError`` naming the field, before anything of the call is stored.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, Optional, Union

import numpy as np
from gymnasium import spaces
from stable_baselines3.common.preprocessing import get_action_dim

from sb3_lifelong.buffers.manifest import obs_keys_of

__all__ = ["MAX_ENVS_PER_ADD", "AddChecks", "exact_integers", "raise_if_not_finite"]

_vdot = np.vdot
_isfinite = math.isfinite
_FLOAT32 = np.dtype(np.float32)
_BOOL = np.dtype(bool)

#: the most envs one ``add()`` takes: each row stores the number of envs of its call (the stride between an env's
#: successive rows) in the ``widths`` field, a uint16 of the directory format
MAX_ENVS_PER_ADD = int(np.iinfo(np.uint16).max)
#: dtype kinds ``add()`` stores: bool, signed and unsigned integers, floats (real numbers only)
NUMERIC_KINDS = frozenset("biuf")
_KIND_NAMES = {
    "c": "complex numbers (their imaginary part would be lost)",
    "M": "datetimes (they would be stored as integers)",
    "m": "time deltas (they would be stored as integers)",
    "U": "strings",
    "S": "bytes",
    "O": "Python objects",
    "V": "raw or structured records",
}


def numeric(label: str, value: Any) -> np.ndarray:
    """
    :param label: The field, for the message (e.g. ``"observations"``, ``"observations['image']"``)
    :param value: What ``add()`` was given for it
    :return: ``value`` as an array of real numbers (bool, integer or float), not converted
    :raises ValueError: naming the field and the dtype, for any other dtype (complex, datetime, timedelta, strings,
        bytes, objects, records): numpy would convert them silently (drop an imaginary part, store a date as an
        integer, parse a numeric string)
    """
    array = np.asarray(value)
    kind = array.dtype.kind
    if kind not in NUMERIC_KINDS:
        raise ValueError(
            f"add(): {label} have dtype {array.dtype} ({_KIND_NAMES.get(kind, 'not real numbers')}): only real numbers "
            "(bool, integer or float arrays) are stored; nothing of this add() was stored"
        )
    return array


def _integer_bounds(dtype: np.dtype) -> tuple[int, int]:
    """:return: the smallest and largest value of an integer or bool dtype"""
    if dtype.kind == "b":
        return 0, 1
    info = np.iinfo(dtype)
    return int(info.min), int(info.max)


def exact_integers(label: str, value: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """
    The float rules for a stored integer (or bool) field: a value is stored only if the stored dtype holds it exactly
    (as a float field refuses what overflows its dtype and a complex value, whose imaginary part would be lost).

    :param label: The field, for the message (e.g. ``"observations"``, ``"observations['image']"``)
    :param value: What ``add()`` was given for it (real numbers: see :func:`numeric`)
    :param dtype: The stored dtype (integers or bool)
    :return: ``value`` converted to ``dtype`` (``value`` itself when its dtype casts safely, e.g. uint8 into int64)
    :raises ValueError: naming the field, the first value and the range, for a value out of the range of ``dtype``
        (300 or -1 into uint8), a fractional one (0.7 into an integer field), NaN or infinite; nothing is stored
    """
    if np.can_cast(value.dtype, dtype, casting="safe"):
        return value
    low, high = _integer_bounds(dtype)
    if value.dtype.kind == "f":
        wide = value.astype(np.float64, copy=False)
        # the bounds +-2**k are exact floats; high + 1 is too (a power of two), high itself may not be (2**63 - 1)
        bad = ~((wide >= low) & (wide < float(high + 1)) & (np.floor(wide) == wide))
    else:  # integers (or bools, which every integer dtype holds)
        bad = (value < low) | (value > high) if value.size else np.zeros(value.shape, bool)
    if np.any(bad):
        flat = np.asarray(value).reshape(-1)
        at = int(np.flatnonzero(np.asarray(bad).reshape(-1))[0])
        first = flat[at]
        count = int(np.count_nonzero(bad))
        more = f" (and {count - 1} more)" if count > 1 else ""
        env = f" of env {at // max(1, flat.size // len(value))}" if value.ndim else ""
        what = "only 0 and 1" if dtype.kind == "b" else f"integers from {low:,} to {high:,}"
        why = (
            "is not finite"
            if not np.isfinite(first)
            else "is not an integer" if first != np.floor(first) else "is out of range"
        )
        raise ValueError(
            f"add(): {label}{env}: the value {first.item()!r}{more} {why}: the field is stored as {dtype} ({what}), and numpy "
            "would store another value (wrapped around or truncated); nothing of this add() was stored"
        )
    return value.astype(dtype)


def _conform(label: str, value: np.ndarray, target: tuple[int, ...], what: str = "") -> np.ndarray:
    """
    ``value`` as an array of shape ``target`` where numpy's assignment rules (as used by SB3's ``ReplayBuffer.add``)
    accept it: leading dimensions of size 1 dropped, then broadcasting. Otherwise a ValueError naming the field.
    """
    shape = value.shape
    while len(shape) > len(target) and shape[0] == 1:
        shape = shape[1:]
    try:
        return np.broadcast_to(value.reshape(shape), target)
    except ValueError:
        where = f"; {what}" if what else ""
        raise ValueError(
            f"add(): {label} have shape {value.shape}, expected {target} ({target[0]} envs, the length of rewards{where})"
        ) from None


def _env_vector(label: str, value: np.ndarray) -> np.ndarray:
    """Rewards given as a scalar (one env) or with leading dimensions of size 1, as a vector (n_envs,)."""
    shape = value.shape
    while len(shape) > 1 and shape[0] == 1:
        shape = shape[1:]
    if len(shape) > 1:
        raise ValueError(f"add(): {label} have shape {value.shape}, expected (n_envs,): one value per env")
    return value.reshape(shape or (1,))


def raise_if_not_finite(values: np.ndarray, what: str, consequence: str, offset: int = 0) -> None:
    """
    :param values: Array whose first dimension is the env (or row) index
    :param what: Start of the message, e.g. ``"add(): rewards of env"``, followed by the first bad index
    :param consequence: End of the message
    :param offset: Added to the index reported
    :raises ValueError: if a value is NaN or infinite
    """
    bad = ~np.isfinite(values)
    if not bad.any():
        return
    rows = np.flatnonzero(bad.reshape(len(values), -1).any(axis=1)) if values.ndim else np.zeros(1, np.int64)
    first = int(rows[0])
    value = values.reshape(len(values), -1)[first][bad.reshape(len(values), -1)[first]][0] if values.ndim else values
    more = f" (and {len(rows) - 1} more)" if len(rows) > 1 else ""
    raise ValueError(
        f"{what} {first + offset}{more} is not finite ({value}): NaN and infinite values are refused; {consequence}"
    )


def _check_finite(obs_rows: dict[str, np.ndarray], actions: np.ndarray, rewards: np.ndarray) -> None:
    """Raise a ValueError naming the field and the envs if a float value is NaN or infinite."""
    fields = {**obs_rows, "actions": actions, "rewards": rewards}
    for name, values in fields.items():
        if values.dtype.kind == "f":
            label = name if "." not in name else "{}[{!r}]".format(*name.split(".", 1))
            raise_if_not_finite(values, f"add(): {label} of env", "nothing of this add() was stored")


class AddChecks:
    """
    The checks of ``add()`` for a buffer's spaces and stored fields. They keep the shapes expected for the last number
    of envs (computed again when it changes).

    :param observation_space: The buffer's observation space (Box, Discrete, or Dict of those)
    :param action_space: Its action space
    :param fields: Its store's fields: field name -> (dtype string, row shape)
    """

    def __init__(
        self,
        observation_space: spaces.Space,
        action_space: spaces.Space,
        fields: Mapping[str, tuple[str, tuple[int, ...]]],
    ) -> None:
        self.observation_space = observation_space
        self.action_space = action_space
        self.action_dim = get_action_dim(action_space)
        self.fields = dict(fields)
        self.dtypes = {name: np.dtype(dt) for name, (dt, _) in self.fields.items()}
        self.obs_keys = obs_keys_of(self.fields)
        self.width = -1  # the number of envs the shapes below are for

    def rows(
        self, obs: Any, next_obs: Any, action: Any, reward: Any, done: Any, infos: list[dict[str, Any]]
    ) -> dict[str, np.ndarray]:
        """
        :param obs: see :meth:`~sb3_lifelong.buffers.LifelongReplayBuffer.add`
        :param next_obs: see ``add``
        :param action: see ``add``
        :param reward: see ``add`` (its length is the number of envs)
        :param done: see ``add``
        :param infos: see ``add`` (only their number is checked here)
        :return: The rows of the call: the observations and next observations (one field per key of Dict
            observations), ``actions`` and ``rewards`` (float ones in their stored dtype) and ``flags`` (a new boolean
            array: done, for ``add`` to mark the timeouts in)
        :raises ValueError: naming the field, for a shape SB3 would not accept, a wrong number of infos, or a NaN or
            infinite value
        """
        reward = np.asarray(reward)
        if reward.dtype is not _FLOAT32:  # the stored dtypes are real numbers: only another one needs the test
            reward = numeric("rewards", reward).astype(np.float32)
        if reward.ndim != 1:
            reward = _env_vector("rewards", reward)
        width = len(reward)
        if len(infos) != width:
            raise ValueError(
                f"add(): infos has {len(infos)} entries for {width} envs (the length of rewards): expected one info dict "
                "per env"
            )
        if width > MAX_ENVS_PER_ADD:
            raise ValueError(
                f"add(): {width:,} envs in one call, at most {MAX_ENVS_PER_ADD:,} are accepted (each row stores the number "
                "of envs of its call, the stride between an env's successive transitions, as a uint16). Split the envs "
                "over several buffers (one per group of envs; LifelongBufferView reads them as one); nothing of this "
                "add() was stored"
            )
        if width != self.width:
            self._set_shapes(width)
        # a copy: stored as the flags (bit 0: done), timeouts set in place by add()
        done = np.asarray(done)
        if done.dtype is not _BOOL:
            numeric("dones", done)
        if done.shape != self._done:
            done = _conform("dones", done, self._done)
        if done.dtype is not _BOOL:
            done = exact_integers("dones", done, _BOOL)  # 0 and 1 only: a done of 2 (or 0.5) is refused
        flags = np.array(done, dtype=bool)
        actions = np.asarray(action)
        if actions.dtype is not self.dtypes["actions"]:
            numeric("actions", actions)
        if actions.shape != self._actions:
            actions = self._conform_actions(actions, width)
        if actions.dtype != self._action_dtype:
            if self._action_dtype.kind == "f":
                actions = actions.astype(self._action_dtype)  # stored as this: the finiteness check sees the stored values
            else:
                actions = exact_integers("actions", actions, self._action_dtype)
        rows = self._checked_rows(obs, next_obs, actions, reward, width)
        rows["actions"] = actions
        rows["rewards"] = reward
        rows["flags"] = flags
        return rows

    def _checked_rows(
        self, obs: Any, next_obs: Any, actions: np.ndarray, reward: np.ndarray, width: int
    ) -> dict[str, np.ndarray]:
        """add(): the observation rows, shaped (or a ValueError), and a ValueError if a float value is not finite."""
        if self.obs_keys is None:
            target, dtype = self._obs, self._obs_dtype
            observations = np.asarray(obs)
            if observations.dtype is not dtype:
                numeric("observations", observations)
            if observations.shape != target:
                observations = self._conform_obs("observations", observations, target)
            next_observations = np.asarray(next_obs)
            if next_observations.dtype is not dtype:
                numeric("next_observations", next_observations)
            if next_observations.shape != target:
                next_observations = self._conform_obs("next_observations", next_observations, target)
            if observations.dtype != dtype:
                observations = self._stored("observations", observations, dtype)
            if next_observations.dtype != dtype:
                next_observations = self._stored("next_observations", next_observations, dtype)
            # a cheap test of every value: a NaN or an infinity in x or y makes the dot product x.y NaN or infinite
            # (x * 0 is NaN for x infinite, and an infinite sum never comes back). Large finite values that overflow
            # do so too: then the exact check finds nothing
            total = float(reward[0]) if width == 1 else float(_vdot(reward, reward))
            if actions.dtype.kind == "f":
                total += float(_vdot(actions, actions))
            if dtype.kind == "f":  # both of the stored float dtype
                total += float(_vdot(observations, next_observations))
            else:
                if observations.dtype.kind == "f":
                    total += float(_vdot(observations, observations))
                if next_observations.dtype.kind == "f":
                    total += float(_vdot(next_observations, next_observations))
            if not _isfinite(total):
                _check_finite({"observations": observations, "next_observations": next_observations}, actions, reward)
            rows = {"observations": observations, "next_observations": next_observations}
        else:
            rows = {
                **self._observation_rows("observations", obs, width),
                **self._observation_rows("next_observations", next_obs, width),
            }
            _check_finite(rows, actions, reward)
        return rows

    @staticmethod
    def _stored(label: str, value: np.ndarray, dtype: np.dtype) -> np.ndarray:
        """``value`` in the stored ``dtype``: floats converted (their finiteness is checked after), integers and bools
        only where exact (:func:`exact_integers`)."""
        if dtype.kind == "f":
            return value.astype(dtype)
        return exact_integers(label, value, dtype)

    def _set_shapes(self, width: int) -> None:
        """The shapes add() expects for ``width`` envs, and the stored dtypes of its float fields."""
        self.width = width
        self._done = (width,)
        self._actions = (width, self.action_dim)
        action_shape = tuple(self.action_space.shape or ())
        accepted = {(width, self.action_dim), (width, *action_shape)}
        if width == 1:  # one env, unbatched: SB3 reshapes it too
            accepted |= {(self.action_dim,), action_shape}
        self._accepted = accepted
        self._action_dtype = self.dtypes["actions"]
        if self.obs_keys is None:
            self._obs = (width, *self.fields["observations"][1])
            self._obs_dtype = self.dtypes["observations"]
        else:
            assert isinstance(self.observation_space, spaces.Dict)
            self._key_obs = {key: (width, *self.fields[f"observations.{key}"][1]) for key in self.obs_keys}
            self._key_spaces = dict(self.observation_space.spaces)

    def _conform_actions(self, actions: np.ndarray, width: int) -> np.ndarray:
        if actions.shape not in self._accepted:
            raise ValueError(
                f"add(): actions have shape {actions.shape}, expected {self._actions} ({width} envs, the length of "
                f"rewards; action space {self.action_space})"
            )
        return actions.reshape(self._actions)

    def _conform_obs(
        self, label: str, obs: np.ndarray, target: tuple[int, ...], space: Optional[spaces.Space] = None
    ) -> np.ndarray:
        """Observations of a shape other than ``target``: what SB3's ``ReplayBuffer.add`` accepts (reshaped Discrete
        observations, numpy broadcasting otherwise), or a ``ValueError``."""
        space = self.observation_space if space is None else space
        if isinstance(space, spaces.Discrete):
            if obs.size == target[0] and obs.ndim <= 2:
                return obs.reshape(target)
            raise ValueError(
                f"add(): {label} have shape {obs.shape}, expected {target} or {target[:1]} ({target[0]} envs, the length "
                f"of rewards; observation space {space})"
            )
        return _conform(label, obs, target, f"observation space {space}")

    def _observation_rows(self, base: str, obs: Union[np.ndarray, dict[str, np.ndarray]], width: int) -> dict[str, np.ndarray]:
        if not isinstance(obs, dict) or set(obs) != set(self.obs_keys or ()):
            got = sorted(obs) if isinstance(obs, dict) else type(obs).__name__
            raise ValueError(f"add(): {base}: expected a dict with the keys {list(self.obs_keys or ())}, got {got}")
        rows = {}
        for key in self.obs_keys or ():
            name, target = f"{base}.{key}", self._key_obs[key]
            value = np.asarray(obs[key])
            if value.dtype is not self.dtypes[name]:
                numeric(f"{base}[{key!r}]", value)
            if value.shape != target:
                value = self._conform_obs(f"{base}[{key!r}]", value, target, self._key_spaces[key])
            dtype = self.dtypes[name]
            rows[name] = self._stored(f"{base}[{key!r}]", value, dtype) if value.dtype != dtype else value
        return rows

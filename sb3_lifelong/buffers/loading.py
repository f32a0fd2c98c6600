"""
The one way in of offline data: any supported source (an SB3 replay buffer, a buffer directory, a d4rl dict, a
``.npz`` file, a Minari dataset) turned into a replay buffer the offline algorithms and ``distill`` can sample.
"""

import os
import pathlib
import re
from collections.abc import Mapping
from typing import Any, Optional, Union

import numpy as np
import torch as th
from gymnasium import spaces
from stable_baselines3.common import utils
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_lifelong.buffers.lifelong import LifelongReplayBuffer
from sb3_lifelong.buffers.views import LifelongBufferView
from sb3_lifelong.core.datasets import (
    OfflineData,
    OfflineDataError,
    import_minari,
    infer_spaces,
    load_d4rl,
    minari_to_d4rl,
    normalize_actions,
    replay_buffer_to_d4rl,
)

__all__ = ["as_lifelong_data", "resolve_data"]


def _is_minari(data: Any) -> bool:
    return hasattr(data, "iterate_episodes")


#: what a Minari dataset id looks like: ``[namespace/]name-v<version>`` (e.g. ``D4RL/door/human-v2``)
_MINARI_ID = re.compile(r"^[\w.-]+(/[\w.-]+)*-v\d+$")


def _open_path(data: Union[str, os.PathLike]) -> Any:
    """
    :param data: a path or a Minari dataset id
    :return: a ``LifelongReplayBuffer`` directory opened read-only, a Minari dataset (loaded from its id), or the path
        of a file (a ``.npz`` for :func:`load_d4rl`)
    :raises OfflineDataError: for a directory that is not a buffer
    :raises FileNotFoundError: naming the path, for anything that is neither a file, a directory nor a Minari id
    """
    path = pathlib.Path(data)
    if path.is_dir():
        if (path / "manifest.json").is_file():
            return LifelongReplayBuffer.open(path, read_only=True)  # read-only: collection may go on elsewhere
        raise OfflineDataError(
            f"{os.fspath(data)!r} is a directory, but not a LifelongReplayBuffer (it has no manifest.json): give a "
            "buffer directory, a .npz file or a Minari dataset id"
        )
    if path.is_file():
        return data
    name = os.fspath(data)
    if not isinstance(data, str) or not _MINARI_ID.match(name) or name.endswith(".npz"):
        raise FileNotFoundError(
            f"no offline data at {name!r}: no such file or directory (nor a Minari dataset id, which ends in "
            "-v<version>, e.g. 'D4RL/door/human-v2')"
        )
    minari = import_minari(f"{name!r} is not a file or directory, so it was taken as a Minari dataset id; loading it")
    try:
        return minari.load_dataset(name)
    except FileNotFoundError as error:
        raise FileNotFoundError(
            f"no offline data at {name!r}: no such file or directory, and no local Minari dataset of that id (download it "
            f"with minari.download_dataset({name!r}), or correct the path): {error}"
        ) from error


def _minari_buffer(
    dataset: Any,
    observation_space: Optional[spaces.Space],
    action_space: Optional[spaces.Space],
    device: th.device,
    normalized_actions: bool,
) -> LifelongReplayBuffer:
    """A Minari dataset as an in-memory ``LifelongReplayBuffer``, each step keeping its source (``from_minari``)."""
    observation_space = observation_space if observation_space is not None else getattr(dataset, "observation_space", None)
    action_space = action_space if action_space is not None else getattr(dataset, "action_space", None)
    if observation_space is None or action_space is None or not isinstance(action_space, spaces.Box):
        # a dataset object without spaces (or a non-Box action space given by it): the spaces are inferred (checked)
        observation_space, action_space = infer_spaces(
            minari_to_d4rl(dataset)[0], observation_space, action_space if isinstance(action_space, spaces.Box) else None
        )
    if not isinstance(action_space, spaces.Box) or not (
        np.isfinite(action_space.low).all() and np.isfinite(action_space.high).all()
    ):
        raise OfflineDataError(
            f"offline learning here needs a bounded Box action space (actions are normalised with it), got {action_space}"
        )
    return LifelongReplayBuffer.from_minari(
        dataset,
        observation_space=observation_space,
        action_space=action_space,
        normalized_actions=normalized_actions,
        device=device,
    )


def resolve_data(
    data: OfflineData,
    observation_space: Optional[spaces.Space] = None,
    action_space: Optional[spaces.Space] = None,
    device: Union[th.device, str] = "auto",
    normalized_actions: Optional[bool] = None,
) -> ReplayBuffer:
    """
    Turn any supported data source into a replay buffer: the one way in of the offline algorithms and ``distill``.

    :param data: an SB3 ``ReplayBuffer`` (returned as it is, after checking its spaces), the directory of a
        ``LifelongReplayBuffer`` (opened read-only), a d4rl dict, the path of a ``.npz`` file, a Minari dataset id or
        object (each step keeps its source, as ``LifelongReplayBuffer.from_minari`` keeps it)
    :param observation_space: observation space (inferred from the data when None)
    :param action_space: action space, a bounded Box (inferred from the data when None)
    :param device: device of the sampled tensors (new buffers only)
    :param normalized_actions: whether the actions of dict / ``.npz`` / Minari data are already normalised to
        ``[-1, 1]``; default False: they are in the environment's units (the d4rl convention). Replay buffers are
        always taken as SB3 fills them (normalised actions).
    :return: the replay buffer
    :raises FileNotFoundError: naming the path, for a path that is neither a file, a directory nor a Minari id
    :raises OfflineDataError: naming the problem, for data that cannot be used (see :func:`validate_d4rl`)
    """
    if isinstance(data, (str, os.PathLike)):
        data = _open_path(data)
    if isinstance(data, ReplayBuffer):
        if normalized_actions is False:
            raise ValueError(
                "A ReplayBuffer holds normalised actions (as SB3 stores them): normalized_actions=False is invalid"
            )
        if data.size() == 0:
            raise OfflineDataError("the replay buffer is empty")
        for name, given, stored in (
            ("observation", observation_space, data.observation_space),
            ("action", action_space, data.action_space),
        ):
            if given is not None and (given.shape != stored.shape or type(given) is not type(stored)):
                raise OfflineDataError(f"the replay buffer's {name} space {stored} does not match {given}")
        if not isinstance(data.action_space, spaces.Box):
            raise OfflineDataError(f"offline learning here needs a continuous (Box) action space, got {data.action_space}")
        return data
    if _is_minari(data):
        return _minari_buffer(data, observation_space, action_space, utils.get_device(device), bool(normalized_actions))
    if not isinstance(data, (Mapping, str, os.PathLike)):
        raise TypeError(
            "offline data must be an SB3 ReplayBuffer, a LifelongReplayBuffer directory, a d4rl-style dict, the path of "
            f"a .npz file or a Minari dataset, got {type(data).__name__}"
        )
    d4rl = load_d4rl(data)
    normalized = bool(normalized_actions)
    observation_space, action_space = infer_spaces(d4rl, observation_space, action_space, normalized)
    d4rl = {**d4rl, "actions": normalize_actions(d4rl, action_space, normalized)}
    return LifelongReplayBuffer.from_d4rl(
        d4rl, observation_space, action_space, normalized_actions=True, device=utils.get_device(device)
    )


def as_lifelong_data(buffer: ReplayBuffer) -> Union[LifelongReplayBuffer, LifelongBufferView]:
    """
    :param buffer: a replay buffer
    :return: the buffer itself if it is a lifelong buffer or view (which know each transition's source and the
        next action in its stream), else an in-memory ``LifelongReplayBuffer`` copy of an SB3 buffer's rows
    """
    if isinstance(buffer, (LifelongReplayBuffer, LifelongBufferView)):
        return buffer
    return LifelongReplayBuffer.from_d4rl(
        replay_buffer_to_d4rl(buffer),
        buffer.observation_space,
        buffer.action_space,
        normalized_actions=True,
        device=buffer.device,
    )

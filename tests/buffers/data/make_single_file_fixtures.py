"""
How the fixtures ``single_file_v1/`` and ``single_file_v2/`` were made: buffer directories in layout "single" (one
append-only file per field), written by the code of main at commit 682b063, before the single-file writer was
removed. ``tests/buffers/test_buffer_legacy.py`` opens copies of them and recomputes every row with :func:`rows`.

Run once from the repository root, with the code that still writes layout "single" (``capacity=None``)::

    PYTHONPATH=. python tests/buffers/data/make_single_file_fixtures.py

- ``single_file_v1``: Box(3,) float32 observations, Box(2,) actions: manifest version 1; 24 transitions in chunks
  of 10 (10, 10, 4), 2 envs per ``add``, sources 0 ("Env-A") then 1 ("Env-B"), episode ends every 4 steps.
- ``single_file_v2``: Dict observations {"pos": Box(2,), "vel": Box(1,) float64 stored as given}, Discrete(3) actions:
  manifest version 2, layout "single"; 17 transitions in chunks of 8 (8, 8, 1), 1 env per ``add``, source 0.
"""

from __future__ import annotations

import os
import shutil
import sys

import numpy as np
from gymnasium import spaces

HERE = os.path.dirname(os.path.abspath(__file__))

V1_OBS = spaces.Box(-100.0, 100.0, (3,), np.float32)
V1_ACT = spaces.Box(-1.0, 1.0, (2,), np.float32)
V2_OBS = spaces.Dict({"pos": spaces.Box(-100.0, 100.0, (2,), np.float32), "vel": spaces.Box(-100.0, 100.0, (1,), np.float32)})
V2_ACT = spaces.Discrete(3)


def rows(version: int, step: int, env: int) -> dict:
    """The values added at ``step`` for ``env`` (deterministic: a test recomputes them)."""
    base = 0.5 * step + 0.25 * env
    if version == 1:
        obs = np.array([base, -base, step % 7], dtype=np.float32)
        return {
            "obs": obs,
            "next_obs": obs + np.float32(1.0),
            "action": np.array([np.float32(step % 5) / 5, -np.float32(env) / 2], dtype=np.float32),
            "reward": np.float32(step - 10 * env),
            "done": step % 4 == 3,
            "truncated": step % 8 == 7,
            "source": 0 if step < 6 else 1,
        }
    obs = {"pos": np.array([base, 2 * base], dtype=np.float32), "vel": np.array([-base], dtype=np.float32)}
    return {
        "obs": obs,
        "next_obs": {key: value + np.float32(0.5) for key, value in obs.items()},
        "action": np.array(step % 3),
        "reward": np.float32(0.125 * step),
        "done": step % 5 == 4,
        "truncated": False,
        "source": 0,
    }


#: (version, steps, n_envs, chunk_size)
SPECS = {1: (12, 2, 10), 2: (17, 1, 8)}


def make(version: int) -> str:
    from sb3_lifelong import LifelongReplayBuffer

    steps, n_envs, chunk_size = SPECS[version]
    obs_space, act_space = (V1_OBS, V1_ACT) if version == 1 else (V2_OBS, V2_ACT)
    path = os.path.join(HERE, f"single_file_v{version}")
    shutil.rmtree(path, ignore_errors=True)
    buffer = LifelongReplayBuffer(0, obs_space, act_space, path=path, chunk_size=chunk_size, device="cpu", n_envs=n_envs)
    for step in range(steps):
        per_env = [rows(version, step, env) for env in range(n_envs)]
        if version == 1:
            buffer.set_source(per_env[0]["source"], name="Env-A" if per_env[0]["source"] == 0 else "Env-B")
            obs = np.stack([r["obs"] for r in per_env])
            next_obs = np.stack([r["next_obs"] for r in per_env])
        else:
            obs = {key: np.stack([r["obs"][key] for r in per_env]) for key in V2_OBS.spaces}
            next_obs = {key: np.stack([r["next_obs"][key] for r in per_env]) for key in V2_OBS.spaces}
        buffer.add(
            obs,
            next_obs,
            np.stack([r["action"] for r in per_env]),
            np.array([r["reward"] for r in per_env]),
            np.array([r["done"] for r in per_env]),
            [{"TimeLimit.truncated": r["truncated"]} for r in per_env],
        )
    buffer.close()
    os.remove(os.path.join(path, "writer.lock"))
    return path


if __name__ == "__main__":
    sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(HERE))))
    for version in SPECS:
        print(make(version))

"""
Property-based tests (``hypothesis``) of :class:`DynamicsSchedule`'s timesteps and of the schedulers: for any switch
times, number of sub-envs and starting timestep, the stage of each step is the number of switches at or before its
global timestep; the schedulers stay in their bounds and follow their definitions at every timestep.
"""

import bisect

import gymnasium as gym
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from sb3_lifelong.envs import Drift, DynamicsSchedule, LinearRamp, RandomWalk, SawWave

FAST = settings(max_examples=20, deadline=None, database=None)

switch_times = st.lists(st.integers(1, 60), min_size=1, max_size=3, unique=True).map(sorted)


@FAST
@given(switch_at=switch_times, n_envs=st.integers(1, 4), start=st.integers(0, 40), steps=st.integers(1, 12))
def test_each_step_runs_the_stage_due_at_its_global_timestep(switch_at, n_envs, start, steps):
    stages = [{"gravity": 9.81 + i} for i in range(len(switch_at) + 1)]
    env = DynamicsSchedule(
        gym.make("HalfCheetah-v5"), stages, switch_at, n_envs=n_envs, mid_episode=True, start_timestep=start
    )
    env.reset(seed=0)
    for k in range(steps):
        timestep = env.timestep
        assert timestep == start + n_envs * k
        due = bisect.bisect_right(switch_at, timestep)
        assert env.stage_at(timestep) == due
        info = env.step(env.action_space.sample())[-1]
        assert info["stage"] == due
        assert info["dynamics_params"]["gravity"] == stages[due]["gravity"]
    env.set_timestep(switch_at[-1])  # jumping there: the last stage is due from its switch on, not before
    assert env.stage_at(env.timestep) == len(switch_at) and env.stage_at(switch_at[-1] - 1) == len(switch_at) - 1
    env.close()


@FAST
@given(
    start=st.floats(0.5, 2.0), end=st.floats(0.5, 2.0), begin=st.integers(0, 100), length=st.integers(1, 100),
    times=st.lists(st.integers(0, 300), min_size=1, max_size=20),
)  # fmt: skip
def test_linear_ramp_is_clamped_linear_interpolation(start, end, begin, length, times):
    ramp = LinearRamp(start, end, begin=begin, finish=begin + length)
    ramp.bind("mass_scale", 0.05, 20.0, 0)
    for t in times:
        fraction = min(max((t - begin) / length, 0.0), 1.0)
        assert np.isclose(ramp.value(t), start + fraction * (end - start))
        assert min(start, end) - 1e-12 <= ramp.value(t) <= max(start, end) + 1e-12
    values = [ramp.value(t) for t in sorted(times)]
    assert all((b - a) * (end - start) >= -1e-12 for a, b in zip(values, values[1:]))  # monotone towards ``end``


@FAST
@given(low=st.floats(0.1, 1.0), span=st.floats(0.1, 2.0), half=st.integers(1, 50), t=st.integers(0, 500))
def test_saw_wave_stays_in_bounds_is_periodic_and_continuous(low, span, half, t):
    saw = SawWave(low, low + span, half_period=half)
    saw.bind("mass_scale", 0.05, 20.0, 0)
    value = saw.value(t)
    assert low - 1e-9 <= value <= low + span + 1e-9
    assert np.isclose(saw.value(t + 2 * half), value)  # one period: up and down
    assert abs(saw.value(t + 1) - value) <= span / half + 1e-9  # moves at most span / half_period per timestep
    cycle = 2 * half * (t // (2 * half))
    assert np.isclose(saw.value(cycle), low) and np.isclose(saw.value(cycle + half), low + span)  # turns at the bounds


@FAST
@given(seed=st.integers(0, 1000), period=st.integers(1, 10), times=st.lists(st.integers(0, 200), min_size=2, max_size=15))
def test_random_walk_and_drift_stay_in_bounds_and_do_not_depend_on_the_query_order(seed, period, times):
    walk = RandomWalk(1.0, 0.2, period=period, low=0.7, high=1.3, seed=seed)
    walk.bind("mass_scale", 0.05, 20.0, 0)
    in_order = {t: walk.value(t) for t in sorted(times)}
    again = RandomWalk(1.0, 0.2, period=period, low=0.7, high=1.3, seed=seed)
    again.bind("mass_scale", 0.05, 20.0, 0)
    assert {t: again.value(t) for t in times} == in_order  # queried in any order, backwards too
    assert all(0.7 <= v <= 1.3 for v in in_order.values())
    assert all(walk.value(t) == walk.value(period * (t // period)) for t in times)  # changes only every period
    up = Drift(1.0, 0.05, direction=1, period=period, high=1.4, seed=seed)
    up.bind("mass_scale", 0.05, 20.0, 0)
    drift = [up.value(t) for t in sorted(times)]
    assert all(b >= a for a, b in zip(drift, drift[1:])) and all(1.0 <= v <= 1.4 for v in drift)

"""CRR's diagnostic of one actor per source with a shared critic (``actor_per_source=True``)."""

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.buffers import ReplayBuffer

from sb3_lifelong import CRR, LifelongReplayBuffer
from sb3_lifelong.crr.policies import PerSourceActor
from sb3_lifelong.evaluation.callbacks import MultiEnvEvalCallback

OBS = spaces.Box(-1.0, 1.0, (3,), np.float32)
ACT = spaces.Box(-1.0, 1.0, (2,), np.float32)
# each source always took the same action: +0.6 (source 0) and -0.6 (source 2); rewards do not favour either
ACTIONS = {0: 0.6, 2: -0.6}


def two_source_buffer(n: int = 300, seed: int = 0) -> LifelongReplayBuffer:
    rng = np.random.default_rng(seed)
    buffer = LifelongReplayBuffer(10, OBS, ACT, device="cpu")
    for source, action in ACTIONS.items():
        buffer.set_source(source, name=f"env_{source}")
        for _ in range(n):
            obs = rng.uniform(-1, 1, (1, 3)).astype(np.float32)
            buffer.add(obs, obs, np.full((1, 2), action, np.float32), np.zeros(1), np.zeros(1), [{"stage": source}])
    return buffer


def per_source_model(buffer: LifelongReplayBuffer, **kwargs) -> CRR:
    # a large beta makes the regression close to behaviour cloning of each source's actions
    params = dict(policy_kwargs=dict(net_arch=[32, 32]), batch_size=64, beta=100.0, seed=0, learning_rate=3e-3)
    params.update(kwargs)
    return CRR.from_offline_data(buffer, actor_per_source=True, **params)


def head_params(model: CRR, head: int) -> th.Tensor:
    assert isinstance(model.actor, PerSourceActor)
    return th.cat([p.detach().flatten().clone() for p in model.actor.heads[head].parameters()])


def mean_action(model: CRR, n: int = 50) -> float:
    obs = np.random.default_rng(1).uniform(-1, 1, (n, 3)).astype(np.float32)
    return float(model.predict(obs, deterministic=True)[0].mean())


@pytest.mark.parametrize("actor_averaging", [None, 0.05])
def test_each_actor_learns_its_own_source(actor_averaging):
    buffer = two_source_buffer()
    model = per_source_model(buffer, actor_averaging=actor_averaging)
    assert model.source_ids == [0, 2]
    assert isinstance(model.actor, PerSourceActor) and model.actor.n_heads == 2
    model.learn_offline(400)
    assert mean_action(model.select_source(0)) == pytest.approx(0.6, abs=0.1)
    assert mean_action(model.select_source(2)) == pytest.approx(-0.6, abs=0.1)
    if actor_averaging is not None:  # predict used the averaged actors, each following its own source's actor
        assert isinstance(model.policy.actor_average, PerSourceActor) and model.policy.actor_average.active_head == 1
    # one actor for everything regresses onto both sources at once: it lands between them
    shared = CRR.from_offline_data(buffer, policy_kwargs=dict(net_arch=[32, 32]), batch_size=64, beta=100.0, seed=0)
    shared.learn_offline(400)
    assert abs(mean_action(shared)) < 0.3
    # ... with the spread of the two sources' actions (+-0.6) as its standard deviation (untrained: 0.77)
    obs = th.as_tensor(np.random.default_rng(1).uniform(-1, 1, (50, 3)).astype(np.float32), device=shared.device)
    with th.no_grad():
        assert float(shared.actor.distribution_params(obs)[1].mean()) == pytest.approx(0.6, abs=0.1)


def test_an_actor_only_learns_from_its_source_and_the_critic_is_shared():
    buffer = two_source_buffer()
    buffer.set_sampling_weights({2: 0.0})  # every batch comes from source 0
    model = per_source_model(buffer)
    before = [head_params(model, 0), head_params(model, 1)]
    critic_before = th.cat([p.detach().flatten().clone() for p in model.critic.parameters()])
    model.learn_offline(20)
    assert not th.equal(head_params(model, 0), before[0])
    assert th.equal(head_params(model, 1), before[1])
    assert not th.equal(th.cat([p.detach().flatten() for p in model.critic.parameters()]), critic_before)
    assert len(model.policy.critic.q_networks) == 1  # one critic, not one per source


def test_rows_are_routed_to_their_actor():
    model = per_source_model(two_source_buffer(50))
    assert isinstance(model.actor, PerSourceActor)
    obs = th.rand(6, 3, device=model.device)
    heads = th.tensor([0, 1, 1, 0, 1, 0], device=model.device)
    mean, std = model.actor.distribution_params(obs, heads)
    for head in (0, 1):
        rows = heads == head
        expected_mean, expected_std = model.actor.heads[head].distribution_params(obs[rows])
        assert th.allclose(mean[rows], expected_mean) and th.allclose(std[rows], expected_std)
    # gradients reach only the actor of each row
    model.actor.distribution_params(obs[:1], heads[:1])[0].sum().backward()
    assert all(p.grad is None for p in model.actor.heads[1].parameters())
    assert any(p.grad is not None for p in model.actor.heads[0].parameters())


def test_save_load_keeps_every_actor(tmp_path):
    model = per_source_model(two_source_buffer(100))
    model.learn_offline(30)
    model.save(tmp_path / "crr")
    loaded = CRR.load(tmp_path / "crr")
    assert loaded.source_ids == [0, 2]
    obs = np.random.default_rng(0).uniform(-1, 1, (5, 3)).astype(np.float32)
    for source in (0, 2):
        expected = model.select_source(source).predict(obs, deterministic=True)[0]
        np.testing.assert_array_equal(loaded.select_source(source).predict(obs, deterministic=True)[0], expected)


class ConstantObsEnv(gym.Env):
    observation_space = OBS
    action_space = ACT

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        return np.zeros(3, np.float32), {}

    def step(self, action):
        # rewarded for the sign of the first action: source 0's actor earns +1, source 2's -1
        return np.zeros(3, np.float32), float(np.sign(action[0])), False, True, {}


def test_eval_callback_evaluates_each_env_with_its_source_actor():
    model = per_source_model(two_source_buffer())
    callback = MultiEnvEvalCallback(
        {"A": ConstantObsEnv(), "B": ConstantObsEnv()}, eval_freq=200, n_eval_episodes=1, sources={"A": 0, "B": 2}
    )
    model.learn_offline(200, callback=callback)
    final = {row["env"]: row["mean_reward"] for row in callback.results}
    assert final == {"A": 1.0, "B": -1.0}
    assert model.actor.active_head == 0  # back to the first source after the evaluation
    model.select_source(2)
    callback.evaluate()
    assert model.active_source == 2  # the evaluation restores the model's own selection
    with pytest.raises(ValueError, match="not evaluated"):
        MultiEnvEvalCallback({"A": ConstantObsEnv()}, sources={"C": 0})


def test_clear_errors():
    buffer = two_source_buffer(50)
    model = per_source_model(buffer)
    with pytest.raises(ValueError, match="has no actor"):
        model.select_source(1)
    with pytest.raises(ValueError, match="offline diagnostic"):
        model.learn(10)
    # one actor per source with SARSA targets: the lifelong buffer gives both the sources and the next actions
    sarsa = CRR.from_offline_data(buffer, actor_per_source=True, critic_target="sarsa", batch_size=16, seed=0)
    sarsa.learn_offline(5, log_interval=0)
    assert sarsa.replay_buffer is buffer and sarsa._n_updates == 5
    data = buffer.to_d4rl()  # the export keeps the source ids, and the import reads them back
    assert CRR.from_offline_data(data, actor_per_source=True, action_space=ACT).source_ids == sorted(buffer.source_counts())
    untagged = ReplayBuffer(50, OBS, ACT)
    untagged.add(np.zeros(OBS.shape), np.zeros(OBS.shape), np.zeros(ACT.shape), 0.0, False, [{}])
    with pytest.raises(ValueError, match="source-tagged"):  # an SB3 buffer has no sources
        CRR.from_offline_data(untagged, actor_per_source=True)
    with pytest.raises(ValueError, match="actor_per_source=True"):
        CRR.from_offline_data(buffer).select_source(0)
    # data with a source the model has no actor for
    other = two_source_buffer(20)
    other.set_source(5)
    obs = np.zeros((1, 3), np.float32)
    other.add(obs, obs, np.zeros((1, 2), np.float32), np.zeros(1), np.zeros(1), [{"stage": 5}])
    other.set_sampling_weights({0: 0.0, 2: 0.0})
    model.set_offline_data(other)
    with pytest.raises(ValueError, match=r"sources \[5\] that have no actor"):
        model.learn_offline(1)

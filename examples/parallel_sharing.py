"""
Parallel data sharing (the paper's appendix set-ups), then one distillation over all the robots' data.

- ``--setup copy``: one agent learns Env-A; it is then copied (policy, critic and replay buffer) into two agents
  that continue independently in Env-B and in Env-C. The buffers are merged, keeping the shared Env-A part once.
- ``--setup independent``: one agent learns Env-A then Env-B; a second agent learns Env-C from scratch. The two
  buffers are viewed as one (no copy) for the distillation.

Usage::

    python examples/parallel_sharing.py --setup copy
    python examples/parallel_sharing.py --setup independent --paper
"""

import argparse
import copy
import pathlib

from sb3_lifelong import CRR
from sb3_lifelong.common.buffers import LifelongBufferView, merge_buffers
from sb3_lifelong.common.distill import distill
from sb3_lifelong.experiments.sequential import (
    add_common_arguments,
    algo_kwargs,
    eval_callbacks,
    final_returns,
    finish,
    make_collector,
    make_eval_envs,
    make_schedule,
    now,
    prepare_output,
    resolve_config,
    set_threads,
    write_layout,
)

STAGES = {
    "quick": [{}, {"hip_deformation": 0.3}, {"friction": 0.1}],
    "tiny": [{}, {"hip_deformation": 0.3}, {"friction": 0.1}],
    "paper": ["default", "hip_0.3", "foot_1.6"],
}
NAMES = ["Env-A", "Env-B", "Env-C"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(parser)
    parser.add_argument(
        "--setup",
        choices=["copy", "independent"],
        default="copy",
        help="copy: one agent learns Env-A, then two copies learn Env-B and Env-C; independent: A -> B, and C from scratch",
    )
    args = parser.parse_args()
    set_threads()
    config = resolve_config(args)
    stages = STAGES[args.preset]
    first, second = config["stage_steps"][0], config["stage_steps"][1]
    output = pathlib.Path(args.output or f"runs/parallel_{args.setup}_{args.preset}")
    prepare_output(output, config, args.overwrite, setup=args.setup)
    tensorboard_log = str(output / "tensorboard")
    episode_steps = config.get("max_episode_steps")
    rows = []
    start = now()
    for seed in config["seeds"]:
        run_dir = output / f"seed_{seed}"
        eval_envs = make_eval_envs(config["env_id"], stages, NAMES, episode_steps)
        env_ab = make_schedule(config["env_id"], stages, None, episode_steps)
        agent_1 = make_collector(env_ab, config, seed, tensorboard_log)
        callbacks_1 = eval_callbacks(run_dir / "MPO_agent1", eval_envs, config)
        agent_1.learn(first, callback=callbacks_1, tb_log_name=f"agent1_s{seed}")

        env_c = make_schedule(config["env_id"], stages, None, episode_steps)
        env_c.set_stage(2)
        if args.setup == "copy":
            ancestor_size = agent_1.replay_buffer.size()
            agent_2 = make_collector(env_c, config, seed + 1000, tensorboard_log)
            agent_2.policy.load_state_dict(agent_1.policy.state_dict())
            agent_2.replay_buffer = copy.deepcopy(agent_1.replay_buffer)
            agent_2.num_timesteps = agent_1.num_timesteps
            agent_2.learning_starts = 0
        else:
            agent_2 = make_collector(env_c, config, seed + 1000, tensorboard_log)
        env_ab.set_stage(1)
        agent_1.learn(second, callback=callbacks_1, tb_log_name=f"agent1_s{seed}", reset_num_timesteps=False)
        callbacks_2 = eval_callbacks(run_dir / "MPO_agent2", eval_envs, config)
        agent_2.learn(second, callback=callbacks_2, tb_log_name=f"agent2_s{seed}", reset_num_timesteps=args.setup != "copy")
        for name, callbacks in (("MPO_agent1", callbacks_1), ("MPO_agent2", callbacks_2)):
            rows += [dict(seed=seed, method=name, env=k, final_return=v) for k, v in final_returns(callbacks[0]).items()]

        if args.setup == "copy":
            data = merge_buffers([agent_1.replay_buffer, agent_2.replay_buffer], starts=[0, ancestor_size])
        else:
            data = LifelongBufferView([agent_1.replay_buffer, agent_2.replay_buffer])
        print(f"seed {seed}: distilling {data.size()} transitions, per source {data.source_counts()}")
        students = (("distilled", dict(beta=1.0)), ("distilled_indicator", dict(advantage_transform="indicator")))
        for method, kwargs in students:
            callbacks = eval_callbacks(run_dir / method, eval_envs, config, source_q=True, offline=True)
            distill(
                data,
                CRR,
                gradient_steps=config["distill_steps"],
                callback=callbacks,
                tensorboard_log=tensorboard_log,
                tb_log_name=f"{method}_s{seed}",
                observation_space=agent_1.observation_space,
                action_space=agent_1.action_space,
                **algo_kwargs(config, seed),
                **kwargs,
            )
            rows += [dict(seed=seed, method=method, env=k, final_return=v) for k, v in final_returns(callbacks[0]).items()]
        if args.setup == "copy":
            switch = f"{NAMES[0]} -> {NAMES[1]} (agent 1), {NAMES[2]} (agent 2)"
        else:  # agent 2 starts from scratch: its steps count from 0
            switch = f"agent 1: {NAMES[0]} -> {NAMES[1]}"
        write_layout(run_dir, NAMES, [method for method, _ in students], [first], [switch], stages=stages)
    finish(output, rows, config, now() - start, plots=not args.no_plots)


if __name__ == "__main__":
    main()

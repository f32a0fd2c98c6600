"""
No task boundaries: the robot wears gradually. The right hip deforms linearly from 0 to 0.3 rad over the whole
life while MPO collects; the lifetime buffer is then distilled. The policies are evaluated on the robot at the
start, the middle and the end of its life.

Usage::

    python examples/continuous_drift.py
    python examples/continuous_drift.py --paper
"""

import argparse
import pathlib

import gymnasium as gym

from sb3_lifelong import CRR
from sb3_lifelong.envs import DynamicsSchedule, LinearRamp
from sb3_lifelong.experiments.sequential import (
    add_common_arguments,
    algo_kwargs,
    eval_callbacks,
    final_returns,
    finish,
    make_collector,
    now,
    prepare_output,
    resolve_config,
    set_threads,
    write_layout,
)

END_DEFORMATION = 0.3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_common_arguments(parser)
    args = parser.parse_args()
    set_threads()
    config = resolve_config(args)
    lifetime = sum(config["stage_steps"])
    output = pathlib.Path(args.output or f"runs/continuous_drift_{args.preset}")
    prepare_output(output, config, args.overwrite)
    make_kwargs = {} if config.get("max_episode_steps") is None else dict(max_episode_steps=config["max_episode_steps"])
    observed = ["hip_deformation"]

    def robot(deformation: float) -> DynamicsSchedule:
        env = DynamicsSchedule(gym.make(config["env_id"], **make_kwargs), append_params=True, observed_params=observed)
        env.set_params(hip_deformation=deformation, immediate=True)
        return env

    rows = []
    start = now()
    for seed in config["seeds"]:
        run_dir = output / f"seed_{seed}"
        eval_envs = {f"hip_{d:.2f}": robot(d) for d in (0.0, END_DEFORMATION / 2, END_DEFORMATION)}
        ramp = LinearRamp(0.0, END_DEFORMATION, begin=0, finish=lifetime)
        env = DynamicsSchedule(
            gym.make(config["env_id"], **make_kwargs),
            schedules={"hip_deformation": ramp},
            append_params=True,
            observed_params=observed,
        )
        mpo = make_collector(env, config, seed, str(output / "tensorboard"))
        callbacks = eval_callbacks(run_dir / "MPO", eval_envs, config, seed=seed)
        mpo.learn(lifetime, callback=callbacks, tb_log_name=f"MPO_s{seed}")
        rows += [dict(seed=seed, method="MPO", env=k, final_return=v) for k, v in final_returns(callbacks[0]).items()]
        callbacks = eval_callbacks(run_dir / "distilled", eval_envs, config, offline=True, seed=seed)
        mpo.distill(CRR, total_updates=config["distill_steps"], callback=callbacks, beta=1.0, **algo_kwargs(config, seed))
        rows += [dict(seed=seed, method="distilled", env=k, final_return=v) for k, v in final_returns(callbacks[0]).items()]
        # one source: the whole drifting life
        lifetime_data = {
            info["name"]: f"hip 0 -> {END_DEFORMATION} rad (drift)" for info in mpo.replay_buffer.sources.values()
        }
        write_layout(run_dir, list(eval_envs), distilled=["distilled"], sources=lifetime_data)
    finish(output, rows, config, now() - start, plots=not args.no_plots)


if __name__ == "__main__":
    main()

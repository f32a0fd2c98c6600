"""
The paper's two-stage protocol (and its three-stage variant) as a set of jobs: one seed is one self-contained command.

A seed's jobs, in the order they depend on each other:

* ``collect``: MPO learns Env-A for ``stage_steps[0]`` steps, then the robot changes and MPO goes on in Env-B for
  ``stage_steps[1]`` steps (and so on through every stage of the preset), keeping every transition in one
  :class:`~sb3_lifelong.LifelongReplayBuffer` on disk (the sources are named after the environments). The Stage-1
  agent and buffer are kept for the online baselines.
* ``distill_<variant>``: offline students on the lifetime buffer, all with the same number of updates: the
  pipeline (CRR exp beta=1), the imbalance baseline (CRR indicator), students of one source only, BC, and the
  paper's diagnostics (reward scale on Env-B, one actor per source, sampling ratios).
* ``online_CRR_indicator``, ``online_CRR_exp_beta1``: the conservative online baselines, continuing from the same
  Stage-1 agent (weights and buffer) through Stage 2 (last: they cost as much as the collection each).

Every job evaluates its policy on every environment periodically (``eval.csv``) and, when it has a critic, the
average Q-value per source (``q_sources.csv``); a finished job writes ``done.json`` and is skipped when the command
is run again, so a crashed or stopped seed continues where it was; a job that another process is running is
skipped (:func:`job_lock`).

Layout of ``<output>/seed_<k>/``::

    buffer/, buffer_stage1/     the lifetime buffer and its Stage-1 part (large: never commit them)
    collect/stage1.zip          the Stage-1 MPO agent
    <job>/eval.csv              timesteps, env, mean_reward, std_reward, n_episodes
    <job>/q_sources.csv         timesteps, source, name, q_mean, n (+ q_probe, mc_return, overestimation, n_mc)
    <job>/train.csv             timesteps, the train/ values (losses, weight_ess, beta, ...)
    <job>/tb/<Algorithm>_<k>/   the job's tensorboard run, as SB3 writes it (when tensorboard is installed): the
                                eval/<env>/, diagnostics/ and train/ values, so ``tensorboard --logdir <output>``
                                browses every seed, job and environment of the study
    <job>/done.json             wall time and the job's settings
"""

import contextlib
import dataclasses
import json
import pathlib
import shutil
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Callable, Optional, Union

import gymnasium as gym

try:  # POSIX: the job locks are advisory and simply skipped elsewhere
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None  # type: ignore[assignment]

from sb3_lifelong.bc import BC
from sb3_lifelong.buffers import LifelongReplayBuffer, merge_buffers
from sb3_lifelong.buffers.files import write_json_atomic
from sb3_lifelong.crr import CRR
from sb3_lifelong.distill import distill
from sb3_lifelong.envs import DynamicsSchedule
from sb3_lifelong.evaluation.callbacks import EVAL_SEED_OFFSET, MultiEnvEvalCallback, SourceQCallback, TrainLogCallback
from sb3_lifelong.experiments.report import REPEAT_MARK, split_repeat, stage_ends
from sb3_lifelong.mpo import MPO

Stage = Union[str, Mapping[str, float]]

#: the critics a preset's CRR students can have
STUDENT_CRITICS = ("mse", "categorical")


@dataclass(frozen=True)
class Preset:
    """
    Settings of the protocol (two stages, or more: one per entry of ``stages``).

    :param env_id: the robot (gymnasium id)
    :param stages: the physical setting of each environment (Env-A first), a dict of perturbations or a preset name
    :param stage_steps: environment steps of each stage (the paper: Env-B five times Env-A)
    :param distill_steps: gradient updates of every offline student
    :param eval_freq: evaluation period of the online methods, in environment steps
    :param distill_eval_freq: evaluation period of the students, in updates
    :param eval_episodes: episodes per environment and evaluation
    :param net_arch: hidden layers of every actor and critic
    :param batch_size: minibatch of the online methods
    :param student_batch_size: minibatch of the students
    :param num_samples: MPO's actions sampled per state
    :param learning_rate: learning rate of the online methods
    :param student_learning_rate: learning rate of the students
    :param learning_starts: MPO's random steps before learning
    :param env_names: names of the environments, in the order of ``stages``
    :param max_episode_steps: episode length limit (None: the environment's own)
    :param minutes_per_seed: measured wall time of one seed of ``run`` on one core of the reference machine (None:
        not measured), for the estimate printed before a run
    :param students: the students a seed trains (None: every one of :data:`STUDENTS`)
    :param online: whether a seed runs the online CRR baselines
    :param layer_norm: the LayerNorm torso for every network of the study (collector, students, online
        baselines); the presets run before MPO's default changed keep ``False``, the setting they ran with
    :param student_repeats: how many times each student is trained on a seed's buffer (each with its own student
        seed); the report scores a student by the mean of its repeats (``benchmarks/results/student_spread.md``: most
        of a student's seed-to-seed spread is its own training)
    :param student_critic: the CRR students' critic: ``"mse"`` (regression on the TD target) or ``"categorical"``
        (the paper's kind: 51 atoms on a support that holds every return of the seed's buffer, :func:`value_support`,
        so it cannot diverge; ``benchmarks/results/paper_cpu_three/bounded_critic``)
    :param note: what a run of this preset can and cannot show (printed with the report)
    """

    env_id: str
    stages: tuple[Stage, ...]
    stage_steps: tuple[int, ...]
    distill_steps: int
    eval_freq: int
    distill_eval_freq: int
    eval_episodes: int
    net_arch: tuple[int, ...] = (256, 256)
    batch_size: int = 256
    student_batch_size: int = 256
    num_samples: int = 20
    learning_rate: float = 3e-4
    student_learning_rate: float = 3e-4
    learning_starts: int = 10_000
    env_names: tuple[str, ...] = ("Env-A", "Env-B")
    max_episode_steps: Optional[int] = None
    minutes_per_seed: Optional[float] = None
    students: Optional[tuple[str, ...]] = None
    online: bool = True
    layer_norm: bool = False
    student_repeats: int = 1
    student_critic: str = "mse"
    note: str = ""

    def __post_init__(self) -> None:
        if self.student_repeats < 1:
            raise ValueError(f"student_repeats must be >= 1, got {self.student_repeats}")
        if self.student_critic not in STUDENT_CRITICS:
            raise ValueError(f"student_critic must be one of {STUDENT_CRITICS}, got {self.student_critic!r}")

    def jobs(self) -> list[str]:
        """:return: the jobs of one seed of this preset, in the order they run"""
        return job_names(self.students, self.online, self.student_repeats)

    def describe(self) -> dict[str, Any]:
        """:return: the settings as JSON-friendly values"""
        data = dataclasses.asdict(self)
        data["stages"] = [_describe(stage) for stage in self.stages]
        return data


PRESETS: dict[str, Preset] = {
    # one core of a CPU machine: Hopper with the hip deformed, Env-B five times Env-A
    "cpu": Preset(
        env_id="Hopper-v5",
        stages=({}, {"hip_deformation": 0.3}),
        stage_steps=(50_000, 250_000),
        distill_steps=30_000,
        eval_freq=10_000,
        distill_eval_freq=5_000,
        eval_episodes=5,
        net_arch=(128, 128),
        batch_size=128,
        student_batch_size=256,
        num_samples=10,
        learning_rate=1e-3,
        learning_starts=2_000,
    ),
    # the paper's scale: OP3 walking, 0.2M steps in Env-A then 1M in Env-B (a GPU machine, or days of CPU)
    "paper": Preset(
        env_id="sb3_lifelong/OP3Walk-v0",
        stages=("default", "hip_0.3"),
        stage_steps=(200_000, 1_000_000),
        distill_steps=500_000,
        eval_freq=20_000,
        distill_eval_freq=25_000,
        eval_episodes=5,
        note=(
            "The paper's scale. Estimated on one core of a 2-core AMD EPYC CPU from measured update rates (MPO and "
            "CRR at 256x256, about 40 updates per second there): roughly 8 h of collection, 14 h of online baselines and "
            "17 h for the twelve students, about 40 h per seed; not run end to end here. Use a GPU machine, or "
            "`study --workers N` / `--address` to spread seeds and students over many cores."
        ),
    ),
    # seconds: for the tests
    "tiny": Preset(
        env_id="Hopper-v5",
        stages=({}, {"hip_deformation": 0.3}),
        stage_steps=(200, 400),
        distill_steps=100,
        eval_freq=100,
        distill_eval_freq=50,
        eval_episodes=1,
        net_arch=(16, 16),
        batch_size=32,
        student_batch_size=32,
        num_samples=4,
        learning_rate=1e-3,
        learning_starts=100,
        max_episode_steps=50,
    ),
}

# the cpu protocol with the one Env-B of the env-pair table that hurt in both directions, the foot twice as long
# (benchmarks/results/env_pairs); evaluated on 10 episodes, as the 5 of `cpu` left the students' scores noisy
PRESETS["cpu_foot"] = dataclasses.replace(
    PRESETS["cpu"],
    stages=({}, {"foot_scale": 2.0}),
    eval_episodes=10,
    note=(
        "Env-B: the foot twice as long, the candidate with a zero-shot drop in both directions (Env-A policy in "
        "Env-B -87 %, Env-B policy in Env-A -42 %, one seed each at 50k steps). Claims pre-registered in "
        "benchmarks/results/paper_cpu_foot/README.md before any seed ran."
    ),
)

# the paper's three-stage set-up (its appendix: Env-A 0.2M, Env-B 0.2M, Env-C 1M steps) at the cpu budgets: 0.2 : 0.2 : 1
# of 250k steps; the order follows the env-pair table: each switch hurts the policy of the stage before, and the
# Env-C (foot x2) policy is poor in both earlier environments (benchmarks/results/env_pairs)
PRESETS["cpu_three"] = dataclasses.replace(
    PRESETS["cpu"],
    stages=({}, {"friction": 0.2}, {"foot_scale": 2.0}),
    stage_steps=(50_000, 50_000, 250_000),
    env_names=("Env-A", "Env-B", "Env-C"),
    eval_episodes=10,
    students=("CRR_exp_beta1", "CRR_indicator", "BC"),
    online=False,
    note=(
        "Three stages (the paper's appendix): default robot, then the floor's friction 0.2, then the foot twice as long, "
        "in the proportions 0.2 : 0.2 : 1; the students that need no task boundaries only, no online baselines. Claims "
        "pre-registered in benchmarks/results/paper_cpu_three/README.md before any seed ran."
    ),
)

# cpu_three again with what its first study asked for: the paper's kind of critic for the CRR students (a categorical
# one on the data's return bounds: no student diverged with it, benchmarks/results/paper_cpu_three/bounded_critic) and
# every student trained three times per buffer and scored by the mean (most of a student's spread is its own training,
# benchmarks/results/student_spread.md); its collection is cpu_three's, so cpu_three's buffers can be reused
PRESETS["cpu_three_c51"] = dataclasses.replace(
    PRESETS["cpu_three"],
    student_critic="categorical",
    student_repeats=3,
    note=(
        "cpu_three's set-up and claims, with categorical-critic CRR students each trained three times per buffer and "
        "scored by the mean. Pre-registered in benchmarks/results/paper_cpu_three_c51/README.md before any seed ran."
    ),
)

# the same at the paper's scale, one preset per environment combination of its appendix (OP3; a GPU machine)
for _number, _stages in enumerate(
    (
        ("default", "hip_0.2", "hip_0.2+foot_1.6"),
        ("default", "hip_0.3", "hip_0.3+foot_1.6"),
        ("default", "foot_1.2", "foot_1.2+ground_0.1"),
    ),
    start=1,
):
    PRESETS[f"paper_three_{_number}"] = dataclasses.replace(
        PRESETS["paper"],
        stages=_stages,
        stage_steps=(200_000, 200_000, 1_000_000),
        env_names=("Env-A", "Env-B", "Env-C"),
        students=PRESETS["cpu_three"].students,
        online=False,
        note=f"The paper's three-stage set-up, its environment combination {_number}, at its scale (a GPU machine).",
    )

# the dose-response study of the imbalance (benchmarks/results/imbalance_dose/README.md, pre-registered before any run):
# the collector at MPO's defaults (256x256 LayerNorm torso, 20 samples), Env-A and Env-B 100k steps each; the
# imbalance is a dose applied by the students (Env-B sampling share, Env-B reward scale), not by the collection
PRESETS["dose_hopper"] = Preset(
    env_id="Hopper-v5",
    stages=({}, {"foot_scale": 2.0}),
    stage_steps=(100_000, 100_000),
    distill_steps=200_000,
    eval_freq=10_000,
    distill_eval_freq=25_000,
    eval_episodes=10,
    learning_starts=5_000,
    layer_norm=True,
    students=(),
    online=False,
    student_critic="categorical",
    note="Collection of the imbalance dose study (Hopper, foot x2); students: benchmarks/imbalance_dose.py.",
)
# the natural-value-gap candidate (no healthy reward); its episodes are 1000 steps long, so 5 evaluation episodes
PRESETS["dose_cheetah"] = dataclasses.replace(
    PRESETS["dose_hopper"],
    env_id="HalfCheetah-v5",
    eval_episodes=5,
    note="Collection of the imbalance dose study (HalfCheetah, foot x2); students: benchmarks/imbalance_dose.py.",
)

# `make demo`: the cpu preset, shortened to minutes; too short to learn Env-A well, so it shows the pipeline, not the claims
PRESETS["demo"] = dataclasses.replace(
    PRESETS["cpu"],
    stage_steps=(8_000, 24_000),
    distill_steps=5_000,
    eval_freq=4_000,
    distill_eval_freq=1_000,
    eval_episodes=3,
    students=("CRR_exp_beta1", "CRR_indicator", "CRR_indicator_A_only", "BC"),
    online=False,
    note=(
        "This is the demo preset: 8k + 24k steps and 5k updates per student, a few minutes on a laptop CPU. At this "
        "budget MPO has not learnt Env-A yet, so there is little to forget and the students copy weak data: the "
        "claims are evaluated for the record, not expected to hold. The study that tests them is the 'cpu' preset "
        "(collection and students about 80 min per seed on one core, the online baselines about as long again): "
        "see benchmarks/results/paper_cpu/report.md."
    ),
)


@dataclass(frozen=True)
class Student:
    """
    One offline student of the lifetime buffer.

    :param algorithm: "CRR" or "BC"
    :param kwargs: the student's hyperparameters (``advantage_transform``, ``beta``, ``actor_per_source``)
    :param ratio: sampling ratio Env-A : Env-B as ``(a, b)`` (None: the raw sizes); ``(1, 0)``: Env-A only
    :param reward_scale: per-source reward scale, by environment index
    :param uses_boundaries: whether the variant needs to know which environment each transition came from
        (a diagnostic, not a lifelong method)
    :param about: one line for the reports
    """

    algorithm: str
    kwargs: dict[str, Any] = field(default_factory=dict)
    ratio: Optional[tuple[float, float]] = None
    reward_scale: Optional[dict[int, float]] = None
    uses_boundaries: bool = False
    about: str = ""


EXP = dict(advantage_transform="exp", beta=1.0)
INDICATOR = dict(advantage_transform="indicator")

#: the offline students of a seed, by name (the job is ``distill_<name>``)
STUDENTS: dict[str, Student] = {
    "CRR_exp_beta1": Student("CRR", EXP, about="the pipeline: CRR, exp transform, beta=1, whole buffer"),
    "CRR_indicator": Student("CRR", INDICATOR, about="the imbalance baseline: CRR, indicator transform, whole buffer"),
    "CRR_indicator_A_only": Student("CRR", INDICATOR, ratio=(1, 0), uses_boundaries=True, about="Env-A data only"),
    "CRR_indicator_B_only": Student("CRR", INDICATOR, ratio=(0, 1), uses_boundaries=True, about="Env-B data only"),
    "CRR_exp_beta1_A_only": Student("CRR", EXP, ratio=(1, 0), uses_boundaries=True, about="Env-A data only, exp beta=1"),
    "BC": Student("BC", about="behaviour cloning on the whole buffer"),
    "CRR_indicator_scale_rwd_B": Student(
        "CRR", INDICATOR, reward_scale={1: 0.5}, uses_boundaries=True, about="Env-B rewards scaled by 0.5"
    ),
    "CRR_indicator_two_actors": Student(
        "CRR", {**INDICATOR, "actor_per_source": True}, uses_boundaries=True, about="one actor per environment"
    ),
    "CRR_indicator_ratio_1to1": Student("CRR", INDICATOR, ratio=(1, 1), uses_boundaries=True, about="sampled 1:1"),
    "CRR_indicator_ratio_1to10": Student("CRR", INDICATOR, ratio=(1, 10), uses_boundaries=True, about="sampled 1:10"),
    "CRR_exp_beta1_ratio_1to1": Student("CRR", EXP, ratio=(1, 1), uses_boundaries=True, about="sampled 1:1"),
    "CRR_exp_beta1_ratio_1to10": Student("CRR", EXP, ratio=(1, 10), uses_boundaries=True, about="sampled 1:10"),
}

#: the online methods continuing from the Stage-1 agent (MPO itself continues in the ``collect`` job)
ONLINE: dict[str, dict[str, Any]] = {"CRR_indicator": INDICATOR, "CRR_exp_beta1": EXP}


#: repeat ``k`` of a student of seed ``s`` trains and evaluates with the student seed ``s + k * REPEAT_SEED_STRIDE``
#: (repeat 0 with ``s`` itself, as a study without repeats), far from the seeds of other buffers
REPEAT_SEED_STRIDE = 1000


def job_names(students: Optional[Sequence[str]] = None, online: bool = True, student_repeats: int = 1) -> list[str]:
    """
    :param students: the students (default: every one of :data:`STUDENTS`)
    :param online: with the online CRR baselines
    :param student_repeats: how many times each student is trained on the seed's buffer
    :return: the jobs of one seed, in the order they run (a student's repeats after all the first trainings)
    """
    if student_repeats < 1:
        raise ValueError(f"student_repeats must be >= 1, got {student_repeats}")
    names = list(students if students is not None else STUDENTS)
    jobs = ["collect"]
    jobs += [f"distill_{name}" for name in names]
    jobs += [f"distill_{name}{REPEAT_MARK}{k}" for k in range(1, student_repeats) for name in names]
    jobs += [f"online_{name}" for name in ONLINE] if online else []
    return jobs


# ------------------------------------------------------------------------------------------------- environments
def make_env(preset: Preset, switch_at: Optional[Sequence[int]] = None, start_timestep: int = 0) -> DynamicsSchedule:
    """The robot through its stages, with the true physical parameters appended to the observation (as the paper)."""
    kwargs: dict[str, Any] = {} if preset.max_episode_steps is None else dict(max_episode_steps=preset.max_episode_steps)
    return DynamicsSchedule(
        gym.make(preset.env_id, **kwargs),
        stages=list(preset.stages),
        switch_at=switch_at,
        append_params=True,
        start_timestep=start_timestep,
    )


def make_eval_envs(preset: Preset) -> dict[str, DynamicsSchedule]:
    """One environment per stage, pinned to it, named after it."""
    envs = {}
    for index, name in enumerate(preset.env_names):
        env = make_env(preset)
        env.set_stage(index, immediate=True)
        envs[name] = env
    return envs


def _describe(stage: Stage) -> Any:
    return stage if isinstance(stage, str) else dict(stage)


def switch_points(preset: Preset) -> list[int]:
    """:return: the timesteps at which the collector's environment changes"""
    return stage_ends(preset.stage_steps)[:-1]


# ------------------------------------------------------------------------------------------------- the jobs
def tensorboard_dir(directory: pathlib.Path) -> Optional[str]:
    """
    :param directory: a job's directory
    :return: the ``tensorboard_log`` of the job's model, ``<directory>/tb`` (SB3 writes each run into a folder
        ``<tb_log_name>_<k>`` there), or None when tensorboard is not installed (the CSV files only)
    """
    try:
        from torch.utils.tensorboard import SummaryWriter  # noqa: F401  (SB3 writes its event files with it)
    except ImportError:
        return None
    return str(directory / "tb")


def _common(preset: Preset, seed: int) -> dict[str, Any]:
    return dict(policy_kwargs=dict(net_arch=list(preset.net_arch), layer_norm=preset.layer_norm), seed=seed)


def value_support(reward_range: tuple[float, float], gamma: float, scales: Sequence[float] = ()) -> dict[str, float]:
    """
    The support of a categorical critic that holds every return of the data: no value outside it can be learnt, so
    the critic cannot diverge (the paper's critic is distributional).

    :param reward_range: the smallest and largest stored reward (:meth:`LifelongReplayBuffer.reward_range`)
    :param gamma: the discount factor
    :param scales: per-source reward scales applied at sampling time (the bounds cover each of them)
    :return: ``v_min`` and ``v_max`` (policy kwargs)
    """
    if not 0 <= gamma < 1:
        raise ValueError(f"a bounded value support needs 0 <= gamma < 1, got {gamma}")
    factors = [1.0, *scales]
    low = min(0.0, *(reward_range[0] * f for f in factors), *(reward_range[1] * f for f in factors))
    high = max(0.0, *(reward_range[0] * f for f in factors), *(reward_range[1] * f for f in factors))
    if low == high:
        high = low + 1.0  # all rewards 0: any non-empty support
    return dict(v_min=low / (1 - gamma), v_max=high / (1 - gamma))


def _callbacks(
    preset: Preset,
    directory: pathlib.Path,
    eval_freq: int,
    seed: int,
    data: Optional[Any] = None,
    q: bool = True,
    reward_scale: Optional[dict[int, float]] = None,
    **eval_kwargs: Any,
) -> list[Any]:
    # the train/ values first: the evaluation dumps the logger, which clears them
    callbacks: list[Any] = [
        TrainLogCallback(directory / "train.csv", log_freq=eval_freq),
        MultiEnvEvalCallback(
            make_eval_envs(preset),
            eval_freq,
            preset.eval_episodes,
            log_path=directory / "eval.csv",
            seed=EVAL_SEED_OFFSET + seed,
            **eval_kwargs,
        ),
    ]
    if q:
        q_log = directory / "q_sources.csv"
        callbacks.append(SourceQCallback(log_freq=eval_freq, log_path=q_log, data=data, reward_scale=reward_scale))
    return callbacks


def collect(preset: Preset, seed: int, run_dir: pathlib.Path, progress_bar: bool = False, log: Callable = print) -> None:
    """MPO through both stages into one lifetime buffer on disk; keeps the Stage-1 agent and buffer."""
    directory = run_dir / "collect"
    for stale in (directory, run_dir / "buffer", run_dir / "buffer_stage1"):  # an unfinished attempt: start again
        if stale.is_symlink():  # a link to another study's buffer (an unfinished adopt_collection): not ours to delete
            stale.unlink()
        else:
            shutil.rmtree(stale, ignore_errors=True)
    directory.mkdir(parents=True)
    model = MPO(
        "MlpPolicy",
        make_env(preset, switch_at=switch_points(preset)),
        replay_buffer_class=LifelongReplayBuffer,
        replay_buffer_kwargs=dict(path=run_dir / "buffer"),
        learning_starts=preset.learning_starts,
        num_samples=preset.num_samples,
        batch_size=preset.batch_size,
        learning_rate=preset.learning_rate,
        tensorboard_log=tensorboard_dir(directory),
        **_common(preset, seed),
    )
    buffer: Any = model.replay_buffer
    for index in reversed(range(len(preset.env_names))):  # names in the manifest; transitions carry their stage
        buffer.set_source(index, name=preset.env_names[index], metadata=dict(setting=_describe(preset.stages[index])))
    callbacks = _callbacks(preset, directory, preset.eval_freq, seed)
    for stage, steps in enumerate(preset.stage_steps):
        log(f"  stage {stage + 1}/{len(preset.stage_steps)}: {preset.env_names[stage]}, {steps:,} steps of MPO")
        model.learn(steps, callback=callbacks, reset_num_timesteps=stage == 0, progress_bar=progress_bar)
        if stage == 0:
            model.save(directory / "stage1.zip")
            merge_buffers([buffer], path=run_dir / "buffer_stage1").close()
    model.save(directory / "final.zip")
    buffer.close()


def online(name: str, preset: Preset, seed: int, run_dir: pathlib.Path, progress_bar: bool = False) -> None:
    """A conservative online baseline continuing from the Stage-1 agent (its weights and its buffer) through Stage 2."""
    directory = run_dir / f"online_{name}"
    shutil.rmtree(directory, ignore_errors=True)
    directory.mkdir(parents=True)
    # the agent only: its saved buffer settings point at the lifetime buffer, which other jobs may be reading
    stage1 = MPO.load(run_dir / "collect" / "stage1.zip", device="cpu", custom_objects={"replay_buffer_kwargs": {}})
    start = int(stage1.num_timesteps)
    env = make_env(preset, switch_at=switch_points(preset))  # learn() tells it the timestep: model.num_timesteps
    model = CRR(
        "MlpPolicy",
        env,
        replay_buffer_class=LifelongReplayBuffer,
        learning_starts=0,
        batch_size=preset.batch_size,
        learning_rate=preset.learning_rate,
        tensorboard_log=tensorboard_dir(directory),
        **ONLINE[name],
        **_common(preset, seed),
    )
    model.policy.load_state_dict(stage1.policy.state_dict())
    with LifelongReplayBuffer.open(run_dir / "buffer_stage1", read_only=True) as stage1_buffer:
        model.replay_buffer = merge_buffers([stage1_buffer])  # a private copy in memory, which this agent extends
    model.num_timesteps = start
    model.learn(sum(preset.stage_steps[1:]), callback=_callbacks(preset, directory, preset.eval_freq, seed),
                reset_num_timesteps=False, progress_bar=progress_bar)  # fmt: skip


def sampling_weights(ratio: tuple[float, float], counts: Mapping[int, int]) -> dict[int, float]:
    """
    Per-source sampling weights that make batches hold Env-A and Env-B transitions in the proportion ``ratio``.

    :param ratio: ``(a, b)``: Env-A : Env-B
    :param counts: transitions per source (0: Env-A, 1: Env-B)
    :return: source id -> weight
    """
    a, b = ratio
    if a < 0 or b < 0 or a + b == 0:
        raise ValueError(f"a sampling ratio needs two non-negative parts, not both zero, got {ratio}")
    n_a, n_b = counts.get(0, 0), counts.get(1, 0)
    if (a > 0 and n_a == 0) or (b > 0 and n_b == 0):
        raise ValueError(f"ratio {ratio} asks for a source with no data (transitions per source: {dict(counts)})")
    return {0: a / n_a if n_a else 0.0, 1: b / n_b if n_b else 0.0}


def distill_student(
    name: str,
    preset: Preset,
    seed: int,
    run_dir: pathlib.Path,
    progress_bar: bool = False,
    student: Optional[Student] = None,
    student_seed: Optional[int] = None,
) -> None:
    """
    Train one offline student on the lifetime buffer (opened read-only) and save it in ``run_dir/distill_<name>``.

    :param name: the student's name (its settings are ``STUDENTS[name]`` unless ``student`` is given)
    :param preset: the protocol's settings
    :param seed: the seed
    :param run_dir: the seed's directory (holds ``buffer``)
    :param progress_bar: show a progress bar
    :param student: settings of a student that is not in :data:`STUDENTS` (e.g. a benchmark's variant)
    :param student_seed: the seed of the student's own training and of its evaluation environments (default:
        ``seed``), to train the same student several times on one buffer
    """
    student = STUDENTS[name] if student is None else student
    directory = run_dir / f"distill_{name}"
    shutil.rmtree(directory, ignore_errors=True)
    directory.mkdir(parents=True)
    data = LifelongReplayBuffer.open(run_dir / "buffer", read_only=True)
    everything = LifelongReplayBuffer.open(run_dir / "buffer", read_only=True)  # unweighted, for Q per source
    if student.ratio is not None:
        data.set_sampling_weights(sampling_weights(student.ratio, data.source_counts()))
    if student.reward_scale is not None:
        data.set_reward_scale(student.reward_scale)
    kwargs = dict(student.kwargs)
    sources = None
    if kwargs.get("actor_per_source"):
        sources = {env_name: index for index, env_name in enumerate(preset.env_names)}
    algorithm = BC if student.algorithm == "BC" else CRR
    seed = seed if student_seed is None else student_seed
    common = _common(preset, seed)
    if algorithm is CRR and preset.student_critic == "categorical":
        common["policy_kwargs"]["distributional_critic"] = True
    common["policy_kwargs"].update(kwargs.pop("policy_kwargs", {}))  # the student's own network options
    if common["policy_kwargs"].get("distributional_critic") and "v_min" not in common["policy_kwargs"]:
        scales = list((student.reward_scale or {}).values())
        common["policy_kwargs"].update(value_support(data.reward_range(), kwargs.get("gamma", 0.99), scales))
    callbacks = _callbacks(
        preset,
        directory,
        preset.distill_eval_freq,
        seed,
        data=everything,
        q=algorithm is CRR,
        reward_scale=student.reward_scale,
        sources=sources,
    )
    model = distill(
        data,
        student_class=algorithm,
        gradient_steps=preset.distill_steps,
        callback=callbacks,
        progress_bar=progress_bar,
        batch_size=preset.student_batch_size,
        learning_rate=preset.student_learning_rate,
        tensorboard_log=tensorboard_dir(directory),
        tb_log_name=algorithm.__name__,
        **kwargs,
        **common,
    )
    model.save(directory / "student.zip")
    data.close()
    everything.close()


def distill_on_study(
    study: pathlib.Path,
    seed: int,
    output: pathlib.Path,
    students: Mapping[str, Student],
    preset: Preset,
    student_seed: Optional[int] = None,
    about: Optional[Mapping[str, Any]] = None,
    log: Callable[[str], None] = print,
) -> list[str]:
    """
    Train students that are not the study's own on one finished seed's lifetime buffer of ``study`` (linked,
    read-only), each in ``output/seed_<seed>/distill_<name>``; a finished one (``done.json``) is skipped, so a
    stopped command is simply run again. For the benchmarks that vary the students of a study.

    :param study: the study's output directory
    :param seed: the seed whose buffer is distilled
    :param output: where the students go
    :param students: the students by job name
    :param preset: the protocol's settings (budgets, evaluations)
    :param student_seed: the seed of the students' own training and evaluations (default: ``seed``)
    :param about: extra entries of each ``done.json`` (beside ``seconds``, ``buffer_seed``, ``student_seed`` and the
        student's ``settings``)
    :param log: where progress messages go
    :return: the names of the students trained by this call
    :raises FileNotFoundError: the study has no finished buffer for ``seed``
    """
    run_dir = output / f"seed_{seed}"
    source = study / f"seed_{seed}" / "buffer"
    if not (study / f"seed_{seed}" / "collect" / "done.json").exists() or not source.is_dir():
        raise FileNotFoundError(f"{source} is not a finished seed's buffer (run the study's collect job first)")
    run_dir.mkdir(parents=True, exist_ok=True)
    link = run_dir / "buffer"
    if not link.exists():
        link.symlink_to(source.resolve())
    trained = []
    for name, student in students.items():
        if (run_dir / f"distill_{name}" / "done.json").exists():
            continue
        start = time.perf_counter()
        log(f"buffer {seed}: {name}, {preset.distill_steps:,} updates")
        distill_student(name, preset, seed, run_dir, student=student, student_seed=student_seed)
        seconds = time.perf_counter() - start
        done: dict[str, Any] = dict(seconds=seconds, buffer_seed=seed)
        done.update(student_seed=seed if student_seed is None else student_seed, settings=dataclasses.asdict(student))
        done.update(about or {})
        write_json_atomic(str(run_dir / f"distill_{name}" / "done.json"), done)
        log(f"buffer {seed}: {name} done in {seconds / 60:.1f} min")
        trained.append(name)
    return trained


# ------------------------------------------------------------------------------------------------- one seed
def record_settings(preset: Preset, output: pathlib.Path) -> None:
    """
    Record the preset of a study in ``output/preset.json``, or check that it is the one recorded.

    :raises ValueError: when ``output`` holds a study with other settings (their seeds cannot be mixed)
    """
    settings = output / "preset.json"
    described = json.loads(json.dumps(preset.describe()))
    if settings.exists():
        recorded = json.loads(settings.read_text())
        if same_settings(recorded, described):
            if recorded.get("student_repeats", 1) >= described["student_repeats"]:
                return
            # more repeats of the students on the same buffers: the study's other settings are unchanged
        else:
            raise ValueError(
                f"{output} holds a study run with other settings ({settings}); its seeds cannot be mixed with these. "
                "Choose another --output, or delete that directory to start again."
            )
    output.mkdir(parents=True, exist_ok=True)
    write_json_atomic(str(settings), described)


#: settings added to :class:`Preset` after studies were recorded, with the value those studies ran with
LATER_SETTINGS: dict[str, Any] = {"layer_norm": False, "student_repeats": 1, "student_critic": "mse"}


def same_settings(recorded: Mapping[str, Any], described: Mapping[str, Any]) -> bool:
    """
    :param recorded: a study's ``preset.json``
    :param described: :meth:`Preset.describe` of a preset, through JSON
    :return: whether they are one study's settings: equal but for the number of student repeats, with settings
        that a recorded file predates read as the value it ran with (:data:`LATER_SETTINGS`)
    """

    def comparable(data: Mapping[str, Any]) -> dict[str, Any]:
        filled = {**LATER_SETTINGS, **data}
        filled.pop("student_repeats")
        return filled

    return comparable(recorded) == comparable(described)


#: the settings that only the students and the report read: two studies that differ in nothing else collect alike
STUDENT_SETTINGS = (
    "distill_steps",
    "distill_eval_freq",
    "student_batch_size",
    "student_learning_rate",
    "students",
    "online",
    "student_repeats",
    "student_critic",
    "note",
    "minutes_per_seed",
)


def collection_differences(recorded: Mapping[str, Any], described: Mapping[str, Any]) -> list[str]:
    """
    :param recorded: a study's ``preset.json``
    :param described: :meth:`Preset.describe` of a preset, through JSON
    :return: the settings of the collection (everything but :data:`STUDENT_SETTINGS`) in which they differ
    """
    filled = {**LATER_SETTINGS, **recorded}, {**LATER_SETTINGS, **described}
    keys = sorted((set(filled[0]) | set(filled[1])) - set(STUDENT_SETTINGS))
    return [key for key in keys if filled[0].get(key) != filled[1].get(key)]


#: the directories of a seed that a study reusing its collection links to (the lifetime and the Stage-1 buffers)
COLLECTED_BUFFERS = ("buffer", "buffer_stage1")


def adopt_collection(preset: Preset, seed: int, source: pathlib.Path, output: pathlib.Path, log: Callable = print) -> bool:
    """
    Reuse seed ``seed``'s finished collection of the study ``source`` in the study ``output``, to train other
    students on the same buffers: its ``collect`` job (curves, agents) is copied, its buffers are linked by absolute
    path (the jobs open them read-only), so ``source`` must stay where it is while ``output``'s students run. Holds
    the seed's ``collect`` job lock. Nothing is done when the seed has adopted this collection already.

    :param preset: the settings of the study in ``output``
    :param seed: the seed
    :param source: a study whose collection settings are ``preset``'s (only :data:`STUDENT_SETTINGS` may differ)
    :param output: the study that reuses it
    :param log: where the one-line messages go
    :return: whether the collection was adopted now
    :raises ValueError: when ``source`` is not a study, collected with other settings, this seed's collection there
        has not finished or lacks a buffer, or ``output``'s seed has another collection (its own, or another study's)
    :raises RuntimeError: when another process is running this seed's ``collect`` job in ``output``
    """
    source, run_dir = pathlib.Path(source).resolve(), output / f"seed_{seed}"
    origin = source / f"seed_{seed}"
    run_dir.mkdir(parents=True, exist_ok=True)
    with job_lock(run_dir, "collect") as ours:
        if not ours:
            raise RuntimeError(f"seed {seed}: another process is running this seed's collect job ({run_dir})")
        done_path = run_dir / "collect" / "done.json"
        if done_path.exists():
            adopted = json.loads(done_path.read_text()).get("adopted_from")
            if adopted is None:
                raise ValueError(f"seed {seed} of {output} has a collection of its own: it cannot reuse {origin}")
            if pathlib.Path(adopted) != origin:
                raise ValueError(
                    f"seed {seed} of {output} reuses the collection of {adopted}, not {origin}; delete "
                    f"{run_dir / 'collect'} to reuse another one"
                )
            check_linked_buffers(run_dir)
            return False
        if not (source / "preset.json").exists():
            raise ValueError(f"{source} is not a study (no preset.json): nothing to reuse")
        recorded = json.loads((source / "preset.json").read_text())
        differences = collection_differences(recorded, json.loads(json.dumps(preset.describe())))
        if differences:
            raise ValueError(
                f"{source} collected with other settings ({', '.join(differences)}): its buffers are not this one's"
            )
        if not (origin / "collect" / "done.json").exists():
            raise ValueError(f"seed {seed} of {source} has no finished collection ({origin / 'collect' / 'done.json'})")
        targets = {name: (origin / name).resolve() for name in COLLECTED_BUFFERS}  # no chain of links
        missing = [str(origin / name) for name, target in targets.items() if not (target / "manifest.json").exists()]
        if missing:
            raise ValueError(f"seed {seed} of {source} is not a whole collection: no buffer at {', '.join(missing)}")
        for name, target in targets.items():
            link = run_dir / name
            if link.is_symlink():
                link.unlink()
            elif link.exists():
                shutil.rmtree(link)  # an unfinished collection of this study's own
            link.symlink_to(target, target_is_directory=True)
        staging = run_dir / ".collect.adopting"
        shutil.rmtree(staging, ignore_errors=True)
        shutil.copytree(origin / "collect", staging, ignore=shutil.ignore_patterns("done.json"))
        done = {**json.loads((origin / "collect" / "done.json").read_text()), "adopted_from": str(origin)}
        write_json_atomic(str(staging / "done.json"), done)
        shutil.rmtree(run_dir / "collect", ignore_errors=True)
        staging.rename(run_dir / "collect")  # done.json appears with the whole directory
    log(f"seed {seed}: collection reused from {origin} (buffers linked, not copied)")
    return True


def check_linked_buffers(run_dir: pathlib.Path) -> None:
    """
    :param run_dir: a seed's directory
    :raises FileNotFoundError: when a buffer it links to (:func:`adopt_collection`) is gone, naming where it was
    """
    for name in COLLECTED_BUFFERS:
        link = run_dir / name
        if link.is_symlink() and not link.exists():
            raise FileNotFoundError(
                f"{link} links to {link.readlink()}, which is gone: this seed reuses another study's collection, which "
                f"was moved or deleted. Delete {run_dir / 'collect'} and run again with --collection-from where that "
                "study is now, or without it to collect this seed again"
            )


@contextlib.contextmanager
def job_lock(run_dir: pathlib.Path, job: str) -> Iterator[bool]:
    """
    Hold a seed's job for this process, so that two commands of the same seed (two terminals, a runner beside a
    command) never run one job at once: the second would delete the first one's directory and mix their files.

    :param run_dir: the seed's directory
    :param job: the job's name
    :return: (as a context manager) True if this process holds the job, False if another process does
    """
    if fcntl is None:  # pragma: no cover
        yield True
        return
    with open(run_dir / f".{job}.lock", "a") as file:  # beside the job's directory, which a job deletes first
        try:
            fcntl.flock(file.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(file.fileno(), fcntl.LOCK_UN)


def run_seed(
    preset: Preset,
    seed: int,
    output: pathlib.Path,
    jobs: Optional[Sequence[str]] = None,
    progress_bar: bool = False,
    log: Callable = print,
    collection_from: Optional[pathlib.Path] = None,
) -> list[str]:
    """
    Run the jobs of one seed that have not finished yet (each writes ``done.json`` when it finishes). A job that
    another process is running (see :func:`job_lock`) is skipped; ``collect``, which the other jobs need, raises.

    :param preset: the protocol's settings
    :param seed: the seed
    :param output: the experiment directory (``seed_<k>`` is created inside)
    :param jobs: the jobs to run (default: the preset's, :meth:`Preset.jobs`), always after ``collect``
    :param progress_bar: show a progress bar per job
    :param log: where the one-line messages go
    :param collection_from: another study whose collection of this seed to reuse (:func:`adopt_collection`)
    :return: the jobs that ran
    """
    record_settings(preset, output)
    run_dir = output / f"seed_{seed}"
    run_dir.mkdir(parents=True, exist_ok=True)
    if collection_from is not None:
        adopt_collection(preset, seed, collection_from, output, log)
    check_linked_buffers(run_dir)
    wanted = list(jobs) if jobs is not None else preset.jobs()
    known = job_names(student_repeats=preset.student_repeats)
    unknown = sorted(set(wanted) - set(known))
    if unknown:
        raise ValueError(f"unknown jobs {unknown}; the jobs are {known}")
    if "collect" not in wanted and not (run_dir / "collect" / "done.json").exists():
        wanted.insert(0, "collect")
    ran = []
    todo = [job for job in known if job in wanted and not (run_dir / job / "done.json").exists()]
    skipped = [job for job in wanted if job not in todo]
    if skipped:
        log(f"seed {seed}: {len(skipped)} job(s) already done, skipped: {', '.join(skipped)}")
    for position, job in enumerate(todo):
        with job_lock(run_dir, job) as ours:
            if not ours:
                if job == "collect":
                    raise RuntimeError(
                        f"seed {seed}: another process is running this seed's collect job ({run_dir}); run this command "
                        "again once it has finished"
                    )
                log(f"seed {seed}: job {job} is running in another process: skipped")
                continue
            if (run_dir / job / "done.json").exists():  # finished by another process since the list was made
                log(f"seed {seed}: job {job} was finished by another process: skipped")
                continue
            log(f"seed {seed}: job {position + 1}/{len(todo)} {job} ...")
            start = time.perf_counter()
            if job == "collect":
                collect(preset, seed, run_dir, progress_bar, log)
            elif job.startswith("online_"):
                online(job[len("online_") :], preset, seed, run_dir, progress_bar)
            else:
                name, repeat = split_repeat(job[len("distill_") :])
                student_seed = seed + repeat * REPEAT_SEED_STRIDE
                distill_student(job[len("distill_") :], preset, seed, run_dir, progress_bar, STUDENTS[name], student_seed)
            seconds = time.perf_counter() - start
            done = dict(job=job, seed=seed, seconds=seconds, preset=preset.describe())
            if job.startswith("distill_"):
                done.update(student=dataclasses.asdict(STUDENTS[name]), repeat=repeat, student_seed=student_seed)
            write_json_atomic(str(run_dir / job / "done.json"), done)  # never a half-written "done"
            log(f"seed {seed}: job {job} done in {seconds / 60:.1f} min")
            ran.append(job)
    return ran

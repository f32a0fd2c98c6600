"""
What a study of the paper's protocol is: its settings (:class:`Preset`, and the study presets by name,
:data:`PRESETS`), its offline students (:data:`STUDENTS`) and online baselines (:data:`ONLINE`), the names of one
seed's jobs (:func:`job_names`), and how a study's recorded settings (``preset.json``) compare with a preset.

Plain data and small functions of it: the jobs that run a preset are :mod:`sb3_lifelong.experiments.protocol`, the
report that reads a study is :mod:`sb3_lifelong.experiments.report`; both read this module, and it imports neither.
A new study preset goes here; its pre-registered claims go in its study folder's ``claims.py``
(:mod:`~sb3_lifelong.experiments.claims`).
"""

import dataclasses
import importlib.util
import itertools
import json
import math
import os
import pathlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Optional, Union

Stage = Union[str, Mapping[str, float]]
#: a drift: parameter -> the values it has at the first and at the last step of the robot's life
DriftSpec = Mapping[str, tuple[float, float]]

#: the critics a preset's CRR students can have
STUDENT_CRITICS = ("mse", "categorical")
#: the parallel data-sharing set-ups of the paper's appendix (``Preset.sharing``)
SHARING = ("copy", "independent")
#: the seed offset of the second collector of a sharing study (its own exploration, evaluated on the seed's episodes)
AGENT2_SEED_OFFSET = 1000


def resolve_device(device: Optional[str]) -> Optional[str]:
    """:return: ``device``, with ``"auto"`` made this machine's choice: ``"cuda"`` if torch sees a GPU, else ``"cpu"``"""
    if device != "auto":
        return device
    import torch as th

    return "cuda" if th.cuda.is_available() else "cpu"


def check_device(device: str, here: bool = True) -> None:
    """
    :param device: a torch device's name
    :param here: check that this machine has it too (False: the name only, e.g. for the report of a study that ran
        on another machine)
    :raises ValueError: when torch does not know the name (``"gpu"``), or (``here``) names a GPU that this machine
        does not have
    """
    import torch as th

    try:
        parsed = th.device(device)
    except (RuntimeError, TypeError) as error:
        raise ValueError(f"device {device!r} is not a torch device (e.g. 'cpu', 'cuda', 'cuda:1'): {error}") from None
    if parsed.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"device {device!r}: a study runs on 'cpu' or a GPU ('cuda', 'cuda:<k>', 'mps')")
    if not here:
        return
    if parsed.type == "cuda":
        if not th.cuda.is_available():
            raise ValueError(f"device {device!r}: torch sees no CUDA GPU on this machine (run with --device cpu)")
        if parsed.index is not None and parsed.index >= th.cuda.device_count():
            raise ValueError(f"device {device!r}: this machine has {th.cuda.device_count()} CUDA GPU(s)")
    elif parsed.type == "mps" and not th.backends.mps.is_available():
        raise ValueError(f"device {device!r}: torch sees no MPS device on this machine (run with --device cpu)")


@dataclass(frozen=True)
class Preset:
    """
    Settings of the protocol (two stages, or more: one per entry of ``stages``).

    :param env_id: the robot (gymnasium id)
    :param stages: the physical setting of each environment (Env-A first), a dict of perturbations or a named stage
        (:data:`~sb3_lifelong.envs.NAMED_STAGES`)
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
        seed); the report scores a student by the mean of its repeats (most of a student's seed-to-seed spread is its
        own training: ``benchmarks/studies/student_spread/student_spread.md``)
    :param student_critic: the CRR students' critic: ``"mse"`` (regression on the TD target) or ``"categorical"``
        (the paper's kind: 51 atoms on a support that holds every return of the seed's buffer,
        :func:`~sb3_lifelong.experiments.jobs.value_support`, so it cannot diverge;
        ``benchmarks/studies/paper_cpu_three/bounded_critic``)
    :param env_a_learnt: the Env-A return MPO must have reached when it leaves Env-A (the mean of its last evaluations
        there) for the claims about Env-A (forgetting it, remembering it, the imbalance drop and its diagnostics) to
        be testable on a seed. The report tests a claim on the seeds where its preconditions were measured and hold,
        and reads it *not testable* when every seed measured a failure of one
        (:data:`~sb3_lifelong.experiments.claims.PRECONDITIONS`). None: not
        checked; the presets run before the report could check preconditions keep None, so their reports read as
        they did. The same for the next three.
    :param value_gap: the least ratio of the discounted return of the last environment's data to Env-A's data (the
        collector's Monte-Carlo measurement) for the imbalance claims to be testable: the paper's explanation needs the
        later data to be worth more
    :param min_weight_ess: the least effective sample size of the exp beta=1 student's weights (a fraction of a batch)
        for the claims that call it conservative: on a reward scale where ``beta=1`` is greedy, it is not
    :param max_switch_spread: the largest spread (standard deviation over the mean) of MPO's last evaluations in an
        environment before it leaves it (:func:`~sb3_lifelong.experiments.scores.switch_spread`) for the claims that it
        forgets that environment to be testable: forgetting is a drop from a level, and an agent still climbing or
        oscillating when it leaves has none to drop from (one evaluation's dip turns "end / switch" into any ratio)
    :param device: where every model of the study runs (a torch device: ``"cpu"``, ``"cuda"``, ``"cuda:1"``). The
        presets' small networks, one transition per update, run fastest as one process per CPU core; larger networks
        (the ``paper`` preset) gain from a GPU. A study runs on one device: the settings record it, and a paused job
        continues on it, so that a run in parts computes what an uninterrupted one does
    :param toy: a budget too small to learn Env-A (``tiny``, ``demo``): a run shows that the pipeline runs, not the
        paper's findings, and its report says so at its top (``toy_budget``)
    :param note: what a run of this preset can and cannot show (printed with the report)
    :param drift: parameters that change without boundaries, ``{parameter: (start, end)}``: the collector's robot
        (:func:`~sb3_lifelong.experiments.jobs.make_env`) moves each linearly from ``start`` at timestep 0 to ``end``
        at the end of its life (the sum of ``stage_steps``), through every stage, applied at each episode's start. A
        stage may not set a drifting parameter. Every robot of the study observes the drifting parameters beside those
        the stages vary (:attr:`observed_params`); the evaluation environments are the stages
        (:func:`~sb3_lifelong.experiments.jobs.eval_envs`), with the drifting parameters at their nominal values
        unless ``drift_eval_at`` places them. None: no drift (the presets recorded before the field, unchanged)
    :param drift_eval_at: with a drift, where in the life each stage's evaluation robot has the drifting parameters,
        one fraction per stage (0: their value at the first step, 1: at the last;
        :func:`~sb3_lifelong.experiments.presets.evaluation_stages`): e.g.
        ``(0.0, 0.5, 1.0)`` evaluates a three-stage life on the robot of its first, middle and last step. None: the
        drifting parameters at their nominal values
    :param sharing: two robots at the same time, their data shared (the paper's appendix; three stages, Env-A, Env-B,
        Env-C). The ``collect`` job's agent learns Env-A for ``stage_steps[0]`` steps, then Env-B for
        ``stage_steps[1]``; the ``collect_agent2`` job's agent learns Env-C for ``stage_steps[2]`` steps, side by side
        with Env-B: ``"copy"``, a copy of the first agent at the switch (its weights and its Stage-1 buffer), or
        ``"independent"``, a new agent from the first step. The ``share`` job merges the two lifetime buffers into
        one (a copy's Env-A once), which the students distill. None: one robot through its stages (the presets
        recorded before the field, unchanged)
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
    env_a_learnt: Optional[float] = None
    value_gap: Optional[float] = None
    min_weight_ess: Optional[float] = None
    max_switch_spread: Optional[float] = None
    device: str = "cpu"
    toy: bool = False
    note: str = ""
    drift: Optional[DriftSpec] = None
    drift_eval_at: Optional[tuple[float, ...]] = None
    sharing: Optional[str] = None

    def __post_init__(self) -> None:
        if not len(self.stages) == len(self.stage_steps) == len(self.env_names):
            raise ValueError(
                f"a preset needs one step count and one name per stage: {len(self.stages)} stages, stage_steps "
                f"{self.stage_steps}, env_names {self.env_names}"
            )
        if len(self.stages) < 2:
            raise ValueError(
                f"a preset needs at least two stages (its scores and report read the switches between them), got "
                f"{len(self.stages)}: a drift over one environment's life (drift=...) goes on top of two or more stages"
            )
        if self.student_repeats < 1:
            raise ValueError(f"student_repeats must be >= 1, got {self.student_repeats}")
        if self.student_critic not in STUDENT_CRITICS:
            raise ValueError(f"student_critic must be one of {STUDENT_CRITICS}, got {self.student_critic!r}")
        check_device(self.device, here=False)
        if self.drift is not None:
            object.__setattr__(self, "drift", check_drift(self.drift, self.stages))
        if self.drift_eval_at is not None:
            object.__setattr__(self, "drift_eval_at", check_drift_eval_at(self.drift_eval_at, self.drift, len(self.stages)))
        if self.sharing is not None:
            check_sharing(self)

    def jobs(self) -> list[str]:
        """:return: the jobs of one seed of this preset, in the order they run"""
        return job_names(self.students, self.online, self.student_repeats, self.sharing is not None)

    def requires(self, job: str) -> tuple[str, ...]:
        """
        :param job: one of the preset's job names
        :return: the jobs that must have finished before ``job`` starts: ``collect`` for every other job; with
            ``sharing``, ``share`` for the students and both collections for ``share`` (the second collection
            of the ``"copy"`` set-up starts from the first one's Stage 1, the runner's ``collect`` up to the switch)
        """
        if job in ("collect", "collect_agent2"):
            return ()
        if self.sharing is None:
            return ("collect",)
        return ("collect", "collect_agent2") if job == "share" else ("share",)

    def with_requirements(self, jobs: Sequence[str]) -> list[str]:
        """
        :param jobs: some of the preset's job names
        :return: them and every job they need (:meth:`requires`, and what those need), in the order the jobs run
            (:meth:`jobs`; names the preset does not run, after them)
        """
        wanted, needed = set(jobs), list(jobs)
        while needed:
            for required in self.requires(needed.pop()):
                if required not in wanted:
                    wanted.add(required)
                    needed.append(required)
        order = self.jobs()
        return [name for name in order if name in wanted] + sorted(wanted - set(order))

    @property
    def collector_steps(self) -> tuple[int, ...]:
        """The environment steps of each stage of the ``collect`` job's agent: every stage, or Env-A and Env-B of a
        sharing study (``sharing``: Env-C is the second agent's)."""
        return self.stage_steps[:2] if self.sharing is not None else self.stage_steps

    @property
    def data_buffer(self) -> str:
        """The directory, in a seed's, of the buffer the students distill: ``buffer``, or ``buffer_shared`` (the
        ``share`` job's) in a sharing study."""
        return "buffer" if self.sharing is None else SHARED_BUFFER

    @property
    def env_kwargs(self) -> dict[str, Any]:
        """The keyword arguments of ``gym.make`` for the robot: its episode length limit, when the preset sets one."""
        return {} if self.max_episode_steps is None else dict(max_episode_steps=self.max_episode_steps)

    @property
    def observed_params(self) -> Optional[list[str]]:
        """
        The parameters appended to the observation of every robot of the study (the collector's, the evaluations'):
        None without a drift (:class:`~sb3_lifelong.envs.DynamicsSchedule`'s default, those the stages vary), else
        :func:`observed_params`.
        """
        return observed_params(self.stages, self.drift)

    def describe(self) -> dict[str, Any]:
        """
        :return: the settings as JSON-friendly values; without a drift (or sharing), no such key: the settings of the presets
            before the field, as their studies recorded them (``preset.json``, a paused student's record, the cost log's
            fingerprint)
        """
        data = dataclasses.asdict(self)
        data["stages"] = [describe_stage(stage) for stage in self.stages]
        for key in ("drift", "drift_eval_at", "sharing"):  # the presets without them keep the settings they recorded
            if data[key] is None:
                del data[key]
        return data


PRESETS: dict[str, Preset] = {
    # one core of a CPU machine: the setting the forgetting screen selected (benchmarks/studies/forgetting_screen:
    # no candidate forgot on every learnt seed; its rule took the closest one, cheetah_back_reversed, where MPO lost
    # Env-A on one of two learnt seeds). HalfCheetah with the back leg's three motors reversed in Env-B, the screen's
    # collector and budgets (Env-B three times Env-A). Env-A learnt from a return of 1500 and steady at the switch
    # (its last 3 evaluations within a spread of 0.2), as the screen read it; the imbalance claims' preconditions as
    # before (a value gap of 1.1, a conservative student at an ESS of 0.8). The Hopper protocol this preset named
    # before is `cpu_hopper_hip` (benchmarks/studies/paper_cpu/presets.py)
    "cpu": Preset(
        env_id="HalfCheetah-v5",
        env_a_learnt=1500.0,
        value_gap=1.1,
        min_weight_ess=0.8,
        max_switch_spread=0.2,
        stages=({}, {"leg_motor_scale": -1.0}),
        stage_steps=(60_000, 180_000),
        distill_steps=30_000,
        eval_freq=5_000,
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
        toy=True,
    ),
}

# `make demo`: the cpu preset, shortened to minutes; too short to learn Env-A, so it shows the pipeline, not the claims
PRESETS["demo"] = dataclasses.replace(
    PRESETS["cpu"],
    stage_steps=(8_000, 24_000),
    distill_steps=5_000,
    eval_freq=8_000,
    distill_eval_freq=2_500,
    eval_episodes=2,
    students=("CRR_exp_beta1", "CRR_indicator", "CRR_indicator_A_only", "BC"),
    online=False,
    toy=True,
    note=(
        "Forgetting is not shown at the demo's budget: MPO does not learn Env-A in 8k steps (it needs about 60k on "
        "HalfCheetah), so it has nothing to forget; the 'cpu' preset (60k + 180k steps, about 45 min of collection "
        "on one core) is the smallest run of this setting that can (MPO forgot there on one of two screen seeds). "
        "The demo runs the pipeline end to end: collection, four students, the report; the claims about Env-A read "
        "'not testable'."
    ),
)


# ------------------------------------------------------------------------------------------------- students and jobs
@dataclass(frozen=True)
class Student:
    """
    One offline student of the lifetime buffer.

    :param algorithm: the student's algorithm class, by name: one of :data:`STUDENT_ALGORITHMS`
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

    def __post_init__(self) -> None:
        if self.algorithm not in STUDENT_ALGORITHMS:
            raise ValueError(f"a student's algorithm is one of {STUDENT_ALGORITHMS}, got {self.algorithm!r}")


#: the algorithms a study's student can be (the classes of :mod:`sb3_lifelong`, by name)
STUDENT_ALGORITHMS = ("CRR", "BC")

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

#: a student's repeat ``k >= 1`` on the same buffer is the job ``distill_<student>__r<k>``
REPEAT_MARK = "__r"


def split_repeat(student_job: str) -> tuple[str, int]:
    """
    :param student_job: a distillation job's name without ``distill_``, e.g. ``"CRR_exp_beta1__r2"``
    :return: the student's name and the repeat (0 for the first training), e.g. ``("CRR_exp_beta1", 2)``
    """
    name, mark, repeat = student_job.rpartition(REPEAT_MARK)
    if mark and name and repeat.isdigit():
        return name, int(repeat)
    return student_job, 0


@dataclass(frozen=True)
class Job:
    """
    One job of a seed, parsed once from its name (which is also its directory's): ``collect``,
    ``distill_<student>`` (``distill_<student>__r<k>`` for the student's repeat ``k``), ``online_<method>``, or a
    sharing study's ``collect_agent2`` and ``share`` (``Preset.sharing``).

    :param kind: ``"collect"``, ``"collect_agent2"``, ``"share"``, ``"distill"`` or ``"online"``
    :param name: the student's name (:data:`STUDENTS`) or the online method's (:data:`ONLINE`); empty for the others
    :param repeat: the student's repeat (0: its first training)
    """

    kind: str
    name: str = ""
    repeat: int = 0

    def __post_init__(self) -> None:
        if self.kind not in JOB_KINDS or (self.kind in UNNAMED_JOBS) != (self.name == ""):
            raise ValueError(f"not a job: kind {self.kind!r}, name {self.name!r} (kinds: {JOB_KINDS})")
        if self.repeat < 0 or (self.repeat and self.kind != "distill"):
            raise ValueError(f"only a distillation job has repeats, and they count from 0: {self.kind} {self.repeat}")

    @classmethod
    def parse(cls, text: str) -> "Job":
        """:return: the job named ``text``; a name that is no job raises ``ValueError``"""
        if text in UNNAMED_JOBS:
            return cls(text)
        for kind in ("distill", "online"):
            prefix = f"{kind}_"
            if text.startswith(prefix) and len(text) > len(prefix):
                name, repeat = split_repeat(text[len(prefix) :]) if kind == "distill" else (text[len(prefix) :], 0)
                return cls(kind, name, repeat)
        raise ValueError(
            f"not a job name: {text!r} (collect, distill_<student>[{REPEAT_MARK}<k>], online_<method>, collect_agent2, share)"
        )

    @property
    def student_job(self) -> str:
        """:return: a distillation job's name without ``distill_``: the student and its repeat mark"""
        return self.name + (f"{REPEAT_MARK}{self.repeat}" if self.repeat else "")

    def __str__(self) -> str:
        return self.kind if self.kind in UNNAMED_JOBS else f"{self.kind}_{self.student_job}"


#: the jobs without a name of their own: the collection, and a sharing study's second collection and merge
UNNAMED_JOBS = ("collect", "collect_agent2", "share")
JOB_KINDS = (*UNNAMED_JOBS, "distill", "online")


def job_names(
    students: Optional[Sequence[str]] = None, online: bool = True, student_repeats: int = 1, sharing: bool = False
) -> list[str]:
    """
    :param students: the students (default: every one of :data:`STUDENTS`)
    :param online: with the online CRR baselines
    :param student_repeats: how many times each student is trained on the seed's buffer
    :param sharing: a sharing study's (``Preset.sharing``): its second collection and the merge of the two
    :return: the jobs of one seed, in the order they run (a student's repeats after all the first trainings)
    """
    if student_repeats < 1:
        raise ValueError(f"student_repeats must be >= 1, got {student_repeats}")
    names = list(students if students is not None else STUDENTS)
    jobs = [Job("collect")] + ([Job("collect_agent2"), Job("share")] if sharing else [])
    jobs += [Job("distill", name, k) for k in range(student_repeats) for name in names]
    jobs += [Job("online", name) for name in ONLINE] if online else []
    return [str(job) for job in jobs]


# ------------------------------------------------------------------------------------------------- stages and drift
def stage_settings(stage: Stage) -> Mapping[str, float]:
    """:return: a stage's parameter values (a named stage's from :data:`~sb3_lifelong.envs.NAMED_STAGES`; an unknown
    name gives none here, and is refused where the robot is built)"""
    if not isinstance(stage, str):
        return stage
    from sb3_lifelong.envs.stages import NAMED_STAGES

    return NAMED_STAGES.get(stage, {})


def check_drift(drift: Mapping[str, Any], stages: Sequence[Stage]) -> dict[str, tuple[float, float]]:
    """
    :param drift: a preset's ``drift``, ``{parameter: (start, end)}``
    :param stages: the preset's stages
    :return: the drift as ``{parameter: (start, end)}`` of floats
    :raises ValueError: naming the parameter, when it is no dynamics parameter
        (:data:`~sb3_lifelong.envs.PERTURBATIONS`), a stage sets it, or its range is not two distinct finite numbers
        within the parameter's physical range (a robot may narrow that range: its
        :class:`~sb3_lifelong.envs.DynamicsSchedule` refuses a drift outside its own)
    """
    from sb3_lifelong.envs.perturbations import PERTURBATIONS

    if not isinstance(drift, Mapping) or not drift:
        raise ValueError(f"drift must be a non-empty dict {{parameter: (start, end)}} (None: no drift), got {drift!r}")
    checked: dict[str, tuple[float, float]] = {}
    for name, values in drift.items():
        if name not in PERTURBATIONS:
            raise ValueError(f"drift: unknown dynamics parameter {name!r}; the parameters are {sorted(PERTURBATIONS)}")
        staged = [index for index, stage in enumerate(stages) if name in stage_settings(stage)]
        if staged:
            raise ValueError(f"drift: stage(s) {staged} set {name!r}, which the drift moves over the whole life")
        pair = finite_numbers(values)
        low, high = PERTURBATIONS[name].low, PERTURBATIONS[name].high
        if pair is None or len(pair) != 2 or pair[0] == pair[1] or not all(low <= v <= high for v in pair):
            raise ValueError(
                f"drift[{name!r}] must be (start, end): two different finite numbers in [{low:.4g}, {high:.4g}] "
                f"({PERTURBATIONS[name].unit}), got {values!r}"
            )
        checked[name] = (pair[0], pair[1])
    return checked


def finite_numbers(values: Any) -> Optional[tuple[float, ...]]:
    """:return: ``values`` (a sequence, or one value) as floats, or None when one is not a finite int or float (a bool
    is not a number here)"""
    items = tuple(values) if isinstance(values, Sequence) and not isinstance(values, str) else (values,)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in items):
        return None
    return tuple(float(v) for v in items)


def drift_text(drift: Mapping[str, Any]) -> str:
    """:return: a drift as the report and the figures say it, e.g. ``hip_deformation 0 -> 0.3``"""
    return ", ".join(f"{name} {start:g} -> {end:g}" for name, (start, end) in drift.items())


def check_drift_eval_at(eval_at: Any, drift: Optional[Mapping[str, Any]], n_stages: int) -> tuple[float, ...]:
    """
    :param eval_at: a preset's ``drift_eval_at``
    :param drift: its drift (checked)
    :param n_stages: its number of stages
    :return: ``eval_at`` as a tuple of floats
    :raises ValueError: when the preset has no drift, or ``eval_at`` is not one fraction in [0, 1] per stage
    """
    if drift is None:
        raise ValueError(f"drift_eval_at places the drifting parameters, and the preset has no drift, got {eval_at!r}")
    values = finite_numbers(eval_at)
    if values is None or len(values) != n_stages or not all(0 <= v <= 1 for v in values):
        raise ValueError(
            f"drift_eval_at must be one fraction of the life in [0, 1] per stage ({n_stages} stages), got {eval_at!r}"
        )
    return values


def evaluation_stages(
    stages: Sequence[Stage], drift: Optional[Mapping[str, Any]] = None, eval_at: Optional[Sequence[float]] = None
) -> list[Stage]:
    """
    The robot each stage is evaluated on.

    :param stages: a study's stages
    :param drift: its drift, ``{parameter: (start, end)}`` (None: none)
    :param eval_at: where in the life each stage's evaluation robot has the drifting parameters, a fraction per stage
        (None: at their nominal values)
    :return: the stages as they are without ``eval_at``; with it, each stage's parameter values and the drifting ones
        at ``start + fraction * (end - start)`` (the collector's ramp at that point of the life)
    """
    if eval_at is None or drift is None:
        return list(stages)
    return [
        {**stage_settings(stage), **{name: start + fraction * (end - start) for name, (start, end) in drift.items()}}
        for stage, fraction in zip(stages, eval_at)
    ]


def observed_params(stages: Sequence[Stage], drift: Optional[Mapping[str, Any]]) -> Optional[list[str]]:
    """
    :param stages: a study's stages
    :param drift: its drifting parameters (None: no drift)
    :return: the parameters every robot of the study appends to its observation: None without a drift (the default
        of :class:`~sb3_lifelong.envs.DynamicsSchedule`: those the stages vary); with one, those the stages vary and
        the drifting ones, sorted (the collector's default, given to the evaluation environments too, whose stages
        alone would not name the drifting ones)
    """
    if drift is None:
        return None
    return sorted({name for stage in stages for name in stage_settings(stage)} | set(drift))


def describe_stage(stage: Stage) -> Any:
    """:return: a stage as a JSON-friendly value (a named stage's name, or a dict of parameter values)"""
    return stage if isinstance(stage, str) else dict(stage)


def stage_ends(stage_steps: Sequence[int]) -> list[int]:
    """
    :param stage_steps: the environment steps of each stage
    :return: the timestep at which each stage ends (all but the last are the switches to the next environment)
    """
    return list(itertools.accumulate(int(steps) for steps in stage_steps))


def switch_points(preset: Preset) -> list[int]:
    """:return: the timesteps at which the collector's environment changes"""
    return stage_ends(preset.stage_steps)[:-1]


#: a sharing study's merged buffer, in a seed's directory (:attr:`Preset.data_buffer`)
SHARED_BUFFER = "buffer_shared"


def check_sharing(preset: Preset) -> None:
    """
    :param preset: a preset with ``Preset.sharing``
    :raises ValueError: naming the problem: an unknown set-up, not three stages, a drift (one robot's life), or the
        online baselines (they continue one robot's Stage 1 through its later stages)
    """
    if preset.sharing not in SHARING:
        raise ValueError(f"sharing must be one of {SHARING} or None, got {preset.sharing!r}")
    if len(preset.stages) != 3:
        raise ValueError(
            f"a sharing study has three stages (Env-A, then Env-B for the first robot and Env-C for the second), got "
            f"{len(preset.stages)}"
        )
    if preset.drift is not None:
        raise ValueError("a sharing study has no drift: a drift is one robot's life, and its robots live side by side")
    if preset.online:
        raise ValueError("a sharing study has no online baselines (online=False): they continue one robot's stages")


def left_environments(preset: Mapping[str, Any]) -> list[str]:
    """
    :param preset: a study's settings (:meth:`Preset.describe`, or its ``preset.json``)
    :return: the environments the ``collect`` job's agent leaves, in stage order: every one but the last, or Env-A
        alone in a sharing study (its first robot goes from Env-A to Env-B; Env-C is the second robot's)
    """
    envs = list(preset["env_names"])
    return envs[:1] if preset.get("sharing") is not None else envs[:-1]


def sharing_text(preset: Mapping[str, Any]) -> str:
    """:return: a sharing study's two robots in words, for the report's settings line ("" without sharing)"""
    sharing = preset.get("sharing")
    if sharing is None:
        return ""
    a, b, c = preset["env_names"]
    second = f"its copy at the switch learns {c}" if sharing == "copy" else f"a second robot learns {c} from scratch"
    return f"two robots side by side ({sharing}): the first learns {a} then {b}, {second}; their buffers merged; "


def study_ends(preset: Mapping[str, Any]) -> list[int]:
    """
    :param preset: a study's settings (:meth:`Preset.describe`, or its ``preset.json``)
    :return: the timestep at which each stage ends on the ``collect`` job's clock (:func:`stage_ends`); in a sharing
        study, Env-C's stage ends with Env-B's: the two robots live side by side
    """
    ends = stage_ends(preset["stage_steps"])
    if preset.get("sharing") is not None:
        ends[2] = ends[1]
    return ends


# ------------------------------------------------------------------------------------------------- recorded settings
#: settings added to :class:`Preset` after studies were recorded, with the value those studies ran with
LATER_SETTINGS: dict[str, Any] = {
    "layer_norm": False,
    "student_repeats": 1,
    "student_critic": "mse",
    "env_a_learnt": None,
    "value_gap": None,
    "min_weight_ess": None,
    "max_switch_spread": None,
    "device": "cpu",
    "toy": False,
}
#: settings that do not make two studies different ones: more repeats of the students, the report's precondition
#: (a study keeps the threshold it recorded, None for those recorded before there was one), and the mark of a toy
#: budget (a study recorded before the mark existed is the same study: ``toy_budget`` reads its preset's mark)
REPORT_THRESHOLDS = ("env_a_learnt", "value_gap", "min_weight_ess", "max_switch_spread")
NOT_IDENTITY = ("student_repeats", *REPORT_THRESHOLDS, "toy")


def same_settings(recorded: Mapping[str, Any], described: Mapping[str, Any]) -> bool:
    """
    :param recorded: a study's ``preset.json``
    :param described: :meth:`Preset.describe` of a preset, through JSON
    :return: whether they are one study's settings: equal but for :data:`NOT_IDENTITY`, with settings that a
        recorded file predates read as the value it ran with (:data:`LATER_SETTINGS`)
    """

    def comparable(data: Mapping[str, Any]) -> dict[str, Any]:
        filled = {**LATER_SETTINGS, **data}
        for key in NOT_IDENTITY:
            filled.pop(key)
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
    *REPORT_THRESHOLDS,
    "note",
    "toy",
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


def read_study_file(path: Union[str, os.PathLike], name: str) -> Any:
    """
    Run a study folder's Python file (its ``presets.py`` or ``claims.py``) and return one of its names.

    :param path: the file
    :param name: the name it defines (``PRESETS``, ``CLAIMS``)
    :return: its value (None when the file does not define it)
    :raises FileNotFoundError: naming the file and what it should define
    """
    path = pathlib.Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no file {path}: a study's {name} are defined in a Python file of its folder")
    spec = importlib.util.spec_from_file_location(f"study_file_{abs(hash(str(path.resolve())))}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return getattr(module, name, None)


def load_presets(path: Union[str, os.PathLike]) -> dict[str, Preset]:
    """
    Read a study's presets file: a Python file that defines ``PRESETS``, a dict of name -> :class:`Preset` (it is run, as
    any Python file: load only your own studies' files). A study's presets are data of its folder
    (``benchmarks/studies/<study>/presets.py``); the package keeps those users run (:data:`PRESETS`).

    :param path: the file
    :return: its presets
    """
    presets = read_study_file(path, "PRESETS")
    if not isinstance(presets, dict) or not all(isinstance(p, Preset) for p in presets.values()):
        raise ValueError(f"{path} must define PRESETS, a dict of name -> sb3_lifelong.experiments.presets.Preset")
    return dict(presets)


def named_preset(recorded: Mapping[str, Any], folder: Optional[pathlib.Path] = None) -> tuple[str, Optional[Preset]]:
    """
    :param recorded: a study's recorded settings (``preset.json``)
    :param folder: the study's directory: the presets of its ``presets.py``, when it has one, are looked at too
    :return: the name and the preset it was run with (:data:`PRESETS`, or the study's own), or ``("", None)``
    """
    candidates = dict(PRESETS)
    if folder is not None and (folder / "presets.py").is_file():
        candidates.update(load_presets(folder / "presets.py"))
    for name, candidate in candidates.items():
        if same_settings(recorded, json.loads(json.dumps(candidate.describe()))):
            return name, candidate
    return "", None


def preset_name(recorded: Mapping[str, Any], folder: Optional[pathlib.Path] = None) -> str:
    """
    :param recorded: a study's recorded settings (``preset.json``)
    :param folder: the study's directory: the presets of its ``presets.py``, when it has one, are looked at too
    :return: the name of the preset it was run with (:data:`PRESETS`, or the study's own), or ``""``
    """
    return named_preset(recorded, folder)[0]


def toy_budget(recorded: Mapping[str, Any], folder: Optional[pathlib.Path] = None) -> bool:
    """
    :param recorded: a study's recorded settings (``preset.json``)
    :param folder: the study's directory (its ``presets.py`` is looked at too)
    :return: whether the study ran at a toy budget (:attr:`Preset.toy`): as recorded, or, for a study recorded
        before presets were marked, as the preset it was run with is marked now
    """
    if "toy" in recorded:
        return bool(recorded["toy"])
    preset = named_preset(recorded, folder)[1]
    return preset is not None and preset.toy

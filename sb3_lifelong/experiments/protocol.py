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
skipped (:func:`~sb3_lifelong.experiments.jobs.job_lock`). What a study runs (its preset, students and job names) is
:mod:`sb3_lifelong.experiments.presets`; this module runs it.

Layout of ``<output>/seed_<k>/``::

    buffer/, buffer_stage1/     the lifetime buffer and its Stage-1 part (large: never commit them)
    collect/stage1.zip          the Stage-1 MPO agent
    <job>/eval.csv              timesteps, env, mean_reward, std_reward, n_episodes
    <job>/q_sources.csv         timesteps, source, name, q_mean, n (+ q_probe, mc_return, overestimation, n_mc)
    <job>/train.csv             timesteps, the train/ values (losses, weight_ess, beta, ...)
    <job>/tb/<Algorithm>_<k>/   the job's tensorboard run, as SB3 writes it (when tensorboard is installed): the
                                eval/<env>/, diagnostics/ and train/ values, so ``tensorboard --logdir <output>``
                                browses every seed, job and environment of the study
    <job>/done.json             wall time and the job's settings (``collect``'s: the rows of each environment's
                                data in the lifetime buffer too, ``source_rows``)
"""

import dataclasses
import json
import pathlib
import shutil
import time
from collections.abc import Mapping, Sequence
from typing import Any, Callable, Optional

from sb3_lifelong.bc import BC
from sb3_lifelong.buffers import LifelongReplayBuffer, merge_buffers
from sb3_lifelong.core.atomic import write_json_atomic
from sb3_lifelong.crr import CRR
from sb3_lifelong.distill import distill
from sb3_lifelong.experiments import costs
from sb3_lifelong.experiments.collection import COLLECTED_BUFFERS, PAUSED_MODEL, collect, remove_unfinished_collection
from sb3_lifelong.experiments.jobs import (
    OWNED_MARKER,
    StudentPauses,
    cut_logs_back,
    finish_job,
    job_callbacks,
    job_lock,
    make_env,
    model_kwargs,
    pause_checkpoints,
    paused_student,
    release_directory,
    start_job,
    tensorboard_dir,
    value_support,
)
from sb3_lifelong.experiments.presets import (
    LATER_SETTINGS,
    NOT_IDENTITY,
    ONLINE,
    REPEAT_SEED_STRIDE,
    REPORT_THRESHOLDS,
    STUDENTS,
    Job,
    Preset,
    Student,
    collection_differences,
    job_names,
    same_settings,
    switch_points,
)
from sb3_lifelong.experiments.scores import SOURCE_ROWS_RECORD, count_source_rows
from sb3_lifelong.experiments.sharing import collect_agent2, share
from sb3_lifelong.mpo import MPO


def online(
    name: str, preset: Preset, seed: int, run_dir: pathlib.Path, progress_bar: bool = False, log: Callable[[str], None] = print
) -> None:
    """
    A conservative online baseline continuing from the Stage-1 agent (its weights and its buffer) through Stage 2.
    An unfinished attempt's directory is deleted first (:func:`~sb3_lifelong.experiments.jobs.start_job`:
    only one this job wrote; anything else is refused).
    """
    directory = run_dir / f"online_{name}"
    start_job(directory, directory.name, log)
    # the agent only: its saved buffer settings point at the lifetime buffer, which other jobs may be reading
    stage1 = MPO.load(run_dir / "collect" / "stage1.zip", device=preset.device, custom_objects={"replay_buffer_kwargs": {}})
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
        **model_kwargs(preset, seed),
    )
    model.policy.load_state_dict(stage1.policy.state_dict())
    with LifelongReplayBuffer.open(run_dir / "buffer_stage1", read_only=True) as stage1_buffer:
        model.replay_buffer = merge_buffers([stage1_buffer])  # a private copy in memory, which this agent extends
    model.num_timesteps = start
    model.learn(sum(preset.stage_steps[1:]), callback=job_callbacks(preset, directory, preset.eval_freq, seed),
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
    pause_every: Optional[int] = None,
    log: Callable[[str], None] = print,
) -> float:
    """
    Train one offline student on the lifetime buffer (opened read-only) and save it in ``run_dir/distill_<name>``.

    With ``pause_every``, the student pauses every that many updates (a checkpoint, ``paused_<updates>.zip``, which
    holds the random streams, and the record that names it, ``paused.json``), and a later call continues it from its
    last pause with the same result as an uninterrupted run; rows its logs gained after that pause are set aside.
    Without a pause the student starts anew; a pause of other settings is refused.

    :param name: the student's name (its settings are ``STUDENTS[name]`` unless ``student`` is given)
    :param preset: the protocol's settings
    :param seed: the seed
    :param run_dir: the seed's directory (holds ``buffer``, or a sharing study's ``buffer_shared``)
    :param progress_bar: show a progress bar
    :param student: settings of a student that is not in :data:`STUDENTS` (e.g. a benchmark's variant)
    :param student_seed: the seed of the student's own training and of its evaluation environments (default:
        ``seed``), to train the same student several times on one buffer
    :param pause_every: pause (checkpoint) every this many updates (None: never)
    :param log: where progress messages go
    :return: the seconds the student took, its earlier parts' included
    :raises ValueError: ``pause_every`` is not positive, or the student's directory holds a pause of other settings
    """
    if pause_every is not None and pause_every <= 0:
        raise ValueError(f"pause_every must be a positive number of updates or None, got {pause_every}")
    student = STUDENTS[name] if student is None else student
    seed = seed if student_seed is None else student_seed
    directory = run_dir / f"distill_{name}"
    settings = dict(student=dataclasses.asdict(student), seed=seed, updates=preset.distill_steps, preset=preset.describe())
    paused = paused_student(directory, settings)
    if paused is None:  # a new student: an unfinished attempt's directory goes (only one it wrote: others are refused)
        start_job(directory, directory.name, log)
    else:
        cut_logs_back(directory, paused["updates"], log)
        log(f"  continuing the student from its checkpoint at {paused['updates']:,} of {preset.distill_steps:,} updates")
    if not (run_dir / preset.data_buffer / "manifest.json").is_file():
        raise FileNotFoundError(f"{run_dir / preset.data_buffer} is not there: the students distill it (run {run_dir.name}'s "
                                f"{' and '.join(preset.requires(f'distill_{name}'))} job first)")  # fmt: skip
    data = LifelongReplayBuffer.open(run_dir / preset.data_buffer, read_only=True)
    everything = LifelongReplayBuffer.open(run_dir / preset.data_buffer, read_only=True)  # unweighted, for Q per source
    if student.ratio is not None:
        data.set_sampling_weights(sampling_weights(student.ratio, data.source_counts()))
    if student.reward_scale is not None:
        data.set_reward_scale(student.reward_scale)
    kwargs = dict(student.kwargs)
    sources = None
    if kwargs.get("actor_per_source"):
        sources = {env_name: index for index, env_name in enumerate(preset.env_names)}
    algorithm: Any = {"CRR": CRR, "BC": BC}[student.algorithm]  # Student checks the name
    common = model_kwargs(preset, seed)
    if algorithm is CRR and preset.student_critic == "categorical":
        common["policy_kwargs"]["distributional_critic"] = True
    common["policy_kwargs"].update(kwargs.pop("policy_kwargs", {}))  # the student's own network options
    if common["policy_kwargs"].get("distributional_critic") and "v_min" not in common["policy_kwargs"]:
        scales = list((student.reward_scale or {}).values())
        common["policy_kwargs"].update(value_support(data.reward_range(), kwargs.get("gamma", 0.99), scales))
    callbacks = job_callbacks(
        preset,
        directory,
        preset.distill_eval_freq,
        seed,
        data=everything,
        q=algorithm is CRR,
        reward_scale=student.reward_scale,
        sources=sources,
    )
    done = 0 if paused is None else int(paused["updates"])
    pauses = StudentPauses(directory, pause_every, preset.distill_steps, settings, paused, log)
    learning: dict[str, Any] = dict(callback=[*callbacks, pauses], progress_bar=progress_bar, tb_log_name=algorithm.__name__)
    if paused is None:
        model = distill(
            data,
            student_class=algorithm,
            total_updates=preset.distill_steps,
            batch_size=preset.student_batch_size,
            learning_rate=preset.student_learning_rate,
            tensorboard_log=tensorboard_dir(directory),
            **learning,
            **kwargs,
            **common,
        )
    else:
        model = algorithm.load(directory / paused["model"], device=preset.device)
        model.set_offline_data(data)
        model.tensorboard_log = tensorboard_dir(directory)
        forward = getattr(model, "_forward", None)
        if paused.get("compiled") and forward is not None:
            forward.compile()
        model.learn_offline(preset.distill_steps - done, reset_num_timesteps=False, **learning)
    model.save(directory / "student.zip")
    # the finished student's record: a stop before the caller writes done.json continues with nothing left to train
    seconds = pauses.record(preset.distill_steps, "student.zip")
    for pause in pause_checkpoints(directory):
        pause.unlink()
    data.close()
    everything.close()
    return seconds


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
    read-only), each in ``output/seed_<seed>/distill_<name>``; a finished one (``done.json``) is skipped and a stopped
    one continues from its last evaluation (it pauses at each), so a stopped command is simply run again. For the
    benchmarks that vary the students of a study.

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
        log(f"buffer {seed}: {name}, {preset.distill_steps:,} updates")
        seconds = distill_student(
            name,
            preset,
            seed,
            run_dir,
            student=student,
            student_seed=student_seed,
            pause_every=preset.distill_eval_freq,
            log=log,
        )
        done: dict[str, Any] = dict(seconds=seconds, buffer_seed=seed)
        done.update(student_seed=seed if student_seed is None else student_seed, settings=dataclasses.asdict(student))
        done.update(about or {})
        finish_job(run_dir / f"distill_{name}", done)
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
            # more repeats of the students on the same buffers: the study's other settings are unchanged, and it
            # keeps the report's thresholds it recorded (None where it predates them)
            described.update({key: recorded.get(key) for key in REPORT_THRESHOLDS})
        else:
            differ = sorted(
                key
                for key in set(recorded) | set(described)
                if key not in NOT_IDENTITY and {**LATER_SETTINGS, **recorded}.get(key) != described.get(key)
            )
            raise ValueError(
                f"{output} holds a study run with other settings ({settings}: {', '.join(differ)} differ); its seeds "
                "cannot be mixed with these. Choose another --output, or delete that directory to start again."
            )
    output.mkdir(parents=True, exist_ok=True)
    write_json_atomic(settings, described)


def refuse_reuse(preset: Preset) -> None:
    """
    :raises ValueError: ``preset`` is a sharing study's (``Preset.sharing``): its students distill the merge of two
        robots' buffers, and another study's collections are not reused for it
    """
    if preset.sharing is not None:
        raise ValueError(
            "a sharing study's collections are not reused from another study (--collection-from): its students distill "
            "the merge of two robots' buffers; run its collect, collect_agent2 and share jobs"
        )


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
    :raises ValueError: (also) a sharing study (``Preset.sharing``, :func:`refuse_reuse`)
    """
    refuse_reuse(preset)
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
        # an unfinished collection of this study's own goes first: only what it wrote (a finished one is refused)
        remove_unfinished_collection(preset, run_dir, log)
        staging = run_dir / ".collect.adopting"
        start_job(staging, "collect (reused)", log)  # an adoption that stopped before its rename goes first
        ignored = shutil.ignore_patterns("done.json", OWNED_MARKER)
        shutil.copytree(origin / "collect", staging, ignore=ignored, dirs_exist_ok=True)
        done = {**json.loads((origin / "collect" / "done.json").read_text()), "adopted_from": str(origin)}
        write_json_atomic(staging / "done.json", done)
        for name, target in targets.items():
            (run_dir / name).symlink_to(target, target_is_directory=True)
        staging.rename(run_dir / "collect")  # done.json appears with the whole directory
        release_directory(run_dir / "collect")
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


def run_seed(
    preset: Preset,
    seed: int,
    output: pathlib.Path,
    jobs: Optional[Sequence[str]] = None,
    progress_bar: bool = False,
    log: Callable = print,
    collection_from: Optional[pathlib.Path] = None,
    until: Optional[int] = None,
) -> list[str]:
    """
    Run the jobs of one seed that have not finished yet (each writes ``done.json`` when it finishes). A job that
    another process is running (see :func:`~sb3_lifelong.experiments.jobs.job_lock`) is skipped; ``collect``,
    which the other jobs need, raises.

    :param preset: the protocol's settings
    :param seed: the seed
    :param output: the experiment directory (``seed_<k>`` is created inside)
    :param jobs: the jobs to run (default: the preset's, :meth:`Preset.jobs`), after those they need that have not
        finished (:meth:`Preset.requires`: ``collect``; a sharing study's students, ``share`` and both collections)
    :param progress_bar: show a progress bar per job
    :param log: where the one-line messages go
    :param collection_from: another study whose collection of this seed to reuse (:func:`adopt_collection`)
    :param until: pause the collection after this many environment steps (:func:`collect`); the other jobs wait
        for a finished collection, so none runs while it is paused
    :return: the jobs that ran (a paused collection is not among them)
    """
    if collection_from is not None:
        refuse_reuse(preset)  # before anything is written
    record_settings(preset, output)
    run_dir = output / f"seed_{seed}"
    run_dir.mkdir(parents=True, exist_ok=True)
    if collection_from is not None:
        adopt_collection(preset, seed, collection_from, output, log)
    check_linked_buffers(run_dir)
    wanted = list(jobs) if jobs is not None else preset.jobs()
    sharing = preset.sharing is not None  # (a sharing study has no online baselines)
    known = job_names(online=not sharing, student_repeats=preset.student_repeats, sharing=sharing)
    unknown = sorted(set(wanted) - set(known))
    if unknown:
        raise ValueError(f"unknown jobs {unknown}; the jobs are {known}")
    wanted = preset.with_requirements(wanted)  # the jobs they need run first, or are counted as done
    ran: list[str] = []
    planned = [job for job in known if job in wanted]  # the order they run in; numbered "job k/n" over all of them
    todo = [job for job in planned if not (run_dir / job / "done.json").exists()]
    skipped = [job for job in planned if job not in todo]
    settings = preset.describe()
    times = costs.measured(settings)  # earlier runs of these settings on this kind of CPU, then this run's jobs
    if skipped:
        log(f"seed {seed}: {len(skipped)} of {len(planned)} job(s) already done, skipped: {', '.join(skipped)}")
    if todo:
        log(f"seed {seed}: {costs.remaining(todo, times)}")
    for index, job in enumerate(todo):
        position = planned.index(job)
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
            expected = costs.estimate(job, times)
            about = f" (about {costs.minutes(expected)}, as measured before)" if expected is not None else ""
            log(f"seed {seed}: job {position + 1}/{len(planned)} {job} ...{about}")
            resumed = job == "collect" and (run_dir / "collect" / PAUSED_MODEL).exists()  # its earlier parts not timed
            start = time.perf_counter()
            trained: Optional[float] = None  # a student's training seconds, its earlier parts' included
            recorded: dict[str, Any] = {}  # what the job records beside its time
            parsed = Job.parse(job)
            if parsed.kind == "collect":
                if not collect(preset, seed, run_dir, progress_bar, log, until=until):
                    log(f"seed {seed}: collection paused at step {until:,}: run the command again to continue it")
                    return ran
            elif parsed.kind == "online":
                online(parsed.name, preset, seed, run_dir, progress_bar, log)
            elif parsed.kind == "collect_agent2":
                collect_agent2(preset, seed, run_dir, progress_bar, log)
            elif parsed.kind == "share":
                recorded[SOURCE_ROWS_RECORD] = share(preset, run_dir, log)
            else:
                name, repeat = parsed.name, parsed.repeat
                student_seed = seed + repeat * REPEAT_SEED_STRIDE
                trained = distill_student(
                    parsed.student_job,
                    preset,
                    seed,
                    run_dir,
                    progress_bar,
                    STUDENTS[name],
                    student_seed,
                    pause_every=preset.distill_eval_freq,
                    log=log,
                )
            seconds = time.perf_counter() - start if trained is None else trained
            done = dict(job=job, seed=seed, seconds=seconds, preset=preset.describe())
            if parsed.kind == "distill":
                done.update(student=dataclasses.asdict(STUDENTS[name]), repeat=repeat, student_seed=student_seed)
            done.update(recorded)
            if parsed.kind == "collect" and preset.sharing is None:  # each environment's rows, for the report
                try:
                    done[SOURCE_ROWS_RECORD] = count_source_rows(run_dir / "buffer")
                except (OSError, ValueError, RuntimeError) as error:  # never lose a finished collection over a record
                    log(f"seed {seed}: the rows per source of the buffer were not recorded ({error})")
            finish_job(run_dir / job, done)  # never a half-written "done"; no later attempt deletes it
            if not resumed:
                costs.record(settings, job, seconds)
                times.setdefault(costs.job_key(job), []).append(seconds)
            left = costs.remaining(todo[index + 1 :], times)
            log(f"seed {seed}: job {job} done in {costs.minutes(seconds)}" + (f"; {left}" if left else "; the seed is done"))
            ran.append(job)
    return ran

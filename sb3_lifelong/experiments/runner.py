"""
A study (several seeds of the two-stage protocol) as a graph of jobs, run in parallel.

Every seed's ``collect`` job comes first; its students and online baselines then run in any order, in parallel;
the report waits for all (a sharing study's two collections run side by side, then their merge, then the students:
:meth:`~sb3_lifelong.experiments.presets.Preset.requires`). Each job is :func:`run_job`: one process-safe call that
reads and writes only its seed's directory and skips itself when its ``done.json`` exists, so a crashed or cancelled
job is re-run alone and finished ones are skipped.

Backends: `Ray <https://www.ray.io>`_ (``pip install "sb3_lifelong[cluster]"``), started locally with ``workers``
CPUs or joined at ``address`` (``HOST:PORT``, or ``RAY_ADDRESS``); without Ray a local process pool runs the same
graph. A job that fails prints its traceback; the others go on, and the jobs that need it are reported as not run.
"""

import contextlib
import multiprocessing
import os
import pathlib
import time
import traceback
from collections.abc import Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import dataclass
from typing import Any, Callable, Optional

from sb3_lifelong.experiments import costs
from sb3_lifelong.experiments.presets import Preset
from sb3_lifelong.experiments.protocol import adopt_collection, record_settings, refuse_reuse, run_seed

BACKENDS = ("auto", "ray", "process")


@dataclass(frozen=True)
class Task:
    """
    One job of a study as the runner schedules it: the job ``name`` (a :class:`~sb3_lifelong.experiments.presets.Job`'s
    name) of seed ``seed``, to run after the tasks in ``after`` (their keys); with ``until``, the collection's part up
    to that step (it pauses there, and the task ``collect`` continues it).
    """

    seed: int
    name: str
    after: tuple[str, ...] = ()
    until: Optional[int] = None

    @property
    def key(self) -> str:
        return f"seed_{self.seed}/{self.name}" + ("" if self.until is None else f"@{self.until}")


def job_graph(preset: Preset, seeds: Sequence[int], jobs: Optional[Sequence[str]] = None) -> list[Task]:
    """
    :param preset: the protocol's settings
    :param seeds: the seeds of the study
    :param jobs: the jobs of each seed (default: the preset's); the jobs they need are added
        (:meth:`~sb3_lifelong.experiments.presets.Preset.requires`)
    :return: every job after the jobs it needs: each seed's ``collect`` before the jobs that read its buffer; in a
        sharing study's ``"copy"`` set-up, ``collect`` up to the switch before the two collections go on side by side
    """
    order = preset.with_requirements(list(jobs) if jobs is not None else preset.jobs())
    graph = []
    for seed in seeds:
        keys = {name: f"seed_{seed}/{name}" for name in order}
        stage1: tuple[str, ...] = ()
        if preset.sharing == "copy" and "collect_agent2" in order:
            part = Task(seed, "collect", until=preset.stage_steps[0])
            graph.append(part)
            stage1 = (part.key,)
        for name in order:
            after = tuple(keys[required] for required in preset.requires(name))
            graph.append(Task(seed, name, after=after + stage1 if name in ("collect", "collect_agent2") else after))
    return graph


def run_job(
    preset: Preset, output: str, seed: int, name: str, threads: int = 1, until: Optional[int] = None
) -> dict[str, Any]:
    """
    Run one job in this process (a no-op when it is done already).

    :param until: (``collect``) pause the collection at this step (the part of a :class:`Task` with ``until``)
    :return: ``{"key", "ran", "seconds", "error"}`` (``error``: the traceback, or None)
    """
    import torch as th

    th.set_num_threads(threads)
    start = time.perf_counter()
    key = Task(seed, name, until=until).key
    try:
        ran = run_seed(preset, seed, pathlib.Path(output), jobs=[name], log=lambda message: None, until=until)
        # a part that paused ran; one whose collection had finished did not
        finished = (pathlib.Path(output) / f"seed_{seed}" / name / "done.json").exists()
        ran_now = name in ran or (until is not None and not finished)
        return dict(key=key, ran=ran_now, seconds=time.perf_counter() - start, error=None)
    except Exception:
        return dict(key=key, ran=False, seconds=time.perf_counter() - start, error=traceback.format_exc())


def _ray_available() -> bool:
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def run_study(
    preset: Preset,
    seeds: Sequence[int],
    output: str,
    workers: int = 1,
    address: Optional[str] = None,
    backend: str = "auto",
    jobs: Optional[Sequence[str]] = None,
    log: Callable[[str], None] = print,
    collection_from: Optional[str] = None,
) -> dict[str, dict[str, Any]]:
    """
    Run every job of a study, ``workers`` at a time (one torch thread each).

    :param preset: the protocol's settings
    :param seeds: the seeds
    :param output: the study's directory (on a cluster: a path every node sees)
    :param workers: jobs at a time on the local machine (ignored when joining a cluster at ``address``)
    :param address: a Ray cluster to submit to (``HOST:PORT``; default ``RAY_ADDRESS`` when set)
    :param backend: ``"ray"``, ``"process"`` (a local process pool) or ``"auto"`` (Ray when installed)
    :param jobs: the jobs of each seed (default: the preset's)
    :param log: where the progress lines go
    :param collection_from: another study whose collections of these seeds to reuse (only the students run), see
        :func:`~sb3_lifelong.experiments.protocol.adopt_collection`
    :return: the result of every job by key (``seed_<k>/<job>``): ran, seconds, error
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    address = address or os.environ.get("RAY_ADDRESS") or None
    use_ray = backend == "ray" or (backend == "auto" and _ray_available())
    if backend == "ray" and not _ray_available():
        raise ImportError('the Ray backend needs Ray: pip install "sb3_lifelong[cluster]"')
    if address and not use_ray:
        raise ValueError("--address submits to a Ray cluster: install Ray (sb3_lifelong[cluster]) or drop --address")
    if collection_from is not None:
        refuse_reuse(preset)  # before anything is written
    record_settings(preset, pathlib.Path(output))  # checked and recorded once, before any worker starts
    if collection_from is not None:
        for seed in seeds:
            adopt_collection(preset, seed, pathlib.Path(collection_from), pathlib.Path(output), log)
    graph = job_graph(preset, seeds, jobs)
    if use_ray:
        where = f"the Ray cluster at {address}" if address else f"Ray on this machine, {workers} worker(s)"
        log(f"study: {len(graph)} jobs on {where}")
        return _run_ray(preset, graph, output, workers, address, log)
    reason = "chosen" if backend == "process" else "Ray is not installed"
    log(f"study: {len(graph)} jobs in a local process pool of {workers} worker(s) ({reason})")
    return _run_pool(preset, graph, output, workers, log)


class _Progress:
    def __init__(self, graph: list[Task], log: Callable[[str], None], preset: Preset, workers: int) -> None:
        self.total = len(graph)
        self.log = log
        self.results: dict[str, dict[str, Any]] = {}
        self.names = {job.key: job.name for job in graph}
        self.workers = workers
        self.times = costs.measured(preset.describe())  # earlier runs of these settings on this CPU, then this study's

    def _left(self) -> str:
        """:return: how many jobs are left, and the work they hold where it was measured"""
        todo = [name for key, name in self.names.items() if key not in self.results]
        known = [costs.estimate(name, self.times) for name in todo]
        seconds = sum(value for value in known if value is not None)
        if not todo or not seconds:
            return f"{len(todo)} left"
        unmeasured = sum(value is None for value in known)
        spread = f", {costs.minutes(seconds / self.workers)} on {self.workers} worker(s)" if self.workers else ""
        return f"{len(todo)} left: about {costs.minutes(seconds)} of work{spread}" + (
            f", {unmeasured} job(s) not measured yet" if unmeasured else ""
        )

    def started(self, job: Task) -> None:
        self.log(f"[start] {job.key}")

    def finished(self, result: dict[str, Any]) -> None:
        self.results[result["key"]] = result
        if result["ran"] and not result["error"]:
            self.times.setdefault(costs.job_key(self.names.get(result["key"], "")), []).append(result["seconds"])
        left = self._left()
        if result["error"]:
            self.log(f"[FAILED] {result['key']} after {costs.minutes(result['seconds'])} ({left}):\n{result['error']}")
        elif result["ran"]:
            self.log(f"[done] {result['key']} in {costs.minutes(result['seconds'])} ({left})")
        else:
            self.log(f"[skip] {result['key']}: done earlier ({left})")

    def blocked(self, job: Task, reason: str) -> None:
        self.results[job.key] = dict(key=job.key, ran=False, seconds=0.0, error=f"not run: {reason}")
        self.log(f"[not run] {job.key}: {reason} ({self._left()})")

    def failed(self, key: str) -> bool:
        return bool(self.results.get(key, {}).get("error"))


def _run_pool(preset: Preset, graph: list[Task], output: str, workers: int, log: Callable[[str], None]) -> dict[str, Any]:
    progress = _Progress(graph, log, preset, workers)
    waiting = list(graph)
    running: dict[Future, Task] = {}
    with ProcessPoolExecutor(max_workers=workers, mp_context=_process_context()) as pool:
        while waiting or running:
            for job in list(waiting):
                if any(progress.failed(dep) for dep in job.after):
                    waiting.remove(job)
                    progress.blocked(job, f"{' and '.join(job.after)} failed")
                elif all(dep in progress.results for dep in job.after) and len(running) < workers:
                    waiting.remove(job)
                    progress.started(job)
                    running[pool.submit(run_job, preset, output, job.seed, job.name, 1, job.until)] = job
            if not running:
                continue
            done, _ = wait(list(running), return_when=FIRST_COMPLETED)
            for future in done:
                running.pop(future)
                progress.finished(future.result())
    return progress.results


def _run_ray(
    preset: Preset, graph: list[Task], output: str, workers: int, address: Optional[str], log: Callable[[str], None]
) -> dict[str, Any]:
    import ray

    with ray_session(workers, address):
        remote_job = ray.remote(num_cpus=1, max_retries=0)(_after(run_job))
        progress = _Progress(graph, log, preset, 0 if address else workers)  # a cluster's size is its own
        refs: dict[str, Any] = {}
        pending: dict[Any, Task] = {}
        for job in graph:  # submitted at once: Ray runs a job when the results it is given are ready
            dependencies = [refs[dep] for dep in job.after]
            # the dependencies go in as top-level arguments: Ray passes them resolved, once they are ready
            refs[job.key] = remote_job.remote(preset, output, job.seed, job.name, job.until, *dependencies)
            pending[refs[job.key]] = job
            if not job.after:
                progress.started(job)
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            job = pending.pop(done[0])
            result = ray.get(done[0])
            if result.get("blocked"):
                progress.blocked(job, result["blocked"])
                continue
            progress.finished(result)
            if not result["error"]:
                for other in graph:
                    ready = all(dep in progress.results and not progress.failed(dep) for dep in other.after)
                    if job.key in other.after and ready:
                        progress.started(other)
        return progress.results


@contextlib.contextmanager
def ray_session(workers: int, address: Optional[str] = None) -> Iterator[None]:
    """
    Ray, started here for the duration of the block unless it is running in this process already: a new local
    instance with ``workers`` CPUs, or a connection to the cluster at ``address``.

    :param workers: CPUs of a local instance (ignored with ``address``)
    :param address: a Ray cluster, ``HOST:PORT``
    """
    import ray

    started_here = not ray.is_initialized()
    if started_here:
        # Ray starts its workers at niceness 15 by default: beside any other work on the machine they then get almost
        # no CPU (importing torch in a worker took 50 s instead of 2 s beside two training runs on 2 cores). The jobs
        # are the work here, so they run at normal priority unless the user says otherwise.
        os.environ.setdefault("RAY_worker_niceness", "0")
        if address:
            ray.init(address=address, log_to_driver=False)
        else:
            # "local": a new instance with these CPUs, never a cluster that `ray start` left running on this machine
            ray.init(address="local", num_cpus=workers, include_dashboard=False, log_to_driver=False)
    try:
        yield
    finally:
        if started_here:
            ray.shutdown()


def map_parallel(
    function: Callable[..., Any],
    calls: Sequence[dict[str, Any]],
    workers: int = 1,
    backend: str = "auto",
    address: Optional[str] = None,
) -> list[Any]:
    """
    ``[function(**kwargs) for kwargs in calls]``, ``workers`` at a time, each call in its own process (one CPU).

    :param function: a module-level function (it is sent to other processes)
    :param calls: the keyword arguments of each call
    :param workers: calls at a time on this machine (ignored when joining a cluster at ``address``); 1 without
        ``address`` and without ``backend="ray"``: one after the other in this process
    :param backend: ``"ray"``, ``"process"`` (a local process pool) or ``"auto"`` (Ray when installed)
    :param address: a Ray cluster (``HOST:PORT``)
    :return: the results, in the order of ``calls``; the first exception of a call is raised
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    if workers == 1 and address is None and backend != "ray":
        return [function(**kwargs) for kwargs in calls]
    if backend == "ray" or (backend == "auto" and _ray_available()):
        import ray

        with ray_session(workers, address):
            remote = ray.remote(num_cpus=1, max_retries=0)(function)
            return ray.get([remote.remote(**kwargs) for kwargs in calls])
    with ProcessPoolExecutor(max_workers=workers, mp_context=_process_context()) as pool:
        return list(pool.map(_call, [function] * len(calls), calls))


def _process_context() -> Any:
    """
    The start method of a local process pool: the platform's default, but ``spawn`` once this process has
    initialised CUDA (a process forked after that cannot use the GPU: each of its models would fail).
    """
    import torch as th

    return multiprocessing.get_context("spawn" if th.cuda.is_initialized() else None)


def _call(function: Callable[..., Any], kwargs: dict[str, Any]) -> Any:
    return function(**kwargs)


def _after(function: Callable[..., dict[str, Any]]) -> Callable[..., dict[str, Any]]:
    """``function`` run only when the results it depends on have no error (Ray passes them resolved)."""

    def job(
        preset: Preset, output: str, seed: int, name: str, until: Optional[int], *dependencies: dict[str, Any]
    ) -> dict[str, Any]:
        failed = [d["key"] for d in dependencies if d.get("error") or d.get("blocked")]
        if failed:  # (a blocked result names its job too: the jobs after it are blocked in turn)
            return dict(key=Task(seed, name, until=until).key, blocked=f"{' and '.join(failed)} failed")
        return function(preset, output, seed, name, 1, until)

    return job

"""
A study's directory read into scores: every finished job of every seed, as the long tables of a :class:`Study`
(:func:`load_study`), which the report (:mod:`sb3_lifelong.experiments.report`: tables, the pre-registered claims)
and the figures (:mod:`sb3_lifelong.experiments.figures`) read.

A seed's scores:

* an online method's final return in an environment: the mean of its last ``ONLINE_LAST`` evaluations;
* MPO's return in an environment *at the switch* (when it leaves that environment): the mean of its last
  ``ONLINE_LAST_STAGE1`` evaluations of that environment's stage, and how steady it was: the relative spread (standard
  deviation over the mean) of its last ``SWITCH_SPREAD_EVALS`` evaluations in the second half of that stage
  (``MPO|switch_spread|<env>``, :func:`switch_spread`);
* Stage-2 learning speed in Env-B: the mean of all Env-B evaluations after the switch (area under the curve);
* the continual-learning field's return matrix of an online method (``<method>|R|<i>|<env>``): its return in each
  environment at the end of stage ``i``, the mean of its last ``ONLINE_LAST_STAGE1`` evaluations up to that stage's
  end (``ONLINE_LAST`` for the last stage: the final score). Online baselines share MPO's Stage 1, so their matrix
  starts at stage 1 (:mod:`sb3_lifelong.evaluation.continual` computes the metrics);
* a student's final return: the mean of its last ``STUDENT_LAST`` evaluations (of each repeat, then the mean over its
  repeats);
* Q per source: the student's last average Q-value over each environment's data;
* the data's value per source: the discounted return that followed each sampled transition of an environment's data
  in its stored episode (the collector's last Monte-Carlo measurement, ``data|mc_return|<env>``), and how far the
  collector's critic overestimates an environment's data when it leaves it and at the end
  (:func:`collector_overestimation`);
* a student's weights: the effective sample size and the share at the clip of its regression weights, the mean of
  its last ``STUDENT_TRAIN_LAST`` logged values (``<student>|weight_ess``, ``<student>|weight_clip_frac``);
* the rows of each environment's data in the seed's lifetime buffer (``buffer|rows|<env>``, :func:`source_rows`):
  the share a student that samples the whole buffer sees.
"""

import csv
import io
import json
import math
import pathlib
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple, Optional

import numpy as np
import pandas as pd

from sb3_lifelong.experiments.presets import Job, left_environments, study_ends

ONLINE_LAST = 3
ONLINE_LAST_STAGE1 = 2
STUDENT_LAST = 2
#: the evaluations before the switch (in the second half of the stage) whose relative spread says whether MPO left
#: an environment steadily (:func:`switch_spread`)
SWITCH_SPREAD_EVALS = 3
STUDENT_TRAIN_LAST = 5


# ------------------------------------------------------------------------------------------------- reading the logs
class LogColumns(NamedTuple):
    """What a job's log must hold for the report to read it."""

    #: columns that must be there, with a value in every row
    required: tuple[str, ...]
    #: columns that hold numbers (an empty cell is NaN, unless the column is required); None: every column
    numeric: Optional[tuple[str, ...]]


#: the logs the report reads, by file name (:func:`read_log`); another file is only checked for its field counts
LOG_COLUMNS = {
    "eval.csv": LogColumns(("timesteps", "env", "mean_reward"), ("timesteps", "mean_reward", "std_reward", "n_episodes")),
    "q_sources.csv": LogColumns(
        ("timesteps", "name", "q_mean"),
        ("timesteps", "source", "q_mean", "n", "q_probe", "mc_return", "overestimation", "n_mc"),
    ),
    "train.csv": LogColumns(("timesteps",), None),
}


@dataclass(frozen=True)
class MalformedRow:
    """A row of a result file that the report does not use: where it is, and what is wrong with it."""

    path: pathlib.Path
    #: the line of the file (1: the header)
    line: int
    problem: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.problem}"


class MalformedResultsError(ValueError):
    """
    Result files of a study hold malformed rows (a file cut in the middle of a row, a row that is not numbers where
    numbers are expected, a missing column): the report refuses to use them. ``rows`` names each one.
    """

    def __init__(self, rows: Sequence[MalformedRow]) -> None:
        self.rows = list(rows)
        shown = "\n".join(f"  {row}" for row in self.rows[:20])
        more = f"\n  ... and {len(self.rows) - 20} more" if len(self.rows) > 20 else ""
        super().__init__(
            f"{len(self.rows)} malformed row(s) in the study's result files (a write cut short, or a file not written by "
            f"this package):\n{shown}{more}\nNo report was written from them. Repair or move those files, or leave the "
            "rows out (report --drop-malformed; load_study(..., malformed='drop')), each named in a warning"
        )


class MalformedRowWarning(UserWarning):
    """A malformed row of a result file was left out of the report (``malformed="drop"``)."""


def read_log(path: pathlib.Path, problems: Optional[list[MalformedRow]] = None) -> pd.DataFrame:
    """
    Read a job's CSV log, checking every row: as many fields as the header, a number in each numeric column, a value
    in each required one (:data:`LOG_COLUMNS`), and a line end after the last row (a file that ends in the middle of
    a row was cut short while writing it). A file without a required column is unusable as a whole.

    :param path: the log
    :param problems: where the malformed rows are recorded; they are left out of the table. None: raise
    :return: the log's well-formed rows (the numeric columns as numbers, empty cells as NaN)
    :raises MalformedResultsError: (``problems`` is None) the file holds malformed rows, each named
    """
    found: list[MalformedRow] = []
    columns = LOG_COLUMNS.get(path.name, LogColumns((), ()))
    with open(path, newline="") as handle:
        text = handle.read()
    reader = csv.reader(io.StringIO(text, newline=""))
    header = next(reader, None)
    rows: list[tuple[int, list[str]]] = []
    if header is not None:
        rows = [(reader.line_num, row) for row in reader if row]  # (blank lines are skipped, as pandas does)
    cut = bool(text) and not text.endswith(("\n", "\r"))  # the last line has no line end: a write cut short
    missing = [] if header is None else [name for name in columns.required if name not in header]
    if header is None or missing or (cut and not rows):
        problem = (
            "an empty file (no header)"
            if header is None
            else (
                f"no column {', '.join(map(repr, missing))} (its columns: {', '.join(header)})"
                if missing
                else "the file ends in the middle of its header (no line end): a write cut short"
            )
        )
        found.append(MalformedRow(path, 1, problem + ": none of its rows is used"))
        frame = pd.DataFrame(columns=list(columns.required))
    else:
        numeric = [name for name in header if columns.numeric is None or name in columns.numeric]
        positions = {name: header.index(name) for name in header}
        kept = []
        for number, (line, row) in enumerate(rows):
            problem = None
            if cut and number == len(rows) - 1:
                problem = "the file ends in the middle of this row (no line end): a write cut short"
            elif len(row) != len(header):
                problem = f"{len(row)} fields where the header has {len(header)} (a row cut short, or two run together)"
            else:
                for name in columns.required:
                    if row[positions[name]] == "":
                        problem = f"no {name}"
                        break
                for name in numeric:
                    value = row[positions[name]]
                    if problem is None and value != "" and not _is_number(value):
                        problem = f"{name} is {value!r}, not a number"
            if problem is None:
                kept.append(row)
            else:
                found.append(MalformedRow(path, line, problem))
        clean = io.StringIO()
        csv.writer(clean).writerows([header, *kept])
        clean.seek(0)
        frame = pd.read_csv(clean)  # the well-formed rows, parsed as pandas parses the file (dtypes, NaN)
    if found and problems is None:
        raise MalformedResultsError(found)
    if problems is not None:
        problems.extend(found)
    return frame


def _is_number(value: str) -> bool:
    try:
        float(value)
    except ValueError:
        return False
    return True


def seeds_of(output: pathlib.Path) -> list[int]:
    """:return: the seeds of the study in ``output`` whose collection has finished, in order"""
    return sorted(int(path.name.split("_")[1]) for path in output.glob("seed_*") if (path / "collect" / "done.json").exists())


def read_eval(
    output: pathlib.Path, seed: int, job: str, problems: Optional[list[MalformedRow]] = None
) -> Optional[pd.DataFrame]:
    """
    :param problems: where malformed rows are recorded and left out (None: raise, :func:`read_log`)
    :return: a finished job's evaluations (its ``eval.csv``), or None when the job has not finished
    """
    path = output / f"seed_{seed}" / job / "eval.csv"
    if not (output / f"seed_{seed}" / job / "done.json").exists() or not path.exists():
        return None
    return read_log(path, problems)


def last_returns(
    frame: pd.DataFrame, env: str, count: int, until: Optional[int] = None, after: Optional[int] = None
) -> pd.Series:
    """:return: the mean returns of the last ``count`` evaluations in ``env`` at timesteps in ``(after, until]``"""
    rows = frame[frame["env"] == env]
    if until is not None:
        rows = rows[rows["timesteps"] <= until]
    if after is not None:
        rows = rows[rows["timesteps"] > after]
    return rows.sort_values("timesteps")["mean_reward"].tail(count)


def last_mean(frame: pd.DataFrame, env: str, count: int, until: Optional[int] = None, after: Optional[int] = None) -> float:
    """:return: the mean return of the last ``count`` evaluations in ``env`` at timesteps in ``(after, until]`` (or NaN)"""
    returns = last_returns(frame, env, count, until, after)
    return float(returns.mean()) if len(returns) else float("nan")


def relative_spread(returns: pd.Series) -> float:
    """
    :param returns: evaluations' mean returns
    :return: their standard deviation (``ddof=1``) over the absolute value of their mean: NaN for fewer than two (not
        measured), infinite for a mean of 0 (no level to speak of)
    """
    if len(returns) < 2:
        return float("nan")
    mean = float(returns.mean())
    return float(returns.std(ddof=1)) / abs(mean) if mean != 0.0 else float("inf")


def switch_spread(frame: pd.DataFrame, env: str, start: int, end: int) -> float:
    """
    How steadily MPO left an environment: the :func:`relative_spread` of its last ``SWITCH_SPREAD_EVALS`` evaluations
    there, taken from the second half of the environment's stage, so that the climb of its first steps is not read as
    an oscillation (where that half holds fewer than two evaluations: the stage's last two).

    :param frame: the collector's evaluations
    :param env: the environment
    :param start: the first timestep of its stage (0 for Env-A)
    :param end: the last timestep of its stage (the switch)
    :return: the spread (NaN with fewer than two evaluations in the stage)
    """
    returns = last_returns(frame, env, SWITCH_SPREAD_EVALS, until=end, after=start + (end - start) // 2)
    if len(returns) < 2:
        returns = last_returns(frame, env, 2, until=end, after=start)
    return relative_spread(returns)


def switch_metrics(seed: int, frame: pd.DataFrame, envs: Sequence[str], ends: Sequence[int]) -> list[dict[str, Any]]:
    """
    MPO's return when it leaves each environment but the last (``MPO|switch|<env>``: the mean of its last
    ``ONLINE_LAST_STAGE1`` evaluations there up to the end of that environment's stage) and how steadily it left it
    (``MPO|switch_spread|<env>``, :func:`switch_spread` over that stage alone).

    :param seed: the seed, for the rows
    :param frame: the collector's evaluations
    :param envs: the environments in the order of their stages
    :param ends: the timestep at which each stage ends (:func:`~sb3_lifelong.experiments.presets.stage_ends`)
    :return: two rows (seed, metric, value) per environment left
    """
    rows = []
    for env, start, end in zip(envs[:-1], [0, *ends[:-2]], ends[:-1]):
        value = last_mean(frame, env, ONLINE_LAST_STAGE1, until=end)
        rows.append(dict(seed=seed, metric=f"MPO|switch|{env}", value=value))
        rows.append(dict(seed=seed, metric=f"MPO|switch_spread|{env}", value=switch_spread(frame, env, start, end)))
    return rows


def last_evaluations(eval_csv: pathlib.Path, env: str, upto: Optional[int], count: int) -> list[float]:
    """
    :param eval_csv: a collection's ``eval.csv`` (``timesteps``, ``env``, ``mean_reward``)
    :param env: the environment's name
    :param upto: the last timestep counted (None: every evaluation)
    :param count: how many
    :return: the mean returns of the last ``count`` evaluations in ``env`` at timesteps <= ``upto``, oldest first;
        each value as Python's ``float`` parses it (the studies' recorded readings hold these values; a frame read by
        :func:`read_log` and :func:`last_returns` holds pandas' parse, which may differ in the last digit)
    """
    with open(eval_csv, newline="") as handle:
        rows = [row for row in csv.DictReader(handle) if row["env"] == env]
    rows = [row for row in rows if upto is None or int(row["timesteps"]) <= upto]
    rows.sort(key=lambda row: int(row["timesteps"]))
    return [float(row["mean_reward"]) for row in rows[-count:]]


def learnt_level(evals: Sequence[float], threshold: float, max_spread: float) -> tuple[float, float, bool]:
    """
    :param evals: an agent's last evaluations in an environment
    :param threshold: the return at which the environment counts as learnt
    :param max_spread: the largest spread (sample sd / mean) of a steady level
    :return: their mean, their spread, and whether it was learnt: a mean of at least ``threshold`` and a spread of at
        most ``max_spread`` (an infinite spread at a mean of 0)
    """
    mean = float(np.mean(evals))
    spread = float(np.std(evals, ddof=1) / abs(mean)) if mean else math.inf
    return mean, spread, bool(mean >= threshold and spread <= max_spread)


def switch_reading(eval_csv: pathlib.Path, switch: int, threshold: float, max_spread: float, count: int) -> dict[str, Any]:
    """
    Whether Env-A was learnt when the robot changed: the mean of the last ``count`` Env-A evaluations up to
    ``switch`` at least ``threshold``, their spread at most ``max_spread``, and ``count`` evaluations there at all.

    :param eval_csv: the collection's ``eval.csv``
    :param switch: the timestep of the change
    :param threshold: the return at which Env-A counts as learnt (a preset's ``env_a_learnt``)
    :param max_spread: the largest spread of a steady level (a preset's ``max_switch_spread``)
    :param count: the evaluations read
    :return: ``evals``, ``mean``, ``spread``, ``threshold``, ``max_spread``, ``learnt``
    """
    evals = last_evaluations(eval_csv, "Env-A", switch, count)
    mean, spread, learnt = learnt_level(evals, threshold, max_spread)
    return dict(evals=evals, mean=mean, spread=spread, threshold=threshold, max_spread=max_spread,
                learnt=learnt and len(evals) == count)  # fmt: skip


def overestimation_at(q_csv: pathlib.Path, name: str, timesteps: int) -> float:
    """
    :param q_csv: a collection's ``q_sources.csv``
    :param name: the source's name (``Env-A``, ...)
    :param timesteps: the timestep of the measurement
    :return: the critic's overestimation of that source logged at ``timesteps`` (NaN when not logged)
    """
    with open(q_csv, newline="") as handle:
        for row in csv.DictReader(handle):
            if row["name"] == name and int(row["timesteps"]) == timesteps and row.get("overestimation"):
                return float(row["overestimation"])
    return math.nan


def data_values(seed: int, q_log: pathlib.Path, problems: Optional[list[MalformedRow]] = None) -> list[dict[str, Any]]:
    """
    :param problems: where malformed rows are recorded and left out (None: raise, :func:`read_log`)
    :return: the extras ``data|mc_return|<env>`` of the collector's last Monte-Carlo measurement (none without one)
    """
    if not q_log.exists():
        return []
    q = read_log(q_log, problems)
    if "mc_return" not in q.columns or not q["mc_return"].notna().any():
        return []
    measured = q[q["mc_return"].notna()]
    last = measured[measured["timesteps"] == measured["timesteps"].max()]
    return [dict(seed=seed, metric=f"data|mc_return|{row.name}", value=float(row.mc_return)) for row in last.itertuples()]


def collector_overestimation(
    seed: int,
    q_log: pathlib.Path,
    envs: Sequence[str],
    ends: Sequence[int],
    problems: Optional[list[MalformedRow]] = None,
) -> list[dict[str, Any]]:
    """
    The forgetting-risk signal beside the forgetting claims: how far the collector's critic overestimates each left
    environment's data (mean Q minus the discounted return that followed), when it left it and at the end.

    :param seed: the seed
    :param q_log: the collector's ``q_sources.csv``
    :param envs: the environments, in stage order
    :param ends: the last timestep of each stage
    :param problems: where malformed rows are recorded and left out (None: raise, :func:`read_log`)
    :return: the extras ``MPO|overestimation_switch|<env>`` (the last measurement up to the end of the environment's
        stage) and ``MPO|overestimation_end|<env>`` (the last one), for each environment MPO left; none without
        Monte-Carlo columns
    """
    if not q_log.exists():
        return []
    q = read_log(q_log, problems)
    if "overestimation" not in q.columns:
        return []
    q = q[q["overestimation"].notna()].sort_values("timesteps")
    extras = []
    for env, end in zip(envs[:-1], ends[:-1]):
        rows = q[q["name"] == env]
        for when, chosen in (("switch", rows[rows["timesteps"] <= end]), ("end", rows)):
            if len(chosen):
                value = float(chosen["overestimation"].iloc[-1])
                extras.append(dict(seed=seed, metric=f"MPO|overestimation_{when}|{env}", value=value))
    return extras


#: the ``collect`` job's record (its ``done.json``; a sharing study's ``share`` job's) of the rows of each source in
#: the seed's lifetime buffer
SOURCE_ROWS_RECORD = "source_rows"
#: the method of a sharing study's second collector (its ``collect_agent2`` job) in the report
AGENT2_METHOD = "MPO agent 2"


def count_source_rows(buffer: pathlib.Path) -> dict[str, int]:
    """
    :param buffer: a lifetime buffer's directory (opened read-only: its sources column only is read)
    :return: the rows of each source, by its name
    """
    from sb3_lifelong.buffers import LifelongReplayBuffer

    with LifelongReplayBuffer.open(buffer, read_only=True) as data:
        return {str(name): int(count) for name, count in data.source_counts(by_name=True).items()}


def source_rows(run_dir: pathlib.Path, job: str = "collect") -> dict[str, int]:
    """
    :param run_dir: a seed's directory, its collection finished
    :param job: the job that recorded them: ``collect``, or a sharing study's ``share`` (its merged buffer's rows)
    :return: the rows of each environment's data in the seed's lifetime buffer: as its ``<job>/done.json`` recorded
        them (:data:`SOURCE_ROWS_RECORD`), else counted in its buffer when it is there (a study collected before the
        record existed); ``{}`` when neither is (a study exported without its buffers, say)
    """
    done_path = run_dir / job / "done.json"
    if not done_path.is_file():  # (a sharing seed whose merge has not run)
        return {}
    done = json.loads(done_path.read_text())
    recorded = done.get(SOURCE_ROWS_RECORD)
    if isinstance(recorded, dict):
        return {str(name): int(count) for name, count in recorded.items()}
    if not (run_dir / "buffer" / "manifest.json").is_file():
        return {}
    try:
        return count_source_rows(run_dir / "buffer")
    except (OSError, ValueError, RuntimeError) as error:  # unreadable: the report stands without the share
        warnings.warn(f"{run_dir / 'buffer'}: its rows per source could not be counted ({error})", stacklevel=2)
        return {}


def student_weights(
    seed: int, method: str, train_log: pathlib.Path, problems: Optional[list[MalformedRow]] = None
) -> list[dict[str, Any]]:
    """
    :param problems: where malformed rows are recorded and left out (None: raise, :func:`read_log`)
    :return: the extras ``<method>|weight_ess`` and ``<method>|weight_clip_frac`` of a student's ``train.csv``
    """
    if not train_log.exists():
        return []
    train = read_log(train_log, problems)
    return [
        dict(seed=seed, metric=f"{method}|{column}", value=float(train[column].dropna().tail(STUDENT_TRAIN_LAST).mean()))
        for column in ("weight_ess", "weight_clip_frac")
        if column in train.columns and train[column].notna().any()
    ]


def return_matrix(
    seed: int, method: str, frame: pd.DataFrame, envs: Sequence[str], ends: Sequence[int], first: int = 0
) -> list[dict[str, Any]]:
    """
    The continual-learning field's return matrix ``R[i][j]`` of an online method: its return in environment ``j`` at
    the end of stage ``i``, the mean of its last ``ONLINE_LAST_STAGE1`` evaluations up to that end (``ONLINE_LAST``
    for the last stage, whose row is the final score).

    :param first: the first stage of the method's own (an online baseline's Stage 1 is MPO's)
    :return: the extras ``<method>|R|<i>|<env>``
    """
    rows = []
    for stage, end in enumerate(ends):
        if stage < first:
            continue
        count = ONLINE_LAST if stage == len(ends) - 1 else ONLINE_LAST_STAGE1
        for env in envs:
            rows.append(dict(seed=seed, metric=f"{method}|R|{stage}|{env}", value=last_mean(frame, env, count, until=end)))
    return rows


@dataclass
class Study:
    """The scores of every seed of a study, as long tables."""

    output: pathlib.Path
    preset: dict[str, Any]
    seeds: list[int]
    finals: pd.DataFrame  # seed, method, kind (online / student), env, score
    extras: pd.DataFrame  # seed, metric, value (switch scores, Stage-2 areas, Q per source)
    #: the malformed rows of its result files that were left out (``load_study(..., malformed="drop")``)
    dropped: list[MalformedRow] = field(default_factory=list)

    def score(self, method: str, env: str) -> dict[int, float]:
        rows = self.finals[(self.finals["method"] == method) & (self.finals["env"] == env)]
        return {int(r.seed): float(r.score) for r in rows.itertuples()}

    def extra(self, metric: str) -> dict[int, float]:
        rows = self.extras[self.extras["metric"] == metric]
        return {int(r.seed): float(r.value) for r in rows.itertuples()}


def collector_extras(
    seed: int, frame: pd.DataFrame, run_dir: pathlib.Path, preset: dict[str, Any], problems: list[MalformedRow]
) -> list[dict[str, Any]]:
    """
    :return: the readings of the ``collect`` job's agent at each environment it left (:func:`switch_metrics`, its
        overestimation there), its data's discounted returns and the rows of each environment in the buffer the
        students distill
    """
    left = left_environments(preset)
    envs, ends = [*left, preset["env_names"][len(left)]], study_ends(preset)[: len(left) + 1]
    collect_dir = run_dir / "collect"
    extras = switch_metrics(seed, frame, envs, ends)
    extras += data_values(seed, collect_dir / "q_sources.csv", [])  # (its problems: counted once, by the caller)
    extras += collector_overestimation(seed, collect_dir / "q_sources.csv", envs, ends, problems)
    rows = source_rows(run_dir, "share" if preset.get("sharing") else "collect")
    return extras + [dict(seed=seed, metric=f"buffer|rows|{name}", value=float(count)) for name, count in rows.items()]


def student_extras(seed: int, method: str, job_dir: pathlib.Path, problems: list[MalformedRow]) -> list[dict[str, Any]]:
    """:return: a student's average Q per source at its last measurement (``<method>|q|<source>``) and its weights"""
    extras = []
    q_path = job_dir / "q_sources.csv"
    if q_path.exists():
        q = read_log(q_path, problems)
        if len(q):
            last = q[q["timesteps"] == q["timesteps"].max()]
            extras += [dict(seed=seed, metric=f"{method}|q|{row.name}", value=float(row.q_mean)) for row in last.itertuples()]
    return extras + student_weights(seed, method, job_dir / "train.csv", problems)


def load_study(
    output: pathlib.Path, seeds: Optional[Sequence[int]] = None, malformed: Literal["refuse", "drop"] = "refuse"
) -> Study:
    """
    Read every finished job of every seed of ``output``. Every row of the logs read is checked (:func:`read_log`).

    :param output: the study's directory
    :param seeds: only these seeds (default: every seed whose collection has finished)
    :param malformed: what to do with malformed rows: ``"refuse"`` (raise, naming each) or ``"drop"`` (leave them
        out, with a :class:`MalformedRowWarning` naming each; they are in ``Study.dropped``)
    :return: the scores; a student's score on a seed is the mean over its finished repeats, and ``finals`` counts
        them in its column ``repeats``
    :raises MalformedResultsError: (``malformed="refuse"``) a log holds malformed rows, each named by file and line
    """
    if malformed not in ("refuse", "drop"):
        raise ValueError(f"malformed must be 'refuse' or 'drop', got {malformed!r}")
    problems: list[MalformedRow] = []
    preset = json.loads((output / "preset.json").read_text())
    envs = preset["env_names"]
    ends = study_ends(preset)
    switch = ends[0]
    finished = seeds_of(output)
    if seeds is not None:
        missing = sorted(set(seeds) - set(finished))
        if missing:
            raise ValueError(f"seeds {missing} of {output} have no finished collection (finished: {finished})")
    seeds = finished if seeds is None else sorted(set(seeds))
    finals, extras = [], []
    for seed in seeds:
        run_dir = output / f"seed_{seed}"
        for job_dir in sorted(p for p in run_dir.iterdir() if (p / "done.json").exists()):
            job = job_dir.name
            frame = read_eval(output, seed, job, problems)
            if frame is None:
                continue
            parsed = Job.parse(job)
            if parsed.kind == "collect_agent2":  # a sharing study's second robot: its finals, on its own clock
                for env in envs:
                    score = last_mean(frame, env, ONLINE_LAST)
                    finals.append(dict(seed=seed, method=AGENT2_METHOD, kind="online", env=env, score=score))
            elif parsed.kind in ("collect", "online"):
                method = "MPO" if parsed.kind == "collect" else f"online {parsed.name}"
                for env in envs:
                    finals.append(
                        dict(seed=seed, method=method, kind="online", env=env, score=last_mean(frame, env, ONLINE_LAST))
                    )
                    area = last_mean(frame, env, 10**9, after=switch, until=ends[1])  # Stage 2 only (of 2 or 3)
                    extras.append(dict(seed=seed, metric=f"{method}|stage2_area|{env}", value=area))
                # an online method's rows start after the Stage 1 it shares with MPO
                if not preset.get("sharing"):  # the field's matrix is one robot's sequence of stages
                    extras += return_matrix(seed, method, frame, envs, ends, first=0 if job == "collect" else 1)
                if job == "collect":
                    extras += collector_extras(seed, frame, run_dir, preset, problems)
            else:
                method = parsed.name  # a student's repeats score as their mean
                for env in envs:
                    score = last_mean(frame, env, STUDENT_LAST)
                    finals.append(dict(seed=seed, method=method, kind="student", env=env, score=score))
                extras += student_extras(seed, method, job_dir, problems)
    finals_frame, extras_frame = pd.DataFrame(finals), pd.DataFrame(extras)
    if len(finals_frame):  # one row per (seed, method, env): the mean over a student's repeats
        groups = finals_frame.groupby(["seed", "method", "kind", "env"], as_index=False, sort=False)["score"]
        finals_frame = groups.agg(score="mean", repeats="size")  # finished jobs, a NaN score (no evaluation) included
    if len(extras_frame):
        extras_frame = extras_frame.groupby(["seed", "metric"], as_index=False, sort=False)["value"].mean()
    if problems and malformed == "refuse":
        raise MalformedResultsError(problems)
    for problem in problems:
        warnings.warn(f"left out of the report, a malformed row: {problem}", MalformedRowWarning, stacklevel=2)
    return Study(output, preset, seeds, finals_frame, extras_frame, problems)

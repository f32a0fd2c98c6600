"""
The report of a two-stage (or three-stage) study: its score tables, the pre-registered claims with their verdicts,
and ``report.md`` with the paper's figures (:mod:`sb3_lifelong.experiments.figures`). ``report.md`` opens with what
the run showed in three lines (``summary_lines``), after a warning when the study ran at a toy budget
(``toy_warning``).

The scores are each seed's (:mod:`sb3_lifelong.experiments.scores`); a table gives their mean +- std over seeds and
a 95 % BCa bootstrap interval of the mean, from ``scipy.stats.bootstrap`` (at one seed: its value alone).

A claim that compares two methods also reports their paired difference: per seed (both from the same seed's
collection), its mean with a BCa interval, and on how many seeds the first is higher (rliable's "probability of
improvement" over seeds). The verdicts themselves are the pre-registered tests on the means.
"""

import json
import os
import pathlib
import shutil
from collections.abc import Mapping, Sequence
from typing import Any, Literal, Optional, Union

import numpy as np
import pandas as pd

from sb3_lifelong.core.atomic import atomic_write, write_text_atomic
from sb3_lifelong.experiments.claims import Claim, evaluate_claims, load_claims, mean_over_envs, ratio, series_mean
from sb3_lifelong.experiments.figures import plot_study
from sb3_lifelong.experiments.presets import (
    STUDENTS,
    describe_stage,
    drift_text,
    evaluation_stages,
    left_environments,
    preset_name,
    sharing_text,
    toy_budget,
)
from sb3_lifelong.experiments.scores import (
    ONLINE_LAST,
    ONLINE_LAST_STAGE1,
    STUDENT_LAST,
    SWITCH_SPREAD_EVALS,
    Study,
    load_study,
)
from sb3_lifelong.experiments.statistics import describe
from sb3_lifelong.experiments.style import over_seeds


def write_csv_atomic(frame: pd.DataFrame, path: pathlib.Path) -> None:
    """Write a table to ``path`` atomically (:mod:`sb3_lifelong.core.atomic`): a failed write leaves the old file."""
    with atomic_write(path, "w", newline="") as handle:
        frame.to_csv(handle, index=False)


# ------------------------------------------------------------------------------------------------- tables
def score_table(study: Study) -> str:
    envs = study.preset["env_names"]
    header = "| method | kind | " + " | ".join(envs) + " | mean over envs | seeds |"
    lines = [header, "|" + " --- |" * (len(envs) + 4)]
    order = list(dict.fromkeys(study.finals["method"])) if len(study.finals) else []
    order.sort(key=lambda m: (0 if m.startswith("MPO") else 1 if m.startswith("online") else 2))
    for method in order:
        kind = study.finals[study.finals["method"] == method]["kind"].iloc[0]
        cells = [_cell(list(study.score(method, env).values()), len(study.seeds)) for env in envs]
        overall = mean_over_envs(study, method)
        lines.append(
            f"| {method} | {kind} | " + " | ".join(cells) + f" | {_cell(list(overall.values()), len(study.seeds))} | "
            f"{len(overall)} |"
        )
    return "\n".join(lines)


def _cell(values: Sequence[float], seeds: int) -> str:
    """:return: the values' :func:`describe`, saying "1 seed" where a study of several seeds has one value"""
    return describe(values) + (" (1 seed)" if len(values) == 1 and seeds > 1 else "")


def weights_table(study: Study) -> str:
    """
    :return: each student's regression weights, per seed: their effective sample size (a fraction of a batch: 1 is
        behaviour cloning, small is greedy) and their share at the clip, the means of its last logged values; "" when
        no student logged them
    """
    metrics = sorted(set(study.extras["metric"])) if len(study.extras) else []
    methods = sorted({metric.rsplit("|", 1)[0] for metric in metrics if metric.endswith("|weight_ess")})
    if not methods:
        return ""
    lines = [
        "| student | weights' effective sample size (per seed) | share at the clip (per seed) |",
        "| --- | --- | --- |",
    ]
    for method in methods:
        cells = []
        for column in ("weight_ess", "weight_clip_frac"):
            values = study.extra(f"{method}|{column}")
            per_seed = ", ".join(f"s{seed}: {value:.2f}" for seed, value in sorted(values.items()))
            cells.append(f"{series_mean(values):.2f} ({per_seed})" if values else "-")
        lines.append(f"| {method} | {cells[0]} | {cells[1]} |")
    return "\n".join(lines)


def forgetting_table(study: Study) -> str:
    """
    :return: for each seed and each environment MPO left: its return there when it left (the switch score) and how
        steady it was then, its return there at the end, their ratio (what the forgetting claims read), and the
        collector's overestimation of that environment's data when it left and at the end (a source whose
        overestimation grows is being forgotten); "" without MPO scores
    """
    envs = left_environments(study.preset)
    if not any(study.extra(f"MPO|switch|{env}") for env in envs):
        return ""
    lines = [
        "| seed | environment | when MPO left it | spread then | at the end | end / switch "
        "| overestimation of its data: when MPO left it -> at the end |",
        "| --- | --- | --- | --- | --- | --- | --- |",
    ]

    def cell(values: Mapping[int, float], seed: int, form: str) -> str:
        value = values.get(seed, float("nan"))
        return form.format(value) if np.isfinite(value) else ("inf" if value == np.inf else "-")

    for env in envs:
        switch, spread, end = (
            study.extra(f"MPO|switch|{env}"),
            study.extra(f"MPO|switch_spread|{env}"),
            study.score("MPO", env),
        )
        over_switch, over_end = study.extra(f"MPO|overestimation_switch|{env}"), study.extra(f"MPO|overestimation_end|{env}")
        forgetting = ratio(end, switch)
        for seed in study.seeds:
            overestimation = f"{cell(over_switch, seed, '{:+.1f}')} -> {cell(over_end, seed, '{:+.1f}')}"
            lines.append(
                f"| {seed} | {env} | {cell(switch, seed, '{:.0f}')} | {cell(spread, seed, '{:.2f}')} | "
                f"{cell(end, seed, '{:.0f}')} | {cell(forgetting, seed, '{:.2f}')} | {overestimation} |"
            )
    return "\n".join(lines)


#: episodes of the uniformly random policy per environment, the zero of the field's normalised scores
RANDOM_EPISODES = 10
#: where a study keeps its random policy's returns (measured once, by the first report that needs them)
RANDOM_RETURNS_FILE = "random_returns.json"


def measure_random_returns(preset: Mapping[str, Any], episodes: int = RANDOM_EPISODES) -> dict[str, float]:
    """
    A uniformly random policy's mean return in each environment of a study: the zero of the continual-learning
    field's normalised scores (:func:`~sb3_lifelong.evaluation.continual.continual_metrics`). The episodes are seeded,
    so the measurement is the same every time.

    :param preset: the study's settings (its ``preset.json``)
    :param episodes: episodes per environment
    :return: environment name -> mean return
    """
    from sb3_lifelong.envs import stage_envs
    from sb3_lifelong.evaluation.callbacks import EVAL_SEED_OFFSET
    from sb3_lifelong.evaluation.continual import random_policy_returns

    steps = preset.get("max_episode_steps")
    env_kwargs = {} if steps is None else dict(max_episode_steps=steps)
    envs = stage_envs(preset["env_id"], _evaluated(preset), preset["env_names"], env_kwargs, append_params=True)
    try:
        return random_policy_returns(
            envs,
            episodes,
            env_seeds=[EVAL_SEED_OFFSET + 1000 * index for index in range(len(envs))],
            action_seeds=[EVAL_SEED_OFFSET + index for index in range(len(envs))],
        )
    finally:
        for env in envs.values():
            env.close()


def _evaluated(preset: Mapping[str, Any]) -> list[Any]:
    """:return: the robot each stage of a study (its ``preset.json``) is evaluated on, as JSON-friendly values"""
    return [describe_stage(s) for s in evaluation_stages(preset["stages"], preset.get("drift"), preset.get("drift_eval_at"))]


def _drift_text(preset: Mapping[str, Any]) -> str:
    """:return: what drifts over a study's life and where each stage is evaluated ("" without a drift), for the report"""
    if not preset.get("drift"):
        return ""
    ramps = drift_text(preset["drift"])
    evaluated = "; ".join(f"{env} on {json.dumps(stage)}" for env, stage in zip(preset["env_names"], _evaluated(preset)))
    return f"drifting over the whole life: {ramps}; evaluated: {evaluated}; "


def random_returns(output: pathlib.Path, preset: Mapping[str, Any]) -> dict[str, float]:
    """
    :return: the random policy's return per environment, read from the study's ``random_returns.json``, or measured
        (:func:`measure_random_returns`) and written there when it is missing or was measured for other environments
    """
    path = output / RANDOM_RETURNS_FILE
    if path.is_file():
        record = json.loads(path.read_text())
        if record.get("env_names") == list(preset["env_names"]) and record.get("stages") == _evaluated(preset):
            return {name: float(value) for name, value in record["returns"].items()}
    returns = measure_random_returns(preset)
    record = dict(
        env_names=list(preset["env_names"]), stages=_evaluated(preset), episodes=RANDOM_EPISODES,
        policy="uniform over the action space, seeded", returns=returns,
    )  # fmt: skip
    write_text_atomic(path, json.dumps(record, indent=1) + "\n")
    return returns


def _signed(value: float) -> str:
    """:return: ``value`` with its sign and two decimals, or ``n/a`` when it was not measured"""
    return f"{value:+.2f}" if np.isfinite(value) else "n/a"


def continual_table(study: Study, random: Mapping[str, float]) -> str:
    """
    :param random: the random policy's return per environment
    :return: each online method's forgetting and transfer in the continual-learning field's terms, per seed and as a
        mean +- std over seeds (:func:`~sb3_lifelong.evaluation.continual.continual_metrics`, the reference of each
        environment being the best end-of-stage return of that seed and method there); "" without MPO's matrix
    """
    from sb3_lifelong.evaluation.continual import continual_metrics

    envs = study.preset["env_names"]
    stages = len(envs)
    metrics = set(study.extras["metric"]) if len(study.extras) else set()
    methods = list(dict.fromkeys(metric.split("|R|")[0] for metric in metrics if "|R|" in metric))
    methods.sort(key=lambda m: (m != "MPO", m))
    if "MPO" not in methods:
        return ""
    left = envs[:-1]
    header = (
        "| method | seed | average performance | "
        + " | ".join(f"forgetting of {env}" for env in left)
        + " | backward transfer | forward transfer |"
    )
    lines = [header, "|" + " --- |" * (len(left) + 5)]
    for method in methods:
        rows_of = {i: {env: study.extra(f"{'MPO' if i == 0 else method}|R|{i}|{env}") for env in envs} for i in range(stages)}
        collected: dict[str, list[float]] = {}
        for seed in study.seeds:
            matrix = [[rows_of[i][env].get(seed, float("nan")) for env in envs] for i in range(stages)]
            if not np.all(np.isfinite(np.asarray(matrix)[np.tril_indices(stages)])):
                continue  # unfinished: an environment not measured at the end of its stage or later
            try:
                found = continual_metrics(matrix, [random[env] for env in envs])
            except ValueError:  # a seed that learnt nothing above the random policy somewhere: nothing to normalise by
                lines.append(f"| {method} | {seed} | not defined: no return above the random policy's in an environment |")
                continue
            values = {
                "average performance": found["average_performance"],
                **{f"forgetting of {env}": found["forgetting"][j] for j, env in enumerate(left)},
                "backward transfer": found["backward_transfer"],
                "forward transfer": found["forward_transfer"],
            }
            for key, value in values.items():
                collected.setdefault(key, []).append(value)
            lines.append(f"| {method} | {seed} | " + " | ".join(_signed(v) for v in values.values()) + " |")
        if collected and len(next(iter(collected.values()))) > 1:
            cells = [
                f"{np.mean(v):+.2f} +- {np.std(v, ddof=1):.2f}" if np.all(np.isfinite(v)) else "n/a"
                for v in collected.values()
            ]
            lines.append(f"| {method} | mean +- std | " + " | ".join(cells) + " |")
    return "\n".join(lines) if len(lines) > 2 else ""


def claims_table(rows: list[dict[str, Any]], seeds: int = 2) -> str:
    """
    :param rows: the claims' verdicts (:func:`~sb3_lifelong.experiments.claims.evaluate_claims`)
    :param seeds: the study's seeds (one: no interval is given, and the header says so)
    :return: the claims as a markdown table (with a precondition column when the rows have one)
    """
    checked = any("precondition" in r for r in rows)
    lines = [
        (
            "| claim | pre-registered criterion | verdict | values: mean [95 % BCa CI] (per seed) "
            "| paired by seed: mean difference [95 % BCa CI], seeds on which the first is higher |"
            if seeds > 1
            else "| claim | pre-registered criterion | verdict | values (1 seed: no interval) | difference on that seed |"
        )
        + (" precondition |" if checked else ""),
        "| --- | --- | --- | --- | --- |" + (" --- |" if checked else ""),
    ]
    lines += [
        f"| {r['claim']} | {r['statement']} | **{r['verdict']}** | {r['values']} | {r.get('paired') or '-'} |"
        + (f" {r.get('precondition', '-')} |" if checked else "")
        for r in rows
    ]
    return "\n".join(lines)


def incomplete_repeats(study: Study) -> list[str]:
    """:return: one line per seed and student scored on fewer repeats than the study trains (some still running)"""
    wanted = int(study.preset.get("student_repeats", 1))
    students = study.finals[study.finals["kind"] == "student"].drop_duplicates(["seed", "method"])
    lines = [
        f"seed {row.seed}: {row.method} on {row.repeats} of {wanted} repeats"
        for row in students.itertuples()
        if row.repeats < wanted
    ]
    for seed in study.seeds:  # the preset's students with no finished repeat on a seed
        trained = set(students[students["seed"] == seed]["method"])
        lines += [
            f"seed {seed}: {name} on 0 of {wanted} repeats"
            for name in study.preset.get("students") or ()
            if name not in trained
        ]
    return lines


def continual_section(output: pathlib.Path, study: Study) -> str:
    """:return: the report's section of forgetting and transfer in the field's terms ("" without MPO's matrix)"""
    from sb3_lifelong.evaluation.continual import NORMALISATION

    metrics = set(study.extras["metric"]) if len(study.extras) else set()
    if not any(metric.startswith("MPO|R|") for metric in metrics):
        return ""
    try:
        random = random_returns(output, study.preset)
    except Exception as error:  # the robot cannot be made here (e.g. no robot model): the rest of the report stands
        return (
            "\n\n## Forgetting and transfer in the field's terms\n\nNot computed: the random policy's returns could not "
            + f"be measured ({type(error).__name__}: {error})."
        )
    table = continual_table(study, random)
    if not table:
        return ""
    measured = ", ".join(f"{env} {value:.1f}" for env, value in random.items())
    return (
        "\n\n## Forgetting and transfer in the field's terms\n\n"
        + "As Continual World, CORA and GEM report them, from the return matrix R[i][j] (the return in environment j at "
        + f"the end of stage i: the mean of the last {ONLINE_LAST_STAGE1} evaluations of a stage, the last "
        + f"{ONLINE_LAST} for the final stage). Normalised per environment: {NORMALISATION}. The random policy's "
        + f"returns ({RANDOM_EPISODES} seeded episodes, `{RANDOM_RETURNS_FILE}`): {measured}; the reference is each "
        + "seed's best end-of-stage return in that environment. Forgetting of an environment: its score at the end of "
        + "its stage minus at the end (positive: forgotten); backward transfer: minus the mean forgetting; forward "
        + "transfer: the mean score in each later environment before training in it (n/a where that environment was not "
        + f"evaluated before its stage). Online baselines share MPO's Stage 1.\n\n{table}"
    )


# ------------------------------------------------------------------------------------------------- the top
#: the student the summary reads: the pipeline's (CRR exp beta=1 on the whole buffer)
PIPELINE_STUDENT = "CRR_exp_beta1"
#: the verdicts, in the order the summary counts them
VERDICTS = ("reproduced", "not reproduced", "not testable", "no data")


def _mean_of_seeds(values: Sequence[float]) -> str:
    """:return: the mean of per-seed values, with their std from two seeds on (``-`` without a finite value)"""
    data = [float(v) for v in values if np.isfinite(v)]
    if not data:
        return "-"
    return f"{np.mean(data):.0f}" + (f" +- {np.std(data):.0f}" if len(data) > 1 else "")


def summary_lines(study: Study, verdicts: Sequence[Mapping[str, Any]]) -> list[str]:
    """
    What the run showed, in three lines (markdown list items): the pipeline's student's final return in every
    environment against MPO's at the end of the collection; what MPO kept of each environment it left (its return
    there at the end against when it left); and the pre-registered claims' verdicts, counted.

    :param study: the study
    :param verdicts: its claims' verdicts (:func:`~sb3_lifelong.experiments.claims.evaluate_claims`; none: no claims
        were given)
    :return: the three lines
    """
    envs = study.preset["env_names"]
    seeds = over_seeds(len(study.seeds), "mean +- std")

    def returns(method: str) -> str:
        return ", ".join(f"{env} {_mean_of_seeds(list(study.score(method, env).values()))}" for env in envs)

    present = list(dict.fromkeys(study.finals[study.finals["kind"] == "student"]["method"])) if len(study.finals) else []
    ordered = [name for name in STUDENTS if name in present] + [name for name in present if name not in STUDENTS]
    mpo = f"MPO at the end of the collection: {returns('MPO')}" if study.score("MPO", envs[0]) else "MPO: no score"
    if not ordered:
        first = f"- **No student has finished**; {mpo} ({seeds})."
    else:
        student = PIPELINE_STUDENT if PIPELINE_STUDENT in ordered else ordered[0]
        who = "The pipeline's student" if student == PIPELINE_STUDENT else "The first student"
        first = (
            f"- **{who}** ({student}, {study.preset['distill_steps']:,} updates): {returns(student)}; against {mpo} ({seeds})."
        )
    kept = []
    for env in left_environments(study.preset):
        switch, end = study.extra(f"MPO|switch|{env}"), study.score("MPO", env)
        if switch and end:
            kept_share = list(ratio(end, switch).values())
            share = f"{np.mean(kept_share):.2f}" if kept_share else "n/a"
            kept.append(
                f"{env}: {_mean_of_seeds(list(end.values()))} at the end against {_mean_of_seeds(list(switch.values()))} "
                f"when it left it (end / switch {share})"
            )
    second = "- **What MPO kept of the environments it left**: " + ("; ".join(kept) if kept else "not measured") + "."
    if verdicts:
        counted = {verdict: sum(row["verdict"] == verdict for row in verdicts) for verdict in VERDICTS}
        reproduced = [str(row["claim"]) for row in verdicts if row["verdict"] == "reproduced"]
        third = (
            f"- **The {len(verdicts)} pre-registered claims**: "
            + ", ".join(f"{count} {verdict}" for verdict, count in counted.items() if count)
            + (f" (reproduced: {', '.join(reproduced)})" if reproduced else "")
            + ("; at a toy budget, no evidence either way." if toy_budget(study.preset, study.output) else ".")
        )
    else:
        third = "- **Claims**: none given, so none was tested."
    return [first, second, third]


def toy_warning(study: Study) -> str:
    """:return: the report's warning at a toy budget (``presets.toy_budget``), or ``""``"""
    if not toy_budget(study.preset, study.output):
        return ""
    name = preset_name(study.preset, study.output)
    return (
        f"> **A toy budget**{f' (preset `{name}`)' if name else ''}: Env-A is not learnt at this budget, so these numbers "
        "show that the pipeline runs end to end, not the paper's findings, and the claims' verdicts are no evidence "
        "either way. The smallest study of the paper's questions here is the `cpu` preset."
    )


#: the claims section of a study reported without claims
NO_CLAIMS = "No claims were given (a study's claims are the claims.py in its folder, or `report --claims FILE`)."


def study_claims(output: pathlib.Path, claims: Optional[Union[str, os.PathLike, Sequence[Claim]]] = None) -> list[Claim]:
    """
    :param output: the study's directory
    :param claims: its claims, or the path of its claims file; None: the ``claims.py`` in ``output`` when there is one
    :return: the claims (none: the report has no claims section)
    """
    if claims is None:
        found = output / "claims.py"
        return load_claims(found) if found.is_file() else []
    if isinstance(claims, (str, os.PathLike)):
        return load_claims(claims)
    return list(claims)


def write_report(
    output: pathlib.Path,
    plots: bool = True,
    seeds: Optional[Sequence[int]] = None,
    claims: Optional[Union[str, os.PathLike, Sequence[Claim]]] = None,
    malformed: Literal["refuse", "drop"] = "refuse",
) -> str:
    """
    Write ``scores.csv``, ``claims.csv``, ``report.md`` and the figures into ``output`` (each atomically: a failed
    write leaves the previous file). Every row of the logs read is checked first (:func:`~.scores.read_log`): a
    malformed one (a file cut in the middle of a row, text where a number is expected, a missing column) is never
    used.

    :param output: the study's directory
    :param claims: the study's pre-registered claims, or the path of its claims file (:func:`study_claims`; None: the
        ``claims.py`` in ``output``, if any)
    :param plots: draw the figures
    :param seeds: report these seeds only, into ``report_seeds_<k>_<l>.md`` (and the CSV files of the same suffix;
        no figures), beside the report of every seed
    :param malformed: ``"refuse"``: a malformed row raises, and nothing is written; ``"drop"``: malformed rows are left
        out, each named in a warning and in the report's section "Rows left out"
    :return: the markdown report
    :raises MalformedResultsError: (``malformed="refuse"``) the study's logs hold malformed rows, named by file and line
    """
    study = load_study(output, seeds, malformed)
    if not study.seeds:
        raise FileNotFoundError(f"no finished seed in {output} (a seed counts once its collect job is done)")
    suffix = "" if seeds is None else "_seeds_" + "_".join(str(seed) for seed in study.seeds)
    plots = plots and seeds is None
    write_csv_atomic(study.finals, output / f"scores{suffix}.csv")
    write_csv_atomic(study.extras, output / f"extras{suffix}.csv")
    verdicts = evaluate_claims(study, study_claims(output, claims))
    write_csv_atomic(pd.DataFrame(verdicts), output / f"claims{suffix}.csv")
    partial = incomplete_repeats(study)
    warning = toy_warning(study)
    one_seed = len(study.seeds) == 1
    text = (
        f"# {len(study.preset['env_names'])}-stage study: {study.preset['env_id']}, seeds {study.seeds}\n\n"
        + (f"{warning}\n\n" if warning else "")
        + "\n".join(summary_lines(study, verdicts))
        + "\n\n"
        f"Stages: {json.dumps(study.preset['stages'])}; steps {study.preset['stage_steps']}; "
        + sharing_text(study.preset)
        + _drift_text(study.preset)
        + f"{study.preset['distill_steps']:,} updates per student"
        + (
            f", each student trained {study.preset['student_repeats']} times per seed and scored by the mean.\n\n"
            if study.preset.get("student_repeats", 1) > 1
            else ".\n\n"
        )
        + (f"{study.preset['note']}\n\n" if study.preset.get("note") else "")
        + (
            "**Not every repeat has finished**; these students are scored on the repeats that have: "
            + "; ".join(partial)
            + ".\n\n"
            if partial
            else ""
        )
        + "## Final returns\n\n"
        + (
            "1 seed: each cell is that seed's value (one seed gives no spread and no interval)"
            if one_seed
            else "mean +- std over seeds [95 % BCa bootstrap CI of the mean]"
        )
        + f"; online methods: mean of the last {ONLINE_LAST} evaluations, students: mean of the last {STUDENT_LAST}.\n\n"
        + score_table(study)
        + (
            "\n\n## What MPO kept of the environments it left\n\nWhen it left: the mean of its last "
            + f"{ONLINE_LAST_STAGE1} evaluations there; spread: std / mean of its last {SWITCH_SPREAD_EVALS} in the "
            + "second half of that stage; at the end: the mean of its last "
            + f"{ONLINE_LAST}; overestimation: the collector's mean Q minus the discounted return that followed, on "
            + f"that environment's data.\n\n{forgetting}"
            if (forgetting := forgetting_table(study))
            else ""
        )
        + continual_section(output, study)
        + (f"\n\n## The students' weights\n\n{weights}" if (weights := weights_table(study)) else "")
        + (
            f"\n\n## Rows left out\n\n{len(study.dropped)} malformed row(s) of the result files were left out:\n\n"
            + "\n".join(
                f"- `{row.path.relative_to(output) if row.path.is_relative_to(output) else row.path}`, "
                f"line {row.line}: {row.problem}"
                for row in study.dropped
            )
            if study.dropped
            else ""
        )
        + "\n\n## Claims\n\n"
        + (claims_table(verdicts, len(study.seeds)) if verdicts else NO_CLAIMS)
        + "\n"
    )
    if plots:
        paths = plot_study(study)
        text += "\n## Figures\n\n" + "\n".join(f"![{p.stem}]({p.name})" for p in paths) + "\n"
    write_text_atomic(output / f"report{suffix}.md", text)
    return text


#: the files of a study that are worth keeping (in git, say): no buffers, no models
SMALL_FILES = ("*.csv", "*.json", "*.md", "*.png")


def export_results(output: pathlib.Path, destination: pathlib.Path) -> list[pathlib.Path]:
    """
    Copy a study's small result files (CSV, JSON, Markdown, PNG; no buffers, no models, nothing of a job that has
    not finished) into ``destination``, keeping their layout, so that its results can be committed without its data.

    :return: the copied files
    """
    copied = []
    for pattern in SMALL_FILES:
        for path in output.rglob(pattern):
            parts = path.relative_to(output).parts
            if any(part.startswith("buffer") or part.startswith(".") for part in parts):
                continue  # buffers, and what a crash left half-made (e.g. an unfinished adopted collection)
            if len(parts) > 2 and parts[0].startswith("seed_") and not (output / parts[0] / parts[1] / "done.json").exists():
                continue  # a job that has not finished: its partial curves would read as results
            target = destination / path.relative_to(output)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(path, target)
            copied.append(target)
    return copied

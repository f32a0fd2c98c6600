"""benchmarks/studies/starvation_control: the matched variants draw what they claim, the readings go each way, and the
report reads a written tree (no training here)."""

import json
import math

import pandas as pd
import pytest
from testkit import benchmark_module

starvation = benchmark_module("starvation")


def test_matched_variants_draw_the_reference_env_a_rows_and_the_dose_fewer():
    variants = starvation.VARIANTS
    reference = variants[starvation.REFERENCE].env_a_draws()
    for name in starvation.MATCHED.values():
        assert variants[name].env_a_draws() == pytest.approx(reference, rel=1e-12)
        assert variants[name].ratio == variants[starvation.DOSE].ratio  # the dose is the share: only the draws differ
    assert reference / variants[starvation.DOSE].env_a_draws() == pytest.approx(3.5)
    # what moves with them: Env-B draws go up four times for both matched ways
    for name in starvation.MATCHED.values():
        assert variants[name].env_b_draws() / variants[starvation.REFERENCE].env_b_draws() == pytest.approx(4.0)


def test_each_variant_is_the_pipeline_student_with_its_batch_and_updates_only():
    from sb3_lifelong.experiments.presets import load_presets

    base = load_presets(starvation.PIPELINE_PRESETS)[starvation.PRESET].describe()
    for variant in starvation.VARIANTS.values():
        changed = starvation.preset_of(variant).describe()
        assert changed["student_batch_size"] == variant.batch_size and changed["distill_steps"] == variant.updates
        differs = {k for k in base if base[k] != changed[k]}
        assert differs <= {"student_batch_size", "distill_steps"}


def test_train_runs_every_variant_and_student_seed_first_seed_first(monkeypatch, tmp_path):
    import sb3_lifelong.experiments.protocol as protocol

    calls = []

    def fake(study, seed, output, students, preset, student_seed=None, about=None, log=print):
        ((name, student),) = students.items()
        calls.append((name, student.ratio, preset.student_batch_size, preset.distill_steps, student_seed, about))
        return [name]

    monkeypatch.setattr(protocol, "distill_on_study", fake)
    starvation.train(tmp_path / "study", 12, tmp_path / "out")
    assert [c[0] for c in calls] == [*starvation.VARIANTS, *(f"{v}__r1" for v in starvation.VARIANTS)]
    for name, ratio, batch, updates, student_seed, about in calls:
        variant = starvation.VARIANTS[about["variant"]]
        assert (ratio, batch, updates) == (variant.ratio, variant.batch_size, variant.updates)
        assert student_seed == 12 + 1000 * about["repeat"]
        assert name == starvation.job_name(about["variant"], about["repeat"])


def summary(low, high, n=5):
    return dict(n=n, mean=(low + high) / 2, sd=0.1, low=low, high=high)


DROP = summary(0.05, 0.20)


@pytest.mark.parametrize(
    "left, recovered, expected",
    [
        (summary(-0.03, 0.04), summary(0.06, 0.20), "starvation"),
        (summary(0.06, 0.20), summary(-0.04, 0.049), "imbalance"),
        (summary(0.01, 0.10), summary(0.02, 0.12), "both"),
        (summary(-0.04, 0.04), summary(-0.04, 0.04), "inconclusive"),  # both equivalences: cannot tell apart
        (summary(-0.02, 0.10), summary(-0.02, 0.12), "inconclusive"),
        (summary(-0.051, 0.04), summary(0.06, 0.20), "inconclusive"),  # just outside the margin
    ],
)
def test_control_reading_each_way(left, recovered, expected):
    assert starvation.control_reading(DROP, left, recovered) == expected


def test_control_reading_needs_a_drop_and_enough_seeds():
    assert starvation.control_reading(summary(-0.01, 0.2), summary(-0.01, 0.01), summary(0.1, 0.2)).startswith(
        "not testable (no drop to explain: D = "
    )
    assert starvation.control_reading(summary(0.1, 0.2, n=2), summary(-0.01, 0.01), summary(0.1, 0.2)) == "too few seeds"
    nan = dict(n=3, mean=0.1, sd=math.nan, low=math.nan, high=math.nan)
    assert starvation.control_reading(nan, summary(-0.01, 0.01), summary(0.1, 0.2)).startswith("not testable")


@pytest.mark.parametrize(
    "drop, expected",
    [
        (summary(0.001, 0.2), "drop"),
        (summary(-0.049, 0.049), "no drop"),
        (summary(-0.049, 0.051), "inconclusive"),
        (summary(0.01, 0.2, n=2), "too few seeds"),
    ],
)
def test_drop_reading_each_way(drop, expected):
    assert starvation.drop_reading(drop) == expected


def write_student(output, seed, variant, repeat, env_a, env_b):
    folder = output / f"seed_{seed}" / f"distill_{starvation.job_name(variant, repeat)}"
    folder.mkdir(parents=True)
    rows = []
    for timesteps, scale in ((20_000, 0.5), (25_000, 1.0), (30_000, 1.0)):  # the last two are the score
        rows += [dict(timesteps=timesteps, env="Env-A", mean_reward=env_a * scale, std_reward=0.0),
                 dict(timesteps=timesteps, env="Env-B", mean_reward=env_b * scale, std_reward=0.0)]  # fmt: skip
    pd.DataFrame(rows).to_csv(folder / "eval.csv", index=False)
    about = dict(buffer_seed=seed, student_seed=seed + 1000 * repeat, variant=variant, repeat=repeat)
    (folder / "done.json").write_text(json.dumps(about))


def test_report_reads_starvation_from_a_written_tree(tmp_path):
    output, results = tmp_path / "runs", tmp_path / "results"
    # the dose drops 20 % on every seed, both matched ways get it back (within 1 %): starvation
    reference = {10: 2000.0, 13: 2400.0, 15: 1800.0}
    for seed, r5 in reference.items():
        wobble = {10: 0.0, 13: 0.01, 15: -0.01}[seed]
        for repeat, noise in ((0, 10.0), (1, -10.0)):
            write_student(output, seed, starvation.REFERENCE, repeat, r5 + noise, 3000.0)
            write_student(output, seed, starvation.DOSE, repeat, 0.8 * r5 + noise, 3100.0)
            write_student(output, seed, starvation.BATCH, repeat, (1 + wobble) * r5 + noise, 3200.0)
            write_student(output, seed, starvation.UPDATES, repeat, (1 - wobble) * r5 + noise, 3300.0)
    # a seed with only one student seed of one variant is not read
    write_student(output, 16, starvation.REFERENCE, 0, 1000.0, 1000.0)
    text = starvation.report(output, results)
    assert "Seeds with every variant and both student seeds: [10, 13, 15]" in text
    assert "S2 on this setting (the dose's Env-A drop D): **drop**" in text
    assert "matched by batch: **starvation**" in text and "matched by updates: **starvation**" in text
    assert "the answer for S2 (both ways must agree): **starvation**" in text
    table = pd.read_csv(results / "starvation.csv")
    assert len(table) == 3 * 4 * 2 * 2 + 2
    assert (results / "results.md").read_text() == text
    # the pooled within-buffer sd of the two student seeds (+-10 around the mean) is read apart from the buffers'
    assert "| S2_indicator_1to5 | Env-A | 14 | 306 |" in text


def test_report_reads_imbalance_and_refuses_an_empty_tree(tmp_path):
    output = tmp_path / "runs"
    for seed, r5 in {10: 2000.0, 11: 2200.0, 12: 2100.0, 13: 1900.0}.items():
        for repeat in (0, 1):
            write_student(output, seed, starvation.REFERENCE, repeat, r5, 3000.0)
            for variant in (starvation.DOSE, starvation.BATCH, starvation.UPDATES):
                write_student(output, seed, variant, repeat, 0.8 * r5 + (seed - 11) * 2.0, 3000.0)
    text = starvation.report(output, tmp_path / "results")
    assert "matched by batch: **imbalance**" in text and "matched by updates: **imbalance**" in text
    assert "the answer for S2 (both ways must agree): **imbalance**" in text
    with pytest.raises(FileNotFoundError, match="no finished student"):
        starvation.report(tmp_path / "nothing", tmp_path / "results")


@pytest.mark.parametrize(
    "readings, expected",
    [
        ({"batch": "starvation", "updates": "starvation"}, "starvation"),
        ({"batch": "imbalance", "updates": "imbalance"}, "imbalance"),
        ({"batch": "too few seeds", "updates": "too few seeds"}, "too few seeds"),
        ({"batch": "both", "updates": "starvation"}, "by batch: both; by updates: starvation"),
        ({"batch": "inconclusive", "updates": "inconclusive"}, "inconclusive"),
        ({"batch": "imbalance", "updates": "starvation"}, "by batch: imbalance; by updates: starvation"),
    ],
)
def test_the_answer_needs_both_ways_to_agree(readings, expected):
    assert starvation.answer(readings) == expected

"""Benchmark scripts that read studies: their verdicts, intervals and merges."""

import dataclasses
import json

import numpy as np
import pandas as pd
import pytest
from testkit import benchmark_module

from sb3_lifelong import LifelongReplayBuffer
from sb3_lifelong.experiments import PRESETS, load_study, run_seed, write_report


def test_seeds_needed_is_the_paired_t_test():
    needed = benchmark_module("seeds_needed")
    # G*Power's one-sided paired t-test, level 0.05, power 0.8: 8 pairs for an effect of 1 sd, 27 for half an sd
    assert needed.seeds_for(100.0, 100.0) == 8 and needed.seeds_for(2.0, 1.0) == 27
    assert needed.seeds_for(1.0, 2.0) == 4  # the normal approximation said 2
    assert needed.power(8, 1.0) >= 0.8 > needed.power(7, 1.0)
    assert needed.seeds_for(1.0, 0.0) == np.inf and needed.seeds_for(0.0, 1.0) == 2


def test_student_spread_on_one_buffer(study, tmp_path):
    """benchmarks/studies/student_spread/student_spread.py: the same students, several seeds, one buffer; the spread
    against the study's."""
    spread = benchmark_module("student_spread")
    output, _ = study
    write_report(output, plots=False)  # the study's scores.csv: the between-seed reference
    runs = tmp_path / "spread"
    students = ["CRR_exp_beta1", "CRR_indicator"]
    spread.train(output, "tiny", 0, students, [0, 5], runs)
    data = spread.scores(runs)
    assert len(data) == 4 and set(data["student_seed"]) == {0, 5} and set(data["buffer_seed"]) == {0}
    # student seed 0 on buffer 0 is the study's own student: same data, same seed, same scores
    own = load_study(output).score("CRR_exp_beta1", "Env-A")[0]
    mine = data[(data["student"] == "CRR_exp_beta1") & (data["student_seed"] == 0)]["score"].iloc[0]
    assert mine == own  # the evaluations are seeded
    text = spread.report(runs, output)
    assert "CRR_exp_beta1 - CRR_indicator" in text
    ratio = float(text.split("ratio ")[1].split(":")[0])

    # by hand: the sd over student seeds of (exp - indicator) on buffer 0, over the sd of the same difference across
    # the study's seeds (its scores.csv, Env-A)
    def pick(frame, student):
        return frame[frame["student"] == student].set_index("student_seed")["score"].sort_index()

    within = np.std((pick(data, "CRR_exp_beta1") - pick(data, "CRR_indicator")).to_numpy(), ddof=1)
    finals = pd.read_csv(output / "scores.csv")
    finals = finals[finals["env"] == "Env-A"].pivot_table(index="seed", columns="method", values="score")
    across = np.std((finals["CRR_exp_beta1"] - finals["CRR_indicator"]).to_numpy(), ddof=1)
    assert ratio == pytest.approx(within / across, abs=0.005)  # printed with 2 decimals
    reverse = spread.report(runs, output, pair=("CRR_indicator", "CRR_exp_beta1"))  # the pair names the order
    assert "CRR_indicator - CRR_exp_beta1" in reverse and float(reverse.split("ratio ")[1].split(":")[0]) == ratio
    one_seed = tmp_path / "one_seed"  # a reference study of one seed has no between-seed spread: a clear error
    one_seed.mkdir()
    finals = pd.read_csv(output / "scores.csv")
    finals[finals["seed"] == 0].to_csv(one_seed / "scores.csv", index=False)
    with pytest.raises(ValueError, match=r"at least 2 seeds.*found 1 seed"):
        spread.report(runs, one_seed)
    with pytest.raises(FileNotFoundError, match="finished seed's buffer"):
        spread.train(output, "tiny", 7, students, [0], runs)


def test_bounded_critic_diagnostic(study, tmp_path):
    """benchmarks/studies/paper_cpu_three/bounded_critic.py: the study's CRR students with a categorical critic on
    the data's bounds."""
    from sb3_lifelong import CRR
    from sb3_lifelong.experiments.jobs import value_support

    bounded = benchmark_module("bounded_critic")
    output, _ = study
    name, preset = bounded.study_preset(output)
    assert name == "tiny"
    crr = bounded.crr_students(preset)
    assert "CRR_exp_beta1" in crr and "BC" not in crr
    runs = tmp_path / "c51"
    bounded.train(output, 0, runs)
    run_dir = runs / "seed_0"
    with LifelongReplayBuffer.open(run_dir / "buffer", read_only=True) as buffer:
        support = value_support(buffer.reward_range(), 0.99)
    model = CRR.load(run_dir / "distill_CRR_exp_beta1" / "student.zip")
    critic = model.critic
    assert critic.v_min == pytest.approx(support["v_min"]) and critic.v_max == pytest.approx(support["v_max"])
    done = json.loads((run_dir / "distill_CRR_exp_beta1" / "done.json").read_text())
    assert done["settings"]["kwargs"]["policy_kwargs"] == {"distributional_critic": True} and done["buffer_seed"] == 0
    assert (run_dir / "collect").is_symlink() and (run_dir / "distill_BC").is_symlink()  # the study's own
    text = bounded.report(output, runs, tmp_path / "export")
    table = pd.read_csv(runs / "comparison.csv")
    assert set(table["critic"]) == {"MSE", "categorical"} and set(table["seed"]) == {0}
    categorical = table[table["critic"] == "categorical"]
    assert (categorical["q_final_max"] <= categorical["q_bound"] + 1e-3).all()  # the support bounds every Q
    assert "categorical" in text and (tmp_path / "export" / "claims.csv").exists()
    assert load_study(runs).seeds == [0]
    with pytest.raises(FileNotFoundError, match="finished seed's buffer"):
        bounded.train(output, 7, runs)


def test_repeat_spread_reads_a_study_with_repeats(study, tmp_path):
    """benchmarks/studies/student_spread/repeat_spread.py: per-seed spread over repeats, and repeat 0 against the
    study without repeats."""

    spread = benchmark_module("repeat_spread")
    source, _ = study
    preset = dataclasses.replace(PRESETS["tiny"], students=("CRR_exp_beta1", "CRR_indicator"), online=False, student_repeats=2)
    output = tmp_path / "repeats"
    for seed in (0, 1):
        run_seed(preset, seed, output, log=lambda line: None, collection_from=source)
    data = spread.repeat_scores(output)
    assert len(data) == 2 * 2 * 2 * 2  # seeds x students x repeats x environments
    per_seed, summary = spread.spread(data)
    assert summary["seeds"] == 2 and summary["repeats"] == 2
    for seed in (0, 1):
        a = data[(data.seed == seed) & (data.env == "Env-A") & (data.student == "CRR_indicator")].set_index("repeat")
        b = data[(data.seed == seed) & (data.env == "Env-A") & (data.student == "CRR_exp_beta1")].set_index("repeat")
        assert per_seed.loc[seed, "list"] == pytest.approx(list(a["score"] - b["score"]))
    means = [np.mean(per_seed.loc[seed, "list"]) for seed in (0, 1)]
    assert summary["between"] == pytest.approx(abs(means[0] - means[1]) / np.sqrt(2))  # the sd of two values
    assert summary["within"] == pytest.approx(np.mean([abs(a - b) / np.sqrt(2) for a, b in per_seed["list"]]))
    envs = ["Env-A", "Env-B"]
    theirs = spread.reference_scores(source, envs)
    table = spread.reproduction(data, theirs)  # the fixture trained the same students with the same seeds
    assert len(table) == 2 * 2 * 2 and (table["difference"] == 0).all()
    text = spread.report(output, source, spread.PAIR, "Env-A")
    assert "largest absolute difference 0.0" in text
    # the same reference as a table of scores: one column per environment, with rows of another run to filter out
    wide = theirs.pivot_table(index=["seed", "student"], columns="env", values="score").reset_index()
    other = wide.assign(critic="MSE", **{env: wide[env] + 100.0 for env in envs})
    table_path = tmp_path / "comparison.csv"
    pd.concat([wide.assign(critic="categorical"), other]).to_csv(table_path, index=False)
    text = spread.report(output, table_path, spread.PAIR, "Env-A", where={"critic": "categorical"})
    assert "largest absolute difference 0.0" in text and "rows with critic = categorical" in text
    shifted = spread.reproduction(data, spread.reference_scores(table_path, envs, where={"critic": "MSE"}))
    assert len(shifted) == 8 and np.allclose(shifted["difference"], -100.0)
    long_path = tmp_path / "long.csv"
    theirs.to_csv(long_path, index=False)
    assert (spread.reproduction(data, spread.reference_scores(long_path, envs))["difference"] == 0).all()
    with pytest.raises(ValueError, match="more than one score"):
        spread.reference_scores(table_path, envs)
    with pytest.raises(ValueError, match="no column 'critc'"):
        spread.reference_scores(table_path, envs, where={"critc": "MSE"})
    with pytest.raises(ValueError, match="study directory"):
        spread.reference_scores(source, envs, where={"critic": "MSE"})
    with pytest.raises(ValueError, match="no finished"):
        spread.spread(data, pair=("BC", "CRR_exp_beta1"))


def test_crr_train_dtype_return_verdict() -> None:
    """benchmarks/studies/crr_train_dtype_return/crr_train_dtype_return.py: its pre-registered rule, pass / fail /
    not testable, paired by seed."""
    check = benchmark_module("crr_train_dtype_return")

    def rows(base: list[float], other: list[float]) -> list[dict]:
        pairs = [("float32", base), ("simulated_bfloat16", other)]
        return [
            {"dtype": dtype, "seed": seed, "return": value} for dtype, values in pairs for seed, value in enumerate(values)
        ]

    base = [240.0, 260.0, 250.0, 230.0, 270.0]  # a spread of 15.8 across seeds
    close = check.verdict(rows(base, [241.0, 258.0, 251.0, 229.0, 272.0]), "simulated_bfloat16", 71.0)
    assert close["verdict"] == "pass" and close["seeds"] == [0, 1, 2, 3, 4]
    assert close["difference_mean"] == pytest.approx(0.2) and close["difference_ci95"][0] < 0 < close["difference_ci95"][1]
    lower = check.verdict(rows(base, [value - 30.0 + seed for seed, value in enumerate(base)]), "simulated_bfloat16", 71.0)
    assert lower["verdict"] == "fail" and lower["difference_ci95"][1] < 0  # consistently 28 lower: not kept
    unlearnt = check.verdict(rows([60.0, 65.0, 70.0], [61.0, 64.0, 70.0]), "simulated_bfloat16", 71.0)
    assert unlearnt["verdict"] == "not testable" and not unlearnt["precondition_float32_above_data"]
    partial = check.verdict(rows(base, base[:3]), "simulated_bfloat16", 71.0)
    assert partial["seeds"] == [0, 1, 2]  # only the seeds run with both settings are paired
    assert check.verdict(rows(base, base[:1]), "simulated_bfloat16", 71.0)["verdict"] == "too few seeds"
    # each condition alone fails: a small but consistent difference (the interval excludes 0, within the spread) ...
    steady = check.verdict(
        rows(base, [value - 5.0 + 0.1 * seed for seed, value in enumerate(base)]), "simulated_bfloat16", 71.0
    )
    assert steady["verdict"] == "fail" and steady["difference_ci95"][1] < 0 < steady["float32_std"] - 5.0
    # ... and a noisy one whose interval contains 0 but whose mean is beyond the spread, which the stricter reading flags
    noisy = check.verdict(
        rows(base, [value + shift for value, shift in zip(base, [60, -20, 70, -10, 0])]), "simulated_bfloat16", 71.0
    )
    assert noisy["verdict"] == "fail" and noisy["difference_ci95"][0] < 0 < noisy["difference_ci95"][1]
    assert noisy["difference_mean"] > noisy["float32_std"] and not noisy["interval_within_spread"]
    assert close["interval_within_spread"]


def test_crr_train_dtype_return_merges_seeds_run_apart() -> None:
    """crr_train_dtype_return.py --merge: seeds run as separate commands give the verdict of one run over them all,
    and parts that do not belong together are refused by name."""
    check = benchmark_module("crr_train_dtype_return")

    def part(seeds: list[int], machine: str = "cpu A", updates: int = 5000) -> dict:
        runs = [
            {"dtype": dtype, "seed": seed, "return": 240.0 + 7.0 * seed + (1.5 if dtype == "bfloat16" else 0.0)}
            for seed in seeds
            for dtype in ("float32", "bfloat16")
        ]
        return {"machine": machine, "command": f"--seeds {seeds}", "updates": updates, "eval_episodes": 10, "runs": runs}

    rows, machine, command, updates, episodes = check.merged([part([0, 1]), part([2]), part([3, 4])])
    assert (machine, updates, episodes) == ("cpu A", 5000, 10) and command.count(";") == 2
    assert check.verdict(rows, "bfloat16", 71.0) == check.verdict(part([0, 1, 2, 3, 4])["runs"], "bfloat16", 71.0)
    assert check.verdict(rows, "bfloat16", 71.0)["seeds"] == [0, 1, 2, 3, 4]
    with pytest.raises(SystemExit, match="differ in machine"):
        check.merged([part([0]), part([1], machine="cpu B")])
    with pytest.raises(SystemExit, match="differ in machine, updates"):
        check.merged([part([0]), part([1], updates=3000)])
    with pytest.raises(SystemExit, match="appears twice"):
        check.merged([part([0, 1]), part([1, 2])])


def test_mpo_quality_paired_verdict(tmp_path, monkeypatch) -> None:
    """benchmarks/studies/mpo_quality/bench_mpo_quality.py: the rule pre-registered for bf16 gradient passes, pass /
    fail / inconclusive."""
    quality = benchmark_module("bench_mpo_quality")
    base = {0: 1000.0, 1: 1400.0, 2: 1200.0, 3: 800.0, 4: 1600.0}  # a spread of 316 across seeds
    close = quality.paired_verdict(base, {seed: value + (-1) ** seed * 30.0 for seed, value in base.items()})
    assert close["verdict"] == "pass" and close["seeds"] == [0, 1, 2, 3, 4]
    assert -close["base_std"] <= close["difference_ci95"][0] < 0 < close["difference_ci95"][1] <= close["base_std"]
    lower = quality.paired_verdict(base, {seed: value - 500.0 + 10 * seed for seed, value in base.items()})
    assert lower["verdict"] == "fail" and lower["difference_ci95"][1] < 0  # consistently lower, beyond the spread
    steady = quality.paired_verdict(base, {seed: value - 200.0 + 10 * seed for seed, value in base.items()})
    assert steady["verdict"] == "within the spread, a difference shown"  # consistently lower, within the spread
    noisy = quality.paired_verdict(base, {seed: value + (-1) ** seed * 600.0 for seed, value in base.items()})
    assert noisy["verdict"] == "inconclusive" and noisy["difference_ci95"][0] < -noisy["base_std"]
    assert quality.paired_verdict(base, {0: 1000.0, 7: 1.0})["verdict"] == "too few seeds"  # one seed in common
    assert quality.paired_verdict(base, {0: 990.0, 1: 1410.0, 9: 0.0})["seeds"] == [0, 1]  # only the common seeds
    assert quality.paired_verdict(base, {0: float("nan"), 1: 1400.0})["verdict"] == "non-finite return"
    # read from the curves: only runs that reached the budget, the base and the other each from their own files
    monkeypatch.setattr(quality, "CURVES", tmp_path)
    (tmp_path / "100k").mkdir()
    header = "timesteps,mean_return,std_return,wall_s,policy_std_p10,policy_std_median,policy_std_p90\n"
    for algo, seed, rows in (("A", 0, [(50000, 5.0), (100000, 10.0)]), ("A", 1, [(100000, 20.0)]), ("A", 2, [(50000, 1.0)])):
        text = header + "".join(f"{steps},{value},0,0,0,0,0\n" for steps, value in rows)
        (tmp_path / "100k" / f"Hopper-v5__{algo}__s{seed}.csv").write_text(text)
        (tmp_path / "100k" / f"Hopper-v5__B__s{seed}.csv").write_text(text.replace(f",{rows[-1][1]},", f",{rows[-1][1] + 1},"))
    assert quality.final_returns("Hopper-v5", "A") == {0: 10.0, 1: 20.0}  # seed 2 stopped at 50k
    result = quality.report_pair(["Hopper-v5"], "A", "B")["Hopper-v5"]
    assert result["seeds"] == [0, 1] and result["difference_mean"] == pytest.approx(1.0)
    assert (tmp_path / "paired_A_B.json").exists()
    with pytest.raises(ValueError, match="two different variants"):
        quality.report_pair(["Hopper-v5"], "A", "A")


@pytest.mark.parametrize("preset", ["cpu", "paper"])
def test_device_benchmark_shapes_are_the_presets_robots(preset) -> None:
    # the device benchmark times random data shaped like each preset's robot: the shapes must stay the envs' own
    from sb3_lifelong.envs import stage_envs
    from sb3_lifelong.experiments.presets import PRESETS

    bench = benchmark_module("bench_device_presets")
    settings = PRESETS[preset]
    try:
        envs = stage_envs(settings.env_id, list(settings.stages), settings.env_names, settings.env_kwargs, append_params=True)
    except (ImportError, RuntimeError) as error:  # the OP3 model comes from mujoco-menagerie
        pytest.skip(f"{settings.env_id} not available (mujoco-menagerie, or MENAGERIE_ROOT set to a local copy): {error}")
    env = next(iter(envs.values()))
    assert (env.observation_space.shape[0], env.action_space.shape[0]) == bench.SHAPES[preset]
    random_env = bench.RandomBoxEnv(*bench.SHAPES[preset], episode=3)
    obs, _ = random_env.reset(seed=0)
    assert obs.shape == env.observation_space.shape and random_env.step(random_env.action_space.sample())[3] is False

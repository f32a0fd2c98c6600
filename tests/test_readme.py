"""The README's snippet runs as written (at a tiny budget: only its step counts are changed) and shows what happens."""

import csv
import os
import pathlib
import re

import pytest

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"
#: the snippet's budgets (steps, updates, evaluation periods) and the tiny ones the test runs it with
TINY_BUDGET = {"200_000": "300", "1_000_000": "300", "500_000": "200", "20_000": "300", "50_000": "200"}


def readme_snippet() -> str:
    text = README.read_text()
    section = text[text.index("## The user's day") :]
    return re.search(r"```python\n(.*?)```", section, re.DOTALL).group(1)


def scalar_tags(directory: pathlib.Path) -> set[str]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    accumulator = EventAccumulator(str(directory))
    accumulator.Reload()
    return set(accumulator.Tags()["scalars"])


def test_users_day_snippet_runs(tmp_path, monkeypatch, capsys):
    pytest.importorskip("tensorboard")
    code = readme_snippet()
    for big, small in TINY_BUDGET.items():
        assert big in code, f"the snippet no longer says {big}: update TINY_BUDGET"
        code = code.replace(big, small)
    monkeypatch.chdir(tmp_path)
    namespace: dict = {}
    exec(compile(code, str(README), "exec"), namespace)
    assert namespace["model"].num_timesteps == 600
    assert namespace["action"].shape == namespace["env"].action_space.shape
    assert (tmp_path / "distilled.zip").exists() and (tmp_path / "runs" / "buffer" / "manifest.json").exists()
    assert set(namespace["model"].replay_buffer.source_counts(by_name=True)) == {"Env-A", "Env-B"}  # both lived in

    # it shows what happens: every evaluation printed, on every environment seen, online and while distilling
    out = capsys.readouterr().out
    for step in (300, 600):  # at the end of each stage: one line per evaluation, both environments on it
        assert re.search(rf"^Eval at {step}: mean reward Env-A .*, Env-B .*; mean over environments", out, re.M)
    assert "Distilling 600 transitions (Env-A: " in out and "into CRR: 200 gradient updates" in out
    assert re.search(r"^Eval at 200: mean reward Env-A .*, Env-B ", out, re.M)  # the student's last evaluation
    assert len(out.splitlines()) < 20, f"verbose=1 prints about one line per evaluation, got:\n{out}"  # no SB3 tables
    with open(tmp_path / "runs" / "eval.csv") as handle:
        assert {row["env"] for row in csv.DictReader(handle)} == {"Env-A", "Env-B"}

    # and tensorboard has the curves per environment: collection (both stages, one run) and the student beside it
    run = tmp_path / "runs" / "lifelong_1"
    assert os.listdir(tmp_path / "runs") and run.is_dir()
    online, student = scalar_tags(run), scalar_tags(run / "distill")
    for tags in (online, student):
        for env in ("Env-A", "Env-B"):
            assert {f"eval/{env}/mean_reward", f"eval/{env}/std_reward", f"eval/{env}/mean_ep_length"} <= tags
    assert {"diagnostics/q_mean/Env-A", "diagnostics/q_mean/Env-B"} <= online  # one name per environment


def test_users_day_states_how_long_its_budget_takes():
    """The time stated under the snippet is the time of the snippet's budget (change both together)."""
    code, text = readme_snippet(), README.read_text()
    steps = [int(n.replace("_", "")) for n in re.findall(r"model\.learn\(([\d_]+)", code)]
    updates = int(re.search(r"total_updates=([\d_]+)", code).group(1).replace("_", ""))
    stated = re.search(r"\*\*How long it takes\.\*\* This budget \(([\d,]+) environment steps, ([\d,]+) updates\)", text)
    assert stated, "the README says how long the user's day takes, right after the snippet"
    assert (int(stated.group(1).replace(",", "")), int(stated.group(2).replace(",", ""))) == (sum(steps), updates)

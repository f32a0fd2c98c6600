"""The README's snippet runs as written (at a tiny budget: only its step counts are changed)."""

import os
import pathlib
import re

README = pathlib.Path(__file__).resolve().parents[1] / "README.md"
TINY_BUDGET = {"200_000": "300", "1_000_000": "300", "500_000": "200"}


def readme_snippet() -> str:
    text = README.read_text()
    section = text[text.index("## The user's day") :]
    return re.search(r"```python\n(.*?)```", section, re.DOTALL).group(1)


def test_users_day_snippet_runs(tmp_path, monkeypatch):
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
    assert os.listdir(tmp_path / "runs")  # tensorboard logs

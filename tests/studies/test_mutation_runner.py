"""benchmarks/mutation/run_mutation.py: the mutants it lists, one change each, its scopes, outcomes and summary."""

import os
import pathlib

import pytest
from testkit import benchmark_module

SOURCE = '''
"""A docstring: 0 < 1 is not mutated."""


def f(x: int = 0, y: Literal[7] = 7) -> float:
    """neither is this one: a + b"""
    if x < 1 and not y >= 2:
        return -x + y * 2
    z = min(x, y)
    z += 1
    return z.detach() if x == 0 else z.mean()
'''


def test_one_mutation_per_mutant_and_none_in_docstrings_or_annotations(tmp_path: pathlib.Path):
    runner = benchmark_module("run_mutation")
    (tmp_path / "module.py").write_text(SOURCE)
    mutants = runner.list_mutants("module.py", root=tmp_path)
    operators = [m.operator for m in mutants]
    for expected in (
        "compare Lt -> LtE",
        "compare GtE -> Gt",
        "compare Eq -> NotEq",
        "boolean And swapped",
        "drop unary Not",
        "drop unary USub",
        "arithmetic Add -> Sub",
        "drop the right term",
        "drop the left term",
        "arithmetic Mult -> Div",
        "call min -> max",
        "augmented += <-> -=",
        "drop .detach()",
        "call mean -> sum",
        "constant 1 -> 0",
        "constant 0 -> 1",
        "constant 2 -> 3",
    ):
        assert expected in operators, expected
    assert all(m.line >= 5 for m in mutants)  # nothing in the module's docstring
    # the default 7 is mutated, the 7 of its annotation is not
    assert [m.operator for m in mutants if m.line == 5 and m.original == "7"] == ["constant 7 -> 8"]
    assert [m.index for m in mutants] == list(range(len(mutants))) and [m.line for m in mutants] == sorted(
        m.line for m in mutants
    )
    unchanged = runner.ast.unparse(runner.ast.parse(SOURCE)).splitlines()
    for mutant in mutants:
        compile(mutant.source, "mutant.py", "exec")
        lines = mutant.source.splitlines()
        assert len(lines) == len(unchanged) and sum(a != b for a, b in zip(lines, unchanged)) == 1, mutant.operator


def test_summary_counts_timeouts_as_killed_and_errors_apart():
    runner = benchmark_module("run_mutation")
    outcomes = [
        runner.Outcome("m.py", i, 1, "op", "a", "b", outcome, 1.0, "")
        for i, outcome in enumerate(["killed", "killed", "timeout", "survived", "error"])
    ]
    (row,) = runner.summarise(outcomes)
    assert (row["mutants"], row["killed"], row["survived"], row["errors"]) == (5, 3, 1, 1)
    assert row["kill_rate"] == 0.75


def test_scope_keeps_the_sites_of_the_named_functions_only(tmp_path: pathlib.Path):
    runner = benchmark_module("run_mutation")
    (tmp_path / "module.py").write_text(
        "class A:\n    def keep(self, x):\n        return x + 1\n\n    def other(self, x):\n        return x - 1\n\n\n"
        "def free(x):\n    return x * 2\n"
    )
    lines = {m.line for m in runner.list_mutants("module.py", root=tmp_path, scope=("A.keep", "free"))}
    assert lines == {3, 10}
    everything = {m.line for m in runner.list_mutants("module.py", root=tmp_path)}
    assert everything == {3, 6, 10}
    with pytest.raises(ValueError, match=r"A\.gone"):
        runner.list_mutants("module.py", root=tmp_path, scope=("A.gone",))
    # every scope the runner uses names functions that exist
    for module, scope in runner.SCOPES.items():
        tree = runner.ast.parse((runner.ROOT / module).read_text())
        assert len(runner._scope_lines(tree, scope)) == len(scope), module


def test_exit_codes_read_as_outcomes_and_results_round_trip(tmp_path: pathlib.Path):
    runner = benchmark_module("run_mutation")
    assert runner._classify(0, "3 passed", 1.0)[0] == "survived"
    assert runner._classify(1, "FAILED tests/x.py::t - boom\n1 failed", 1.0) == ("killed", 1.0, "FAILED tests/x.py::t - boom")
    assert runner._classify(2, "ImportError", 1.0)[0] == "killed"  # the mutant breaks an import
    assert runner._classify(3, "internal error", 1.0)[0] == "error"
    outcomes = [
        runner.Outcome("a.py", 0, 3, "op", "x + 1", "x - 1", "killed", 1.5, "FAILED"),
        runner.Outcome("b.py", 1, 9, "op", "a < b", "a <= b", "survived", 2.0, "1 passed"),
    ]
    runner.write_results(outcomes, tmp_path, "cmd", {"a.py": 1, "b.py": 4})
    assert runner.read_outcomes(tmp_path / "mutation.csv") == outcomes
    assert runner.read_outcomes(tmp_path / "mutation.csv", exclude=["a.py"]) == outcomes[1:]
    assert runner.read_outcomes(tmp_path / "absent.csv") == []


@pytest.mark.skipif(not hasattr(os, "fork"), reason="the forking runner needs os.fork")
def test_forked_run_refuses_a_package_imported_from_elsewhere(tmp_path: pathlib.Path):
    # this process has imported sb3_lifelong from the checkout: a child forked from it would test that, not the copy,
    # so it must end as an error (never as a kill or a survivor)
    import sb3_lifelong  # noqa: F401

    runner = benchmark_module("run_mutation")
    (tmp_path / "sb3_lifelong").mkdir()
    (tmp_path / "sb3_lifelong" / "__init__.py").write_text("")
    (tmp_path / "test_nothing.py").write_text("def test_nothing():\n    pass\n")
    child = runner.ForkedTests(tmp_path, ["test_nothing.py"], timeout=60)
    result = None
    while result is None:
        result = child.poll()
    assert result[0] == "error" and "not from the copy" in (tmp_path / "pytest.log").read_text()


def test_survivors_of_an_earlier_run_are_found_after_their_lines_moved(tmp_path: pathlib.Path):
    runner = benchmark_module("run_mutation")
    (tmp_path / "module.py").write_text("def f(x):\n    a = x + 0\n    return a + 0\n")
    before = runner.list_mutants("module.py", root=tmp_path)
    survived = {1}  # the second mutant only
    earlier = [
        runner.Outcome(
            "module.py", m.index, m.line, m.operator, m.original, m.mutated, "survived" if k in survived else "killed", 1.0, ""
        )
        for k, m in enumerate(before)
    ]
    (tmp_path / "module.py").write_text(
        'def f(x):\n    """A docstring moves every line down."""\n    a = x + 0\n    return a + 0\n'
    )
    after = runner.list_mutants("module.py", root=tmp_path)
    (chosen,) = runner.same_mutants(after, earlier)
    assert (chosen.operator, chosen.original, chosen.mutated) == (before[1].operator, before[1].original, before[1].mutated)
    assert chosen.line == before[1].line + 1
    # the same code twice: the occurrence decides (the "+ 0" of line 3 is not the one of line 2)
    assert [m.line for m in runner.same_mutants(after, earlier, outcome="killed")] == [
        m.line + 1 for m in before if m.index != 1
    ]


@pytest.mark.parametrize("tests", [None, ["tests/buffers"]])
def test_tests_option_replaces_the_targeted_files(monkeypatch, tmp_path: pathlib.Path, tests):
    runner = benchmark_module("run_mutation")
    module = "sb3_lifelong/common/losses.py"
    seen = []

    def run_forked(jobs, workers, timeout, scratch):
        for name, mutant, files in jobs:
            seen.append(files)
            yield name, mutant, ("survived", 0.1, "1 passed")

    monkeypatch.setattr(runner, "run_forked", run_forked)
    monkeypatch.setattr(runner, "preload", lambda: None)
    argv = ["--modules", module, "--limit", "1", "--runner", "fork", "--output", str(tmp_path)]
    assert runner.main(argv + (["--tests", *tests] if tests else [])) == 0
    assert seen == [tests or runner.MODULES[module]] * 2  # the baseline, then the one mutant
    assert ("--tests tests/buffers" in (tmp_path / "mutation.md").read_text()) == bool(tests)  # the command is recorded

"""benchmarks/mutation/run_mutation.py: the mutants it lists, one change each, and its summary (no test run here)."""

import pathlib

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

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
    argv = ["--modules", module, "--limit", "1", "--runner", "fork", "--select", "all", "--output", str(tmp_path)]
    assert runner.main(argv + (["--tests", *tests] if tests else [])) == 0
    assert seen == [tests or runner.MODULES[module]] * 2  # the baseline, then the one mutant
    assert ("--tests tests/buffers" in (tmp_path / "mutation.md").read_text()) == bool(tests)  # the command is recorded


COVERED_MODULE = """X = 1


def f(a):
    if (a >
            2):
        return a + X
    return a


def g(a):
    return f(a) * 2


def never(a):
    return a - 1


def closed(a):
    return a + 100
"""

COVERED_TESTS = """import subprocess
import sys

import pytest

import mod


@pytest.fixture(scope="module")
def big():
    return mod.g(5)


@pytest.fixture(scope="module")
def resource():
    yield 1
    mod.closed(1)  # its teardown runs after the module's last test, which does not use it


def test_uses_the_resource(resource):
    assert resource == 1


def test_f():
    assert mod.f(1) == 1


@pytest.mark.parametrize("v", [3, 4])
def test_g(v, big):
    assert mod.g(v) == 2 * (v + 1) and big == 12


def test_starts_a_process():
    subprocess.run([sys.executable, "-c", "pass"], check=True)


def test_shares_the_fixture(big):
    assert big == 12
"""


def _coverage_map_elsewhere(runner, copy_root: pathlib.Path, tests: list):
    """coverage_map in a new Python process: this one has imported sb3_lifelong, which a forked child would inherit"""
    import json
    import subprocess
    import sys

    script = (
        "import dataclasses, json, pathlib, sys\n"
        f"sys.path.insert(0, {str(pathlib.Path(runner.__file__).parent)!r})\n"
        "import run_mutation as r\n"
        f"result, where = r.coverage_map(pathlib.Path({str(copy_root)!r}), 'mod.py', {tests!r}, 120)\n"
        "print(json.dumps([result, None if where is None else dataclasses.asdict(where)]))\n"
    )
    done = subprocess.run([sys.executable, "-c", script], cwd=copy_root, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    result, where = json.loads(done.stdout.splitlines()[-1])
    if where is not None:
        where["lines"] = {int(line): contexts for line, contexts in where["lines"].items()}
        where = runner.CoverageMap(**where)
    return tuple(result), where


@pytest.mark.skipif(not hasattr(os, "fork"), reason="the coverage map runs the tests in a forked child")
def test_covering_selection_runs_the_tests_that_run_a_statement(tmp_path: pathlib.Path):
    runner = benchmark_module("run_mutation")
    (tmp_path / "sb3_lifelong").mkdir()  # the child checks that it imports the package from the copy
    (tmp_path / "sb3_lifelong" / "__init__.py").write_text("")
    (tmp_path / "mod.py").write_text(COVERED_MODULE)
    (tmp_path / "tests").mkdir()
    (tmp_path / "tests" / "test_mod.py").write_text(COVERED_TESTS)
    result, where = _coverage_map_elsewhere(runner, tmp_path, ["tests"])
    assert result[0] == "survived" and where is not None, (tmp_path / "pytest.log").read_text()
    names = [test.rsplit("::", 1)[1] for test in where.order]
    assert names == [
        "test_uses_the_resource",
        "test_f",
        "test_g[3]",
        "test_g[4]",
        "test_starts_a_process",
        "test_shares_the_fixture",
    ]
    tree = runner.ast.parse(COVERED_MODULE)

    def chosen(line: int):
        tests = where.tests_for(*runner.statement_lines(tree, line))
        return None if tests is None else [test.rsplit("::", 1)[1] for test in tests]

    # a statement only g's callers run: the module fixture's users (it called g first), then the tests that start a
    # process (what the process runs is not measured), never test_f
    assert chosen(7) == ["test_g[3]", "test_g[4]", "test_shares_the_fixture", "test_starts_a_process"]
    # the second line of a two-line if: the whole header, which test_f runs too
    assert runner.statement_lines(tree, 6) == (5, 6) and runner.statement_lines(tree, 7) == (7, 7)
    assert chosen(6) == ["test_f", "test_g[3]", "test_g[4]", "test_shares_the_fixture", "test_starts_a_process"]
    assert chosen(8) == ["test_f", "test_starts_a_process"]
    # a shared fixture's teardown is its users' (it ran after the last test, which does not use it)
    assert chosen(20) == ["test_uses_the_resource", "test_starts_a_process"]
    # the tests that start processes come last, whatever their place in the file
    where.order.insert(0, where.order.pop(4))
    assert chosen(8) == ["test_f", "test_starts_a_process"]
    # at import (a constant, a def line), or in no test: every test runs
    assert chosen(1) is None and chosen(4) is None and chosen(16) is None
    assert runner.statement_lines(tree, 4) == (4, 4)
    mutant = runner.Mutant("mod.py", 0, 16, "op", "a - 1", "a + 1", "")
    assert runner.chosen_tests(mutant, ["tests"], where, tree) == ["tests"]
    assert runner.chosen_tests(mutant, ["tests"], None, tree) == ["tests"]


@pytest.mark.skipif(not hasattr(os, "fork"), reason="the coverage map runs the tests in a forked child")
def test_a_failing_baseline_gives_no_coverage_map(tmp_path: pathlib.Path):
    runner = benchmark_module("run_mutation")
    (tmp_path / "sb3_lifelong").mkdir()
    (tmp_path / "sb3_lifelong" / "__init__.py").write_text("")
    (tmp_path / "mod.py").write_text(COVERED_MODULE)
    (tmp_path / "test_mod.py").write_text("import mod\n\n\ndef test_f():\n    assert mod.f(1) == 2\n")
    result, where = _coverage_map_elsewhere(runner, tmp_path, ["test_mod.py"])
    assert result[0] == "killed" and where is None


@pytest.mark.skipif(not pathlib.Path("/proc/self/stat").exists(), reason="CPU seconds of a process are read from /proc")
def test_a_timeout_counts_cpu_seconds_and_a_run_without_cpu_stops_at_the_wall_limit():
    runner = benchmark_module("run_mutation")
    sleeper = runner.subprocess.Popen([runner.sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        import time

        time.sleep(0.5)
        cpu = runner.cpu_seconds(sleeper.pid)
        assert cpu is not None and cpu < 0.5  # asleep: no CPU, whatever the wall clock says
        assert runner.overdue(sleeper.pid, seconds=10.0, timeout=1.0) is None  # slow beside other jobs: not a hang
        late = runner.overdue(sleeper.pid, seconds=runner.WALL_FACTOR * 1.0 + 1, timeout=1.0)
        assert late is not None and "of CPU" in late  # no CPU for 30 times its timeout: a deadlock, stopped
    finally:
        sleeper.kill()
        sleeper.wait()
    busy = runner.subprocess.Popen([runner.sys.executable, "-c", "while True: pass"])
    try:
        deadline = time.perf_counter() + 60
        while (runner.cpu_seconds(busy.pid) or 0.0) < 0.3 and time.perf_counter() < deadline:
            time.sleep(0.05)
        assert runner.overdue(busy.pid, seconds=0.5, timeout=0.2) == "over 0.2 s of CPU"
    finally:
        busy.kill()
        busy.wait()
    # a group's leader counts the processes of its group while they run; stop() ends them with it
    script = "import subprocess, sys, time; subprocess.Popen([sys.executable, '-c', 'while True: pass']); time.sleep(60)"
    leader = runner.subprocess.Popen([runner.sys.executable, "-c", script], start_new_session=True)
    try:
        deadline = time.perf_counter() + 60
        while (runner.cpu_seconds(leader.pid) or 0.0) < 0.3 and time.perf_counter() < deadline:
            time.sleep(0.05)
        own = runner._stat(leader.pid)
        assert sum(int(v) for v in own[11:15]) / os.sysconf("SC_CLK_TCK") < 0.2  # the leader itself sleeps
        assert runner.cpu_seconds(leader.pid) >= 0.3
    finally:
        runner.stop(leader.pid)

    def alive() -> list:  # the group's processes that still run (a killed one may stay a zombie until it is reaped)
        stats = [runner._stat(entry) for entry in os.listdir("/proc") if entry.isdigit()]
        return [fields for fields in stats if fields and fields[2] == str(leader.pid) and fields[0] != "Z"]

    deadline = time.perf_counter() + 10
    while alive() and time.perf_counter() < deadline:
        time.sleep(0.05)
    assert not alive()
    assert runner.cpu_seconds(2**22 + 12345) is None  # no such process: the wall clock decides
    assert runner.overdue(2**22 + 12345, seconds=2.0, timeout=1.0) == "over 1 s"


def test_a_kill_by_a_part_that_fails_unmutated_is_withdrawn(monkeypatch, tmp_path: pathlib.Path):
    runner = benchmark_module("run_mutation")
    mutants = [runner.Mutant("m.py", k, k + 1, "op", "a", "b", "") for k in range(4)]
    jobs = [("mutant_0", mutants[0], ["t::a"]), ("mutant_1", mutants[1], ["t::b", "t::c"]),
            ("mutant_2", mutants[2], ["t"]), ("mutant_3", mutants[3], ["t::b", "t::c"])]  # fmt: skip
    outcomes = [
        runner.outcome_of(m, (result, 1.0, "FAILED")) for m, result in zip(mutants, ["killed", "killed", "killed", "survived"])
    ]
    ran = []

    def run_forked(runs, workers, timeout, scratch):
        for name, mutant, tests in runs:
            assert mutant is None  # unmutated
            ran.append(tests)
            yield name, None, ("killed" if tests == ["t::b", "t::c"] else "survived", 0.5, "FAILED t::c")

    monkeypatch.setattr(runner, "run_forked", run_forked)
    assert runner.verify_kills(outcomes, jobs, {"m.py": ["t"]}, 1, 60.0, tmp_path) == 1
    # one run per part that killed: not the whole set (mutant 2), not a survivor's part (mutant 3 shares mutant 1's)
    assert sorted(ran) == [["t::a"], ["t::b", "t::c"]]
    assert [o.outcome for o in outcomes] == ["killed", "error", "killed", "survived"]
    assert "2 chosen tests fail unmutated" in outcomes[1].detail


def test_lines_take_ranges_and_single_lines():
    runner = benchmark_module("run_mutation")
    _, ranges = runner.parse_arguments(["--lines", "17", "20-22", "--runner", "spawn"])
    assert ranges == [(17, 17), (20, 22)]

"""
Mutation testing as a measurement: how many plausible bugs planted in the losses, the policies' arithmetic and the
claim engine the targeted tests catch.

A small self-contained runner (no mutmut / cosmic-ray: their import hooks and caches do not fit an editable install
and a package under ``PYTHONPATH``). For each module it lists every mutation site of its source (:class:`Sites`):

- comparisons: ``<`` <-> ``<=``, ``>`` <-> ``>=``, ``==`` <-> ``!=``, ``is`` <-> ``is not``, ``in`` <-> ``not in``;
- arithmetic: ``+`` <-> ``-``, ``*`` <-> ``/``, ``**`` -> ``*``, and a sum or difference reduced to one of its terms
  (a term dropped);
- unary: ``-x`` -> ``x``, ``not x`` -> ``x``; boolean ``and`` <-> ``or``; ``+=`` <-> ``-=``;
- constants: ``0`` <-> ``1``, another number ``c`` -> ``c + 1``, ``True`` <-> ``False``;
- calls: ``min`` <-> ``max`` (builtins, methods, ``clamp_min`` / ``clamp_max``, ``amin`` / ``amax``), ``x.detach()``
  -> ``x`` (a gradient let through), ``mean`` <-> ``sum``.

Each mutant is the module with one site changed (``ast.unparse``), written into a private copy of the repository's
Python files (``sb3_lifelong/``, ``tests/``, ``benchmarks/**.py``, the configuration files); the module's targeted test
files then run there with ``PYTHONPATH`` at the copy (``pytest -x -q -p no:cacheprovider``). A failing run kills the
mutant, a passing one lets it survive, a run past ``--timeout`` counts as killed (a mutant that hangs is caught) and is
reported as such; with the forking runner the timeout counts CPU seconds (:func:`overdue`), so the runs may share the
cores with other jobs, even at a low priority. By default a mutant runs only the targeted tests that run its statement
(``--select covering``, :class:`CoverageMap`). Mutants run in parallel (``--workers``), one thread each.

Writes ``results/mutation.csv`` (one row per mutant: module, line, operator, original and mutated code, outcome,
seconds), ``results/summary.csv`` (kill rate per module) and ``results/mutation.md`` (the table, and every survivor
with its line: the bugs the tests do not catch yet). From the repository root::

    OMP_NUM_THREADS=1 python benchmarks/mutation/run_mutation.py --workers 16
    python benchmarks/mutation/run_mutation.py --modules sb3_lifelong/common/losses.py --workers 1 --limit 10
    python benchmarks/mutation/run_mutation.py --list   # the mutants, without running them
"""

import argparse
import ast
import copy
import csv
import datetime
import importlib
import json
import os
import pathlib
import platform
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from typing import Any, Callable, Optional

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
RESULTS = pathlib.Path(__file__).resolve().parent / "results"

#: the modules measured, each with the test files that target it (fast ones: a mutant's run takes seconds)
MODULES: dict[str, list[str]] = {
    "sb3_lifelong/mpo/losses.py": [
        "tests/mpo/test_mpo_losses.py",
        "tests/common/test_properties.py",
        "tests/mpo/test_mpo.py::test_dual_parametrisation",
    ],
    "sb3_lifelong/crr/losses.py": [
        "tests/crr/test_crr_losses.py",
        "tests/crr/test_crr_ess.py",
        "tests/common/test_properties.py",
    ],
    "sb3_lifelong/common/losses.py": [
        "tests/mpo/test_mpo_losses.py",
        "tests/crr/test_crr_losses.py",
        "tests/mpo/test_mpo.py::test_td_target_hand_computed_with_episode_ends_and_n_step_discounts",
    ],
    "sb3_lifelong/common/policies.py": [
        "tests/golden/test_golden_policy_defaults.py",  # every default (the full run found them free to change)
        "tests/golden/test_golden_policies.py",  # the survivors of the full run: flags, layers, heads, archs
        "tests/common/test_policies.py",
        "tests/mpo/test_presets.py",  # the heads' init scale (Acme's MuJoCo baseline)
        "tests/common/test_properties.py",
        "tests/mpo/test_mpo_losses.py",
        "tests/crr/test_crr_losses.py",
        "tests/bc/test_bc.py",
    ],
    "sb3_lifelong/experiments/claims.py": [
        "tests/experiments/test_claims_both_ways.py",
        "tests/experiments/test_claims_files.py",
        "tests/experiments/test_study.py::test_a_ratio_with_a_non_positive_denominator_is_left_out",
        "tests/experiments/test_study.py::test_claims_pair_the_compared_series_by_seed",
    ],
    "sb3_lifelong/experiments/statistics.py": [
        "tests/experiments/test_claims_both_ways.py",
        "tests/experiments/test_study.py::test_bootstrap_interval",
        "tests/experiments/test_study.py::test_claims_pair_the_compared_series_by_seed",
    ],
    "benchmarks/studies/paper_cpu/claims.py": ["tests/experiments/test_claims_both_ways.py"],
    # the numbers a user relies on beyond the losses (issue 66): targets, the update loop, sampling, views, the
    # dynamics changes, evaluation, distillation and the study scores, each with its golden and targeted tests
    "sb3_lifelong/crr/targets.py": ["tests/golden/test_golden_crr.py", "tests/crr/test_crr_losses.py"],
    "sb3_lifelong/crr/distributional.py": [
        "tests/golden/test_golden_crr.py",
        "tests/golden/test_golden_categorical.py",
        "tests/crr/test_crr_losses.py",
    ],
    "sb3_lifelong/mpo/mpo.py": [
        "tests/golden/test_golden_mpo.py",
        "tests/golden/test_golden_eager.py",
        "tests/test_sb3_contrib_shapes.py::test_consistency",
    ],
    "sb3_lifelong/buffers/sampling.py": [
        "tests/golden/test_golden_sampling.py",
        "tests/golden/test_golden_views.py",
        "tests/golden/test_golden_student_rows.py",
        "tests/buffers/test_sampling_checks.py",
        "tests/buffers/test_buffers.py",
        "tests/common/test_offline_data.py",  # the next actions of the data (CRR's SARSA target)
        "tests/buffers/test_buffer_dict.py",  # Dict observations
    ],
    "sb3_lifelong/buffers/views.py": [
        "tests/golden/test_golden_views.py",
        "tests/golden/test_golden_sampling.py",
        "tests/buffers/test_buffers.py",
    ],
    "sb3_lifelong/envs/perturbations.py": [
        "tests/golden/test_golden_perturbations.py",  # the table (module constants: every test runs for them)
        "tests/golden/test_golden_model_edits.py",  # every field edit on a toy model, in about 3 s
        "tests/golden/test_golden_schedule.py",
        "tests/envs/test_perturbations.py",
    ],
    "sb3_lifelong/envs/schedule.py": [
        "tests/golden/test_golden_schedulers.py",
        "tests/golden/test_golden_schedule.py",
        "tests/envs/test_schedule.py",
    ],
    "sb3_lifelong/evaluation/overestimation.py": [
        "tests/golden/test_golden_overestimation.py",
        "tests/evaluation/test_overestimation.py",
    ],
    "sb3_lifelong/evaluation/callbacks.py": [
        "tests/golden/test_golden_callbacks.py",
        "tests/golden/test_golden_eval_sources.py",
        "tests/evaluation/test_callbacks.py",
        "tests/evaluation/test_eval_callback_parity.py",
    ],
    "sb3_lifelong/common/distillation.py": [
        "tests/golden/test_golden_student_rows.py",
        "tests/test_distill.py",
        "tests/golden/test_golden_crr.py",
        "tests/common/test_verbose.py",
        "tests/core/test_one_way_in.py::test_distill_follows_a_logger_given_with_set_logger",
    ],
    "sb3_lifelong/common/offline.py": [
        "tests/golden/test_golden_offline.py",
        "tests/golden/test_golden_eval_sources.py",
        "tests/common/test_offline_data.py",
        "tests/common/test_offline_learning.py",
        "tests/crr/test_crr.py::test_the_offline_progress_bar_counts_updates",
    ],
    "sb3_lifelong/experiments/scores.py": [
        "tests/golden/test_golden_scores.py",
        "tests/experiments/test_report_inputs.py",
        "tests/experiments/test_study_readings.py",
        "tests/experiments/test_study.py",
    ],
    # the buffer's commit and recovery path (its scope below): rows written, committed, recovered after a crash
    "sb3_lifelong/buffers/rowstore.py": [
        "tests/buffers/test_buffer_crash_prefix.py",
        "tests/buffers/test_buffer_faults.py",
    ],
}

#: the modules measured in part: only the mutation sites inside these functions (``Class.method`` or ``function``)
SCOPES: dict[str, tuple[str, ...]] = {
    "sb3_lifelong/buffers/rowstore.py": (
        "RowStore._first_tail_rows",
        "RowStore._open_or_create",
        "RowStore.refresh",
        "RowStore.append",
        "RowStore._keep_pending",
        "RowStore._extend_tail",
        "RowStore._make_room",
        "RowStore.flush",
        "RowStore._write_chunks",
        "RowStore._commit",
        "RowStore._adopt_commit",
        "RowStore._delete_undeleted",
    ),
}

#: what the copy of the repository holds (``benchmarks``: its Python files only, not its results)
COPIED = ("sb3_lifelong", "tests", "docs/modules")  # docs/modules: the tables that golden tests check against the code
COPIED_FILES = ("setup.cfg", "pyproject.toml", "setup.py", "conftest.py")


# ---------------------------------------------------------------------------------------------------------------------
# The mutation sites
# ---------------------------------------------------------------------------------------------------------------------

COMPARISONS: dict[type, type] = {
    ast.Lt: ast.LtE,
    ast.LtE: ast.Lt,
    ast.Gt: ast.GtE,
    ast.GtE: ast.Gt,
    ast.Eq: ast.NotEq,
    ast.NotEq: ast.Eq,
    ast.Is: ast.IsNot,
    ast.IsNot: ast.Is,
    ast.In: ast.NotIn,
    ast.NotIn: ast.In,
}
ARITHMETIC: dict[type, type] = {ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult, ast.Pow: ast.Mult}
SWAPPED_NAMES = {
    "min": "max",
    "max": "min",
    "amin": "amax",
    "amax": "amin",
    "clamp_min": "clamp_max",
    "clamp_max": "clamp_min",
    "minimum": "maximum",
    "maximum": "minimum",
    "mean": "sum",
    "sum": "mean",
}


@dataclass(frozen=True)
class Mutant:
    """One mutation of a module: where, what, and the mutated source."""

    module: str
    index: int
    line: int
    operator: str
    original: str
    mutated: str
    source: str


Mutation = Callable[[ast.AST], Optional[ast.AST]]


def _docstring_nodes(tree: ast.AST) -> set[int]:
    """:return: the ids of the docstrings' nodes (never mutated)"""
    found: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str):
                found.update(id(sub) for sub in ast.walk(first))
    return found


def _annotation_nodes(tree: ast.AST) -> set[int]:
    """:return: the ids of the nodes inside type annotations (never mutated: a mutant there changes nothing)"""
    found: set[int] = set()
    for node in ast.walk(tree):
        annotations = []
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            annotations.append(node.returns)
            arguments = node.args
            for arg in [*arguments.posonlyargs, *arguments.args, *arguments.kwonlyargs, arguments.vararg, arguments.kwarg]:
                if arg is not None:
                    annotations.append(arg.annotation)
        elif isinstance(node, ast.AnnAssign):
            annotations.append(node.annotation)
        for annotation in annotations:
            if annotation is not None:
                found.update(id(sub) for sub in ast.walk(annotation))
    return found


def mutations_of(node: ast.AST) -> Iterator[tuple[str, Mutation]]:  # noqa: C901 (one branch per kind of node)
    """:return: the mutations of one node, each a name and a function that rewrites (a copy of) the node"""
    if isinstance(node, ast.Compare):
        for position, op in enumerate(node.ops):
            if type(op) in COMPARISONS:

                def compare(n: ast.AST, position: int = position) -> ast.AST:
                    assert isinstance(n, ast.Compare)
                    n.ops[position] = COMPARISONS[type(n.ops[position])]()
                    return n

                yield f"compare {type(op).__name__} -> {COMPARISONS[type(op)].__name__}", compare
    elif isinstance(node, ast.BinOp) and type(node.op) in ARITHMETIC:

        def arithmetic(n: ast.AST) -> ast.AST:
            assert isinstance(n, ast.BinOp)
            n.op = ARITHMETIC[type(n.op)]()
            return n

        yield f"arithmetic {type(node.op).__name__} -> {ARITHMETIC[type(node.op)].__name__}", arithmetic
        if isinstance(node.op, (ast.Add, ast.Sub)):
            yield "drop the right term", lambda n: n.left  # type: ignore[attr-defined]
            yield "drop the left term", lambda n: n.right if isinstance(n.op, ast.Add) else ast.UnaryOp(ast.USub(), n.right)  # type: ignore[attr-defined]
    elif isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.Not)):
        yield f"drop unary {type(node.op).__name__}", lambda n: n.operand  # type: ignore[attr-defined]
    elif isinstance(node, ast.BoolOp):

        def boolean(n: ast.AST) -> ast.AST:
            assert isinstance(n, ast.BoolOp)
            n.op = ast.Or() if isinstance(n.op, ast.And) else ast.And()
            return n

        yield f"boolean {type(node.op).__name__} swapped", boolean
    elif isinstance(node, ast.AugAssign) and isinstance(node.op, (ast.Add, ast.Sub)):

        def augmented(n: ast.AST) -> ast.AST:
            assert isinstance(n, ast.AugAssign)
            n.op = ast.Sub() if isinstance(n.op, ast.Add) else ast.Add()
            return n

        yield "augmented += <-> -=", augmented
    elif isinstance(node, ast.Constant) and not isinstance(node.value, str):
        value = node.value
        if isinstance(value, bool):
            yield f"constant {value} -> {not value}", lambda n: ast.Constant(not value)
        elif isinstance(value, (int, float)) and not isinstance(value, complex):
            replaced = 1 if value == 0 else 0 if value == 1 else value + 1
            if isinstance(value, float):
                replaced = float(replaced)
            yield f"constant {value!r} -> {replaced!r}", lambda n: ast.Constant(replaced)
    elif isinstance(node, ast.Call):
        function = node.func
        name = (
            function.id if isinstance(function, ast.Name) else function.attr if isinstance(function, ast.Attribute) else None
        )
        if name in SWAPPED_NAMES:
            swapped = SWAPPED_NAMES[name]

            def swap(n: ast.AST, swapped: str = swapped) -> ast.AST:
                assert isinstance(n, ast.Call)
                if isinstance(n.func, ast.Name):
                    n.func.id = swapped
                elif isinstance(n.func, ast.Attribute):
                    n.func.attr = swapped
                return n

            yield f"call {name} -> {swapped}", swap
        if name == "detach" and isinstance(function, ast.Attribute) and not node.args:
            yield "drop .detach()", lambda n: n.func.value  # type: ignore[attr-defined]


def _scope_lines(tree: ast.AST, scope: Sequence[str]) -> list[tuple[int, int]]:
    """:return: the line ranges of the functions named in ``scope`` (``Class.method`` or ``function``)"""
    ranges: dict[str, tuple[int, int]] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                name = prefix + child.name
                if not isinstance(child, ast.ClassDef):
                    ranges[name] = (child.lineno, child.end_lineno or child.lineno)
                visit(child, name + ".")

    visit(tree, "")
    missing = [name for name in scope if name not in ranges]
    if missing:
        raise ValueError(f"no function {missing} in the module: its scope is out of date")
    return [ranges[name] for name in scope]


def list_mutants(module: str, root: pathlib.Path = ROOT, scope: Optional[Sequence[str]] = None) -> list[Mutant]:
    """
    :param module: a path relative to ``root``
    :param root: the repository's root
    :param scope: only the sites inside these functions (``Class.method`` or ``function``); all when None
    :return: every mutant of ``module``, in the order of the source's lines
    """
    source = (root / module).read_text()
    tree = ast.parse(source)
    skipped = _docstring_nodes(tree) | _annotation_nodes(tree)
    lines = _scope_lines(tree, scope) if scope is not None else None
    original_nodes = list(ast.walk(tree))
    mutants = []
    for position, node in enumerate(original_nodes):
        if id(node) in skipped or not hasattr(node, "lineno"):
            continue
        if lines is not None and not any(lo <= node.lineno <= hi for lo, hi in lines):
            continue
        for name, mutate in mutations_of(node):
            mutated_tree = copy.deepcopy(tree)
            target = list(ast.walk(mutated_tree))[position]
            replacement = mutate(copy.deepcopy(target))
            if replacement is None:
                continue
            _replace(mutated_tree, target, replacement)
            ast.fix_missing_locations(mutated_tree)
            try:
                mutated_source = ast.unparse(mutated_tree)
                compile(mutated_source, module, "exec")
            except (SyntaxError, ValueError):
                continue
            mutants.append(
                Mutant(
                    module=module,
                    index=0,  # numbered below, in the order of the source's lines
                    line=node.lineno,
                    operator=name,
                    original=ast.unparse(node),
                    mutated=ast.unparse(replacement),
                    source=mutated_source,
                )
            )
    mutants.sort(key=lambda m: m.line)  # stable: the nodes of a line keep the tree's order
    return [Mutant(**{**asdict(m), "index": index}) for index, m in enumerate(mutants)]


def _replace(tree: ast.AST, target: ast.AST, replacement: ast.AST) -> None:
    """Put ``replacement`` where ``target`` is in ``tree`` (in its parent's field or list)."""
    for parent in ast.walk(tree):
        for field, value in ast.iter_fields(parent):
            if value is target:
                setattr(parent, field, replacement)
                return
            if isinstance(value, list):
                for position, item in enumerate(value):
                    if item is target:
                        value[position] = replacement
                        return
    raise AssertionError("mutation target not found in its tree")


# ---------------------------------------------------------------------------------------------------------------------
# Running a mutant
# ---------------------------------------------------------------------------------------------------------------------


def copy_repository(destination: pathlib.Path, root: pathlib.Path = ROOT) -> None:
    """Copy what the tests import and read: the package, the tests, ``benchmarks``' Python files, the configuration."""
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", ".hypothesis")
    for name in COPIED:
        shutil.copytree(root / name, destination / name, ignore=ignore)
    for name in COPIED_FILES:
        if (root / name).exists():
            shutil.copy2(root / name, destination / name)
    for path in (root / "benchmarks").rglob("*.py"):
        if "__pycache__" in path.parts:
            continue
        target = destination / path.relative_to(root)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, target)


@dataclass
class Outcome:
    """What the targeted tests made of a mutant."""

    module: str
    index: int
    line: int
    operator: str
    original: str
    mutated: str
    outcome: str  # killed, survived, timeout, error (the tests could not run: counted apart)
    seconds: float
    detail: str


#: (``--hypothesis-seed``: every run draws the same examples, so the coverage map's tests are the mutants' tests)
PYTEST_ARGS = (
    "-x",
    "-q",
    "-p",
    "no:cacheprovider",
    "-W",
    "ignore::DeprecationWarning",
    "-o",
    "addopts=",
    "--hypothesis-seed=0",
)
TEST_ENV = dict(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONDONTWRITEBYTECODE="1", CUDA_VISIBLE_DEVICES="")

#: what the forking runner imports once, before its first fork (never the package itself: each child imports its copy)
PRELOADED = (
    "numpy",
    "scipy.stats",
    "torch",
    "torch._dynamo",
    "gymnasium",
    "stable_baselines3",
    "pytest",
    "hypothesis",
    "filelock",
)


def _classify(returncode: int, output: str, seconds: float) -> tuple[str, float, str]:
    """:return: a pytest exit code and its output read as an outcome (killed / survived / error), seconds, a detail"""
    lines = [line for line in output.splitlines() if line.strip()]
    detail = lines[-1] if lines else ""
    if returncode == 0:
        return "survived", seconds, detail
    if returncode == 1:  # tests ran and failed
        failed = next((line for line in lines if line.startswith("FAILED")), detail)
        return "killed", seconds, failed[:200]
    # 2: interrupted (an error at collection, e.g. the mutant breaks an import), 3/4: pytest's own errors
    return ("killed" if returncode == 2 else "error"), seconds, detail[:200]


def run_tests(copy_root: pathlib.Path, tests: Sequence[str], timeout: float) -> tuple[str, float, str]:
    """:return: the outcome of the tests in the copy (killed / survived / timeout / error), their seconds and a detail"""
    path = os.pathsep.join(p for p in (str(copy_root), os.environ.get("PYTHONPATH", "")) if p)  # the copy first
    env = dict(os.environ, PYTHONPATH=path, **TEST_ENV)  # on the CPU, as CI runs them (no GPU shared by the workers)
    command = [sys.executable, "-m", "pytest", *PYTEST_ARGS, *tests]
    start = time.perf_counter()
    try:
        completed = subprocess.run(command, cwd=copy_root, env=env, capture_output=True, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return "timeout", time.perf_counter() - start, f"over {timeout:g} s"
    return _classify(completed.returncode, completed.stdout + completed.stderr, time.perf_counter() - start)


def preload() -> None:
    """Import the heavy libraries once, in the process that forks the test runs (a child then starts in milliseconds)."""
    for name, value in TEST_ENV.items():
        os.environ[name] = value
    for name in PRELOADED:
        try:
            importlib.import_module(name)
        except ImportError:
            pass
    assert "sb3_lifelong" not in sys.modules, "the forking runner must not import the package it mutates"


class ForkedTests:
    """
    A module's targeted tests, run by ``pytest.main`` in a forked child of this process, with the copy first on
    ``sys.path`` (the libraries are imported already: see :func:`preload`). The child checks that it imports the
    package from the copy and not from anywhere else; its output goes to ``pytest.log`` in the copy.

    :param covering: a module (a path from the copy's root) to measure: every test runs (no ``-x``) under coverage,
        and which tests ran each of its lines goes to ``coverage_map.json`` in the copy (see :func:`coverage_map`)
    """

    def __init__(self, copy_root: pathlib.Path, tests: Sequence[str], timeout: float, covering: Optional[str] = None):
        self.copy_root = copy_root
        self.tests = list(tests)
        self.timeout = timeout
        self.covering = covering
        self.log = copy_root / "pytest.log"
        self.started = time.perf_counter()
        self.looked = 0.0  # when its CPU was last read (once a second: reading a group scans /proc)
        self.pid = os.fork()
        if self.pid == 0:  # the child never returns
            self._child()

    def _child(self) -> None:
        code = 4
        try:
            os.setpgid(0, 0)  # its own process group: the processes its tests start are timed and stopped with it
            descriptor = os.open(self.log, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
            os.dup2(descriptor, 1)
            os.dup2(descriptor, 2)
            sys.stdout = open(1, "w", closefd=False)  # what the parent's sys.stdout was (a capture) is not ours
            sys.stderr = open(2, "w", closefd=False)
            os.chdir(self.copy_root)
            sys.path.insert(0, str(self.copy_root))
            cov = None
            if self.covering is not None:  # before the package's import: its lines at import are in the "" context
                import coverage

                cov = coverage.Coverage(data_file=None, include=[str(self.measured())], config_file=False)
                cov.start()
            try:
                import sb3_lifelong  # noqa: F401 (the mutant may break its import: killed, as pytest would say)
            except Exception:
                traceback.print_exc()
                code = 2
            else:
                where = pathlib.Path(sys.modules["sb3_lifelong"].__file__ or "").resolve()
                if self.copy_root.resolve() not in where.parents:
                    print(f"sb3_lifelong was imported from {where}, not from the copy")
                    code = 3
                else:
                    code = self._pytest(cov)
        except BaseException:
            traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)

    def measured(self) -> pathlib.Path:
        """:return: the module measured, as coverage names it (a path through no link)"""
        assert self.covering is not None
        return (self.copy_root / self.covering).resolve()

    def _pytest(self, cov: Any) -> int:
        if cov is None:
            return int(pytest.main([*PYTEST_ARGS, *self.tests]))
        plugin = _Contexts(cov)
        _watch_processes(plugin)
        code = int(pytest.main([*(arg for arg in PYTEST_ARGS if arg != "-x"), *self.tests], plugins=[plugin]))
        cov.stop()
        lines = cov.get_data().contexts_by_lineno(str(self.measured()))
        data = dict(order=plugin.order, lines=lines, fixtures=plugin.fixtures, spawning=sorted(plugin.spawning))
        (self.copy_root / "coverage_map.json").write_text(json.dumps(data))
        return code

    def poll(self) -> Optional[tuple[str, float, str]]:
        """:return: the outcome once the child has ended (it is killed past its timeout), None while it runs"""
        pid, status = os.waitpid(self.pid, os.WNOHANG)
        seconds = time.perf_counter() - self.started
        if pid == 0:
            if seconds - self.looked < 1.0:
                return None
            self.looked = seconds
            late = overdue(self.pid, seconds, self.timeout)
            if late is None:
                return None
            stop(self.pid)
            return "timeout", seconds, late
        output = self.log.read_text(errors="replace") if self.log.exists() else ""
        return _classify(os.waitstatus_to_exitcode(status), output, seconds)


#: a run that takes no CPU (a deadlock) is stopped after this many times its timeout of wall-clock time
WALL_FACTOR = 30


def _stat(pid: Any) -> Optional[list[str]]:
    """:return: the fields of ``/proc/<pid>/stat`` after the command's name (the process state first), or None"""
    try:
        return pathlib.Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def cpu_seconds(pid: int) -> Optional[float]:
    """
    :return: the CPU seconds of a running process and of the children it has waited for, and where it leads a
        process group (the forked runs do), of every process of its group (Linux); None elsewhere
    """
    fields = _stat(pid)
    if fields is None:
        return None
    members = [fields]
    if int(fields[2]) == pid:  # a group's leader: the processes its tests started, while they run, count too
        for entry in os.listdir("/proc"):
            if entry.isdigit() and int(entry) != pid:
                other = _stat(entry)
                if other is not None and int(other[2]) == pid:
                    members.append(other)
    ticks = sum(int(value) for member in members for value in member[11:15])  # utime, stime, cutime, cstime
    return ticks / os.sysconf("SC_CLK_TCK")


def overdue(pid: int, seconds: float, timeout: float) -> Optional[str]:
    """
    A run's timeout counts its CPU seconds where they can be read, so that a run slowed by other jobs on the machine
    (or started at a low priority, to use the cores they leave) is not taken for a mutant that hangs; a run that
    takes no CPU at all is stopped after :data:`WALL_FACTOR` times the timeout.

    :param pid: the run's process
    :param seconds: its wall-clock seconds so far
    :param timeout: its timeout, in seconds
    :return: why it is overdue, or None while it is not
    """
    cpu = cpu_seconds(pid)
    if cpu is None:
        return f"over {timeout:g} s" if seconds > timeout else None
    if cpu > timeout:
        return f"over {timeout:g} s of CPU"
    return f"over {WALL_FACTOR * timeout:g} s, {cpu:.0f} s of CPU" if seconds > WALL_FACTOR * timeout else None


def stop(pid: int) -> None:
    """Kill a run and the processes of its group (what its tests started), and reap it."""
    try:
        os.killpg(pid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass
    try:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
    except (ProcessLookupError, ChildProcessError):
        pass


def _fresh_copy(scratch: pathlib.Path, prefix: str, mutant: Optional[Mutant] = None) -> pathlib.Path:
    copy_root = pathlib.Path(tempfile.mkdtemp(prefix=prefix, dir=scratch))
    copy_repository(copy_root)
    if mutant is not None:
        (copy_root / mutant.module).write_text(mutant.source)
    return copy_root


def run_forked(
    jobs: Sequence[tuple[str, Optional[Mutant], Sequence[str]]],
    workers: int,
    timeout: float,
    scratch: pathlib.Path,
) -> Iterator[tuple[str, Optional[Mutant], tuple[str, float, str]]]:
    """
    Run the jobs (a name, the mutant or None for a baseline, the tests) in forked children, ``workers`` at once.

    :return: each job with its outcome, as they end
    """
    waiting = list(jobs)
    running: list[tuple[str, Optional[Mutant], pathlib.Path, ForkedTests]] = []
    try:
        while waiting or running:
            while waiting and len(running) < workers:
                name, mutant, tests = waiting.pop(0)
                copy_root = _fresh_copy(scratch, f"{name}_", mutant)
                running.append((name, mutant, copy_root, ForkedTests(copy_root, tests, timeout)))
            time.sleep(0.02)
            for entry in list(running):
                name, mutant, copy_root, child = entry
                result = child.poll()
                if result is not None:
                    running.remove(entry)
                    shutil.rmtree(copy_root, ignore_errors=True)
                    yield name, mutant, result
    finally:  # interrupted: no child outlives the runner, no copy is left behind
        for _, _, copy_root, child in running:
            stop(child.pid)
            shutil.rmtree(copy_root, ignore_errors=True)


# ---------------------------------------------------------------------------------------------------------------------
# The tests that run a mutant's statement (``--select covering``)
# ---------------------------------------------------------------------------------------------------------------------

#: where a line ran outside any test (at import, at collection): a mutant there may change what every test sees
IMPORT_CONTEXT = ""
FIXTURE_CONTEXT = "fixture:"


@dataclass
class CoverageMap:
    """
    Which of a module's targeted tests run each of its lines, read once from the unmutated tests under coverage
    (:func:`coverage_map`). A test that never runs a statement runs the same code in a mutant of that statement, so
    only the tests that run it are needed, unless one test leaves state for another (a cache, a global) or the
    statement runs in a thread or a finalizer while another test runs (coverage's context is the process's). Where it
    is not known which tests run a line, every test runs (:meth:`tests_for` returns None). A kill by a part of the
    tests is checked by running that part unmutated (``main``'s ``--verify-kills``).

    :param order: the tests (pytest node ids) in the order they ran
    :param lines: line -> the contexts that ran it: a test's node id, ``fixture:<name>`` (a fixture of class, module
        or session scope set up for the tests that use it) or ``""`` (at import or collection)
    :param fixtures: test -> the fixtures it uses
    :param spawning: the contexts that started a process (``subprocess``, ``multiprocessing``, ``os.fork``): what the
        process ran is not measured, so their tests run with every mutant (a process started at import or collection
        is not any test's: a line it alone runs looks unmeasured, and every test runs)
    """

    order: list[str]
    lines: dict[int, list[str]]
    fixtures: dict[str, list[str]]
    spawning: list[str]

    def _tests_of(self, context: str) -> set[str]:
        if context.startswith(FIXTURE_CONTEXT):
            name = context[len(FIXTURE_CONTEXT) :]
            return {test for test in self.order if name in self.fixtures.get(test, ())}
        return {context} if context in self.fixtures else set()

    def tests_for(self, first: int, last: int) -> Optional[list[str]]:
        """
        :param first: the first line of the mutated statement (see :func:`statement_lines`)
        :param last: its last line
        :return: the tests that ran a line of it in their order, then those that start processes; None (run every
            test) when a line of it ran at import or collection, or in no test of this process
        """
        contexts = {context for line in range(first, last + 1) for context in self.lines.get(line, ())}
        if not contexts or IMPORT_CONTEXT in contexts:
            return None
        chosen: set[str] = set()
        for context in contexts:
            chosen |= self._tests_of(context)
        spawning = set().union(*(self._tests_of(context) for context in self.spawning))
        if not chosen:
            return None
        # the tests that start processes last: they are often the slow ones, and a mutant killed earlier skips them
        return [test for test in self.order if test in chosen - spawning] + [test for test in self.order if test in spawning]


def statement_lines(tree: ast.AST, line: int) -> tuple[int, int]:
    """
    :return: the lines of the innermost statement that holds ``line``: all of a simple statement's, a compound one's
        header (``if``, ``for``, ``def``... up to its first inner statement, decorators included), an ``except``
        clause's; a ``match`` statement's whole (its cases are no statements)
    """
    best: Optional[tuple[int, int]] = None
    for node in ast.walk(tree):
        if not isinstance(node, (ast.stmt, ast.excepthandler)):
            continue
        start = min([node.lineno, *(d.lineno for d in getattr(node, "decorator_list", []))])
        end = node.end_lineno or node.lineno
        inner = [
            child.lineno
            for field in ("body", "orelse", "finalbody", "handlers")
            for child in getattr(node, field, [])
            if isinstance(child, (ast.stmt, ast.excepthandler))
        ]
        if inner:
            end = min(end, min(inner) - 1)
        if start <= line <= end and (best is None or end - start < best[1] - best[0]):
            best = (start, end)
    return best if best is not None else (line, line)


class _Contexts:
    """A pytest plugin that tells coverage which test (or shared fixture) runs, and notes the ones that start processes."""

    def __init__(self, cov: Any) -> None:
        self.cov = cov
        self.current = IMPORT_CONTEXT
        self.order: list[str] = []
        self.fixtures: dict[str, list[str]] = {}
        self.spawning: set[str] = set()

    def switch(self, context: str) -> str:
        previous, self.current = self.current, context
        self.cov.switch_context(context)
        return previous

    def spawned(self) -> None:
        self.spawning.add(self.current)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_protocol(self, item: Any, nextitem: Any) -> Iterator[None]:
        self.order.append(item.nodeid)
        self.fixtures[item.nodeid] = list(item.fixturenames)
        self.switch(item.nodeid)
        yield
        self.switch(IMPORT_CONTEXT)

    @pytest.hookimpl(hookwrapper=True)
    def pytest_fixture_setup(self, fixturedef: Any, request: Any) -> Iterator[None]:
        if fixturedef.scope == "function":  # the test's own: its context already
            yield
            return
        context = FIXTURE_CONTEXT + fixturedef.argname
        during: list[str] = []  # the context its teardown interrupts (the test being torn down, or "")
        # finalizers run last in, first out: these two bracket the fixture's own teardown, added in between
        fixturedef.addfinalizer(lambda: self.switch(during.pop() if during else IMPORT_CONTEXT))
        previous = self.switch(context)
        yield
        self.switch(previous)
        fixturedef.addfinalizer(lambda: during.append(self.switch(context)))


def _watch_processes(plugin: _Contexts) -> None:
    """Note the context of every process started from here on (``subprocess.Popen``, ``multiprocessing``, a fork)."""
    import multiprocessing.process

    popen_init = subprocess.Popen.__init__
    process_start = multiprocessing.process.BaseProcess.start

    def init(self: Any, *args: Any, **kwargs: Any) -> None:
        plugin.spawned()
        popen_init(self, *args, **kwargs)

    def start(self: Any) -> None:
        plugin.spawned()
        process_start(self)

    subprocess.Popen.__init__ = init  # type: ignore[method-assign]
    multiprocessing.process.BaseProcess.start = start  # type: ignore[method-assign]
    os.register_at_fork(before=plugin.spawned)  # a test's own fork: what the child runs is not saved either


def coverage_map(
    copy_root: pathlib.Path, module: str, tests: Sequence[str], timeout: float
) -> tuple[tuple[str, float, str], Optional[CoverageMap]]:
    """
    Run a module's targeted tests, unmutated, in a forked child under coverage (every test, not stopping at a
    failure: :class:`ForkedTests` with ``covering``): the baseline of the module, and which tests run each of its lines.

    :return: the baseline's outcome (``survived``: every test passed), and the map (None when the baseline failed)
    """
    child = ForkedTests(copy_root, tests, timeout, covering=module)
    result = child.poll()
    while result is None:
        time.sleep(0.05)
        result = child.poll()
    record = copy_root / "coverage_map.json"
    if result[0] != "survived" or not record.exists():
        return result, None
    data = json.loads(record.read_text())
    lines = {int(line): contexts for line, contexts in data["lines"].items()}
    return result, CoverageMap(data["order"], lines, data["fixtures"], data["spawning"])


def chosen_tests(mutant: Mutant, tests: Sequence[str], where: Optional[CoverageMap], tree: ast.AST) -> list[str]:
    """:return: the tests a mutant runs: those that run its statement (``where``), or all of ``tests``"""
    if where is None:
        return list(tests)
    return where.tests_for(*statement_lines(tree, mutant.line)) or list(tests)


def run_mutant(mutant: Mutant, tests: Sequence[str], timeout: float, scratch: pathlib.Path) -> Outcome:
    """Write the mutant into a fresh copy of the repository, run its module's tests there (a subprocess), remove it."""
    copy_root = _fresh_copy(scratch, f"mutant_{mutant.index}_", mutant)
    try:
        result = run_tests(copy_root, tests, timeout)
    finally:
        shutil.rmtree(copy_root, ignore_errors=True)
    return outcome_of(mutant, result)


def outcome_of(mutant: Mutant, result: tuple[str, float, str]) -> Outcome:
    """:return: the mutant's row of the results"""
    outcome, seconds, detail = result
    fields = {k: v for k, v in asdict(mutant).items() if k != "source"}
    return Outcome(**fields, outcome=outcome, seconds=round(seconds, 2), detail=detail)


def baseline(tests: Sequence[str], timeout: float, scratch: pathlib.Path) -> tuple[str, float, str]:
    """:return: the unmutated tests' outcome (they must pass, or no mutant's outcome means anything)"""
    copy_root = _fresh_copy(scratch, "baseline_")
    try:
        return run_tests(copy_root, tests, timeout)
    finally:
        shutil.rmtree(copy_root, ignore_errors=True)


# ---------------------------------------------------------------------------------------------------------------------
# Results
# ---------------------------------------------------------------------------------------------------------------------


def summarise(outcomes: Sequence[Outcome]) -> list[dict]:
    """:return: per module: mutants, killed (timeouts included), survived, errors, kill rate over the decided ones"""
    rows = []
    for module in dict.fromkeys(o.module for o in outcomes):
        mine = [o for o in outcomes if o.module == module]
        killed = sum(o.outcome in ("killed", "timeout") for o in mine)
        survived = sum(o.outcome == "survived" for o in mine)
        errors = sum(o.outcome == "error" for o in mine)
        decided = killed + survived
        rows.append(
            dict(
                module=module,
                mutants=len(mine),
                killed=killed,
                survived=survived,
                errors=errors,
                kill_rate=round(killed / decided, 3) if decided else float("nan"),
                seconds=round(sum(o.seconds for o in mine), 1),
            )
        )
    return rows


def write_results(outcomes: Sequence[Outcome], output: pathlib.Path, command: str, total_mutants: dict[str, int]) -> None:
    output.mkdir(parents=True, exist_ok=True)
    ordered = sorted(outcomes, key=lambda o: (o.module, o.index))
    with open(output / "mutation.csv", "w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(asdict(ordered[0]))) if ordered else None
        if writer is not None:
            writer.writeheader()
            writer.writerows(asdict(o) for o in ordered)
    summary = summarise(ordered)
    with open(output / "summary.csv", "w", newline="") as handle:
        writer = csv.DictWriter(
            handle, fieldnames=["module", "mutants", "killed", "survived", "errors", "kill_rate", "seconds"]
        )
        writer.writeheader()
        writer.writerows(summary)
    lines = [
        "# Mutation testing: the bugs the targeted tests catch",
        "",
        f"`{command}`, {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {platform.node()}, "
        f"Python {platform.python_version()}. A mutant is killed when its module's targeted tests fail (a timeout "
        "counts as killed); the kill rate is over the killed and surviving ones (errors: the tests could not run).",
        "",
        "| module | mutants run (of all) | killed | survived | errors | kill rate |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for row in summary:
        lines.append(
            f"| `{row['module']}` | {row['mutants']} (of {total_mutants.get(row['module'], row['mutants'])}) | "
            f"{row['killed']} | {row['survived']} | {row['errors']} | {row['kill_rate']:.0%} |"
        )
    survivors = [o for o in ordered if o.outcome == "survived"]
    lines += ["", f"## Survivors ({len(survivors)})", ""]
    if survivors:
        lines += ["| module | line | operator | original | mutated |", "| --- | --- | --- | --- | --- |"]
        for o in survivors:
            lines.append(f"| `{o.module}` | {o.line} | {o.operator} | `{_cell(o.original)}` | `{_cell(o.mutated)}` |")
    else:
        lines.append("None.")
    errors = [o for o in ordered if o.outcome == "error"]
    if errors:
        lines += ["", f"## Errors ({len(errors)})", ""]
        lines += [f"- `{o.module}`:{o.line} {o.operator}: {o.detail}" for o in errors]
    (output / "mutation.md").write_text("\n".join(lines) + "\n")


def same_mutants(mutants: Sequence[Mutant], earlier: Sequence[Outcome], outcome: str = "survived") -> list[Mutant]:
    """
    :param mutants: a module's mutants now
    :param earlier: all its mutants in an earlier run (a ``mutation.csv``'s rows of the module)
    :param outcome: which of them to pick
    :return: the mutants now that had ``outcome`` then. A mutant is known by its operator, original and mutated code
        and which occurrence of those it is, in the order of the source (lines move when the code above them changes;
        a change that adds or removes such a mutant above it is not followed)
    """

    def keyed(items: Sequence[Any]) -> list[tuple[tuple[str, str, str], int]]:
        seen: dict[tuple[str, str, str], int] = {}
        keys = []
        for item in items:
            key = (item.operator, item.original, item.mutated)
            keys.append((key, seen.get(key, 0)))
            seen[key] = seen.get(key, 0) + 1
        return keys

    then = sorted(earlier, key=lambda o: o.index)
    wanted = {k for k, o in zip(keyed(then), then) if o.outcome == outcome}
    return [m for k, m in zip(keyed(mutants), mutants) if k in wanted]


def read_outcomes(path: pathlib.Path, exclude: Sequence[str] = ()) -> list[Outcome]:
    """:return: the rows of an earlier ``mutation.csv`` (none if it does not exist), less those of ``exclude``'s modules"""
    if not path.exists():
        return []
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    return [
        Outcome(
            module=row["module"],
            index=int(row["index"]),
            line=int(row["line"]),
            operator=row["operator"],
            original=row["original"],
            mutated=row["mutated"],
            outcome=row["outcome"],
            seconds=float(row["seconds"]),
            detail=row["detail"],
        )
        for row in rows
        if row["module"] not in exclude
    ]


def _cell(code: str) -> str:
    code = " ".join(code.split()).replace("|", "\\|").replace("`", "'")
    return code if len(code) <= 90 else code[:87] + "..."


def forked_jobs(
    chosen: Sequence[Mutant],
    targets: dict[str, list[str]],
    select: str,
    workers: int,
    timeout: float,
    scratch: pathlib.Path,
    baseline_failed: Callable[[str, tuple[str, float, str]], bool],
) -> Optional[list[tuple[str, Optional[Mutant], Sequence[str]]]]:
    """
    Each module's baseline (all its targeted tests, as a mutant runs them; with ``select="covering"`` also under
    coverage: which tests run each line), then the mutants' runs for :func:`run_forked`, each with its tests
    (:func:`chosen_tests`).

    :return: the runs; None when a module's unmutated tests do not pass
    """
    modules = list(targets)
    # the baseline as a mutant runs (all its tests, within the timeout), with either selection
    baselines = [(f"baseline_{k}", None, targets[module]) for k, module in enumerate(modules)]
    for name, _, result in run_forked(baselines, workers, timeout, scratch):
        if baseline_failed(modules[int(name.rsplit("_", 1)[1])], result):
            return None
    maps: dict[str, Optional[CoverageMap]] = {}
    if select == "covering":
        for module in modules:
            copy_root = _fresh_copy(scratch, "coverage_")
            try:  # coverage slows the tests down: thrice the time of a mutant's run
                result, maps[module] = coverage_map(copy_root, module, targets[module], 3 * timeout)
            finally:
                shutil.rmtree(copy_root, ignore_errors=True)
            if baseline_failed(f"{module} (under coverage)", result):
                return None
    trees = {module: ast.parse((ROOT / module).read_text()) for module in targets}
    jobs: list[tuple[str, Optional[Mutant], Sequence[str]]] = [
        (f"mutant_{m.index}", m, chosen_tests(m, targets[m.module], maps.get(m.module), trees[m.module])) for m in chosen
    ]
    for module, where in maps.items():
        if where is not None:
            runs = [list(tests) for _, m, tests in jobs if m is not None and m.module == module]
            parts = [len(tests) for tests in runs if tests != list(targets[module])]
            mean = f" ({sum(parts) / len(parts):.1f} tests on average)" if parts else ""
            print(
                f"{module}: {len(where.order)} targeted tests; {len(parts)} of {len(runs)} mutants run only those that run "
                f"their statement{mean}, the others every one",
                flush=True,
            )
    return jobs


def verify_kills(
    outcomes: list[Outcome],
    jobs: Sequence[tuple[str, Optional[Mutant], Sequence[str]]],
    targets: dict[str, list[str]],
    workers: int,
    timeout: float,
    scratch: pathlib.Path,
) -> int:
    """
    Run unmutated, once each, the parts of the targeted tests that killed mutants (:func:`chosen_tests`), in the order
    the mutants ran them. A part that fails without a mutant (a test that needs state an earlier test left, or one
    moved after the others) killed nothing: its mutants' outcomes become ``error``, naming the part.

    :param outcomes: the mutants' outcomes, changed in place
    :param jobs: the mutants' runs (name, mutant, tests)
    :return: how many kills were withdrawn
    """
    tests_of = {(m.module, m.index): tuple(tests) for _, m, tests in jobs if m is not None}
    parts = sorted(
        {
            tests_of[(o.module, o.index)]
            for o in outcomes
            if o.outcome == "killed" and tests_of.get((o.module, o.index), ()) not in ((), tuple(targets[o.module]))
        }
    )
    failed: dict[tuple[str, ...], str] = {}
    runs = [(f"part_{k}", None, list(part)) for k, part in enumerate(parts)]
    for name, _, (result, _, detail) in run_forked(runs, workers, timeout, scratch):
        if result != "survived":
            failed[parts[int(name.rsplit("_", 1)[1])]] = detail
    withdrawn = 0
    for position, o in enumerate(outcomes):
        part = tests_of.get((o.module, o.index))
        if o.outcome == "killed" and part in failed:
            detail = f"its {len(part)} chosen tests fail unmutated: {failed[part]}"[:200]
            outcomes[position] = Outcome(**{**asdict(o), "outcome": "error", "detail": detail})
            withdrawn += 1
    print(f"verified {len(parts)} parts of the tests that killed mutants unmutated: {len(failed)} failed, "
          f"{withdrawn} kills withdrawn", flush=True)  # fmt: skip
    return withdrawn


def parse_arguments(argv: Optional[Sequence[str]]) -> tuple[argparse.Namespace, list[tuple[int, ...]]]:
    """:return: the command line's arguments, and its ``--lines`` as ranges"""
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--modules", nargs="+", default=list(MODULES), help="modules to mutate (paths from the root)")
    parser.add_argument("--workers", type=int, default=1, help="mutants run at once (one torch thread each)")
    parser.add_argument("--limit", type=int, default=None, help="at most this many mutants per module (spread evenly)")
    parser.add_argument(
        "--timeout",
        type=float,
        default=300.0,
        help="seconds a mutant's tests may take (then: killed); with the forking runner, CPU seconds where /proc has them",
    )
    parser.add_argument("--output", type=pathlib.Path, default=RESULTS, help="where the csv and markdown go")
    parser.add_argument("--scratch", type=pathlib.Path, default=None, help="where the copies go (default: the temp dir)")
    parser.add_argument("--list", action="store_true", help="list the mutants and stop")
    parser.add_argument(
        "--survivors-of",
        type=pathlib.Path,
        default=None,
        metavar="CSV",
        help="only the mutants that survived in an earlier mutation.csv (matched by operator and code, not by line: "
        "the lines may have moved), to measure the tests added for them",
    )
    parser.add_argument(
        "--lines",
        nargs="+",
        default=None,
        metavar="FIRST-LAST",
        help="only the mutants on these source lines (e.g. a function's, to measure the tests added for its survivors)",
    )
    parser.add_argument(
        "--runner",
        choices=("fork", "spawn"),
        default="fork" if hasattr(os, "fork") else "spawn",
        help="fork: each run is a forked child of this process, the libraries imported once (the default where "
        "os.fork exists); spawn: each run is a new Python process",
    )
    parser.add_argument(
        "--tests",
        nargs="+",
        default=None,
        metavar="PATH",
        help="run these test files or folders against every module's mutants instead of its targeted ones (e.g. a "
        "module's survivors against a wider part of the suite)",
    )
    parser.add_argument(
        "--select",
        choices=("covering", "all"),
        default=None,
        help="covering (the default with the forking runner): each mutant runs only the targeted tests that run its "
        "statement, read once from the unmutated tests under coverage (every test where a line ran at import, or in "
        "no test of the process; tests that start processes always); all: every targeted test for every mutant",
    )
    parser.add_argument(
        "--no-verify-kills",
        dest="verify_kills",
        action="store_false",
        help="with --select covering, do not run unmutated the part of the tests that killed a mutant (by default each "
        "such part runs once; a part that fails unmutated makes its mutants errors, not kills)",
    )
    parser.add_argument(
        "--keep-others",
        action="store_true",
        help="keep the rows of the modules not run now from the output's mutation.csv (a measurement in parts)",
    )
    args = parser.parse_args(argv)
    unknown = [module for module in args.modules if module not in MODULES]
    if unknown:
        parser.error(f"no targeted tests known for {unknown}: one of {list(MODULES)}")
    if args.workers < 1:
        parser.error("--workers must be >= 1")
    if args.select is None:
        args.select = "covering" if args.runner == "fork" else "all"
    if args.select == "covering" and args.runner != "fork":
        parser.error("--select covering needs the forking runner (--runner fork)")
    try:
        ranges = [tuple(int(x) for x in (text.split("-", 1) if "-" in text else [text, text])) for text in args.lines or []]
    except ValueError:
        parser.error(f"--lines takes FIRST-LAST ranges, got {args.lines}")
    return args, ranges


def main(argv: Optional[Sequence[str]] = None) -> int:
    args, ranges = parse_arguments(argv)
    targets = {module: list(args.tests) if args.tests else MODULES[module] for module in args.modules}
    chosen: list[Mutant] = []
    total: dict[str, int] = {}
    for module in args.modules:
        mutants = list_mutants(module, scope=SCOPES.get(module))
        if args.lines is not None:
            mutants = [m for m in mutants if any(lo <= m.line <= hi for lo, hi in ranges)]
        if args.survivors_of is not None:
            mutants = same_mutants(mutants, [o for o in read_outcomes(args.survivors_of) if o.module == module])
        total[module] = len(mutants)
        if args.limit is not None and len(mutants) > args.limit:
            step = len(mutants) / args.limit  # an even spread over the module, not its first lines only
            mutants = [mutants[int(k * step)] for k in range(args.limit)]
        chosen += mutants
        print(f"{module}: {len(mutants)} mutants (of {total[module]})", flush=True)
    if args.list:
        for m in chosen:
            print(f"{m.module}:{m.line} [{m.operator}] {_cell(m.original)}  ->  {_cell(m.mutated)}")
        return 0

    scratch = args.scratch or pathlib.Path(tempfile.gettempdir())
    scratch.mkdir(parents=True, exist_ok=True)
    outcomes: list[Outcome] = read_outcomes(args.output / "mutation.csv", exclude=args.modules) if args.keep_others else []
    for module in dict.fromkeys(o.module for o in outcomes):
        total.setdefault(module, sum(o.module == module for o in outcomes))
    kept = len(outcomes)
    command = "python benchmarks/mutation/run_mutation.py " + " ".join(argv if argv is not None else sys.argv[1:])

    def report(done: int, outcome: Outcome) -> None:
        outcomes.append(outcome)
        print(
            f"[{done}/{len(chosen)}] {outcome.outcome:8s} {outcome.module}:{outcome.line} {outcome.operator}: "
            f"{_cell(outcome.original)} -> {_cell(outcome.mutated)} ({outcome.seconds:.1f} s)",
            flush=True,
        )
        if done % 10 == 0 or done == len(chosen):  # partial results survive an interrupted run
            write_results(outcomes, args.output, command.strip(), total)

    def baseline_failed(module: str, result: tuple[str, float, str]) -> bool:
        outcome, seconds, detail = result
        print(f"baseline {module}: {outcome} in {seconds:.1f} s ({detail})", flush=True)
        if outcome != "survived":
            print(f"the unmutated tests of {module} do not pass: fix them first", file=sys.stderr)
        return outcome != "survived"

    if args.runner == "fork":
        preload()
        jobs = forked_jobs(chosen, targets, args.select, args.workers, args.timeout, scratch, baseline_failed)
        if jobs is None:
            return 1
        for done, (_, mutant, result) in enumerate(run_forked(jobs, args.workers, args.timeout, scratch), 1):
            assert mutant is not None
            report(done, outcome_of(mutant, result))
        if args.select == "covering" and args.verify_kills:
            verify_kills(outcomes, jobs, targets, args.workers, args.timeout, scratch)
            write_results(outcomes, args.output, command.strip(), total)
    else:
        with ThreadPoolExecutor(max_workers=args.workers) as pool:
            futures_of = {module: pool.submit(baseline, targets[module], args.timeout, scratch) for module in args.modules}
            if any(baseline_failed(module, future.result()) for module, future in futures_of.items()):
                return 1
            futures = [pool.submit(run_mutant, m, targets[m.module], args.timeout, scratch) for m in chosen]
            for done, future in enumerate(as_completed(futures), 1):
                report(done, future.result())
    if kept:
        print(f"kept {kept} rows of other modules from {args.output / 'mutation.csv'}")
    for row in summarise(sorted(outcomes, key=lambda o: (o.module, o.index))):
        print(
            f"{row['module']}: {row['killed']} killed, {row['survived']} survived, {row['errors']} errors, "
            f"kill rate {row['kill_rate']}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

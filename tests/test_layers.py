"""The package's layers import downwards only (docs/guide/architecture.md): a move that breaks this fails here."""

import ast
import pathlib
from typing import Optional

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "sb3_lifelong"

#: layer of each module prefix, lowest first; a module may import its own layer and the layers below it
LAYERS = [
    ("sb3_lifelong.core", 0),
    ("sb3_lifelong.numerics", 1),
    ("sb3_lifelong.envs", 1),
    ("sb3_lifelong.buffers", 1),
    ("sb3_lifelong.evaluation", 1),
    ("sb3_lifelong.common", 2),
    ("sb3_lifelong.mpo", 3),
    ("sb3_lifelong.crr", 3),
    ("sb3_lifelong.bc", 3),
    ("sb3_lifelong.distill", 4),
    ("sb3_lifelong", 5),  # the package's __init__ (the public names), and names imported from it
    ("sb3_lifelong.zoo", 6),
    ("sb3_lifelong.experiments", 6),
]
#: names the package's __init__ exports (``from sb3_lifelong import MPO`` is an import of layer 5)
PUBLIC = {"sb3_lifelong.BC", "sb3_lifelong.CRR", "sb3_lifelong.MPO", "sb3_lifelong.LifelongReplayBuffer"}
#: the algorithms do not import each other
PEERS = ("sb3_lifelong.mpo", "sb3_lifelong.crr", "sb3_lifelong.bc")


def layer_of(module: str) -> int:
    if module in PUBLIC:
        return layer_of("sb3_lifelong")
    for prefix, layer in LAYERS:
        if module == prefix or (prefix != "sb3_lifelong" and module.startswith(prefix + ".")):
            return layer
    raise AssertionError(f"{module} is in no layer: add it to LAYERS (and to docs/guide/architecture.md)")


def module_name(path: pathlib.Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: pathlib.Path, text: Optional[str] = None) -> set[str]:
    """:return: the package's modules (and names in them) that the module at ``path`` (its text: ``text``) imports"""
    found = set()
    package = module_name(path) if path.name == "__init__.py" else module_name(path).rpartition(".")[0]
    for node in ast.walk(ast.parse(path.read_text() if text is None else text)):
        if isinstance(node, ast.ImportFrom) and (node.module or node.level):
            # a relative import (``from ..buffers import x``) is resolved against the module's package
            base = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
            module = node.module if node.level == 0 else ".".join(part for part in (base, node.module) if part)
            assert module is not None
            found.add(module)
            found.update(f"{module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
    return {name for name in found if name.split(".")[0] == "sb3_lifelong"}


MODULES = sorted(PACKAGE.rglob("*.py"))


@pytest.mark.parametrize("path", MODULES, ids=lambda path: module_name(path))
def test_imports_go_downwards(path):
    module = module_name(path)
    own = layer_of(module)
    for imported in imports_of(path):
        try:
            target = layer_of(imported)
        except AssertionError:
            continue  # a name imported from a module (e.g. sb3_lifelong.buffers.LifelongReplayBuffer) is checked as its module
        assert target <= own, f"{module} (layer {own}) imports {imported} (layer {target}): imports must go downwards"
        for peer in PEERS:
            if module.startswith(peer) and imported.startswith(PEERS) and not imported.startswith(peer):
                raise AssertionError(f"{module} imports another algorithm, {imported}")


def test_relative_imports_are_resolved():
    source = PACKAGE / "common" / "relative_probe.py"  # a module that is not there: only its path and text are used
    found = imports_of(source, text="from ..mpo import MPO\nfrom . import scoring\nfrom .losses import sum_of\n")
    assert {"sb3_lifelong.mpo", "sb3_lifelong.mpo.MPO", "sb3_lifelong.common.scoring", "sb3_lifelong.common.losses"} <= found
    assert layer_of("sb3_lifelong.mpo") > layer_of(module_name(source))  # so such an import would fail the layer check


def test_every_module_has_a_layer():
    for path in MODULES:
        layer_of(module_name(path))


def module_graph() -> dict[str, set[str]]:
    """Module -> the package's modules it imports (at the top or inside a function), a package's own ``__init__`` aside."""
    names = {module_name(path): path for path in MODULES}

    def resolve(name: str) -> str:
        while name and name not in names:
            name = name.rsplit(".", 1)[0] if "." in name else ""
        return name

    graph: dict[str, set[str]] = {}
    for module, path in names.items():
        targets = {resolve(name) for name in imports_of(path)}
        graph[module] = {t for t in targets if t and t != module and t != "sb3_lifelong" and not module.startswith(t + ".")}
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """:return: the strongly connected groups of more than one module (Tarjan)"""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    circles: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        for target in graph.get(node, ()):
            if target not in index:
                visit(target)
                low[node] = min(low[node], low[target])
            elif target in stack:
                low[node] = min(low[node], index[target])
        if low[node] == index[node]:
            group = []
            while True:
                member = stack.pop()
                group.append(member)
                if member == node:
                    break
            if len(group) > 1:
                circles.append(sorted(group))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return circles


def test_no_import_circles():
    # imports inside functions count: they hide a circle from Python, not from a reader
    assert import_circles(module_graph()) == []


def test_circles_are_found():
    assert import_circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert import_circles({"a": {"b"}, "b": set()}) == []

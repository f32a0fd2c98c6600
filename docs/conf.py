# Sphinx configuration of sb3-lifelong (MyST markdown pages)
import importlib
import inspect
import os
import sys
from typing import Any, Optional

from sphinx import addnodes

sys.path.insert(0, os.path.abspath(".."))

with open(os.path.join(os.path.dirname(__file__), "..", "sb3_lifelong", "version.txt")) as file_handler:
    __version__ = file_handler.read().strip()

project = "sb3-lifelong"
copyright = "2026, sb3-lifelong developers"
author = "sb3-lifelong developers"
version = __version__
release = __version__

extensions = [
    "myst_parser",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.intersphinx",
    "sphinx.ext.mathjax",
    "sphinx.ext.viewcode",
    "sphinx_copybutton",
]
myst_enable_extensions = ["dollarmath", "colon_fence"]
# links to a page's sections by their titles ([Guarantees](buffer.md#guarantees))
myst_heading_anchors = 3
source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
master_doc = "index"
exclude_patterns = ["_build", "Thumbs.db", ".DS_Store"]
autodoc_mock_imports = ["mujoco", "dm_control", "mujoco_menagerie"]
autodoc_member_order = "bysource"
autodoc_typehints = "signature"

# Links to the other projects' documentation, read from small local inventories (docs/inventories, written by
# make_inventories.py) so that the build needs no network: the links still lead to the projects' own pages.
_INVENTORIES = os.path.join(os.path.dirname(os.path.abspath(__file__)), "inventories")
sys.path.insert(0, _INVENTORIES)
from make_inventories import INVENTORIES  # noqa: E402

intersphinx_mapping = {name: (url, os.path.join(_INVENTORIES, f"{name}.inv")) for name, (url, _) in INVENTORIES.items()}

# `make doc` builds with -n -W: every reference must resolve. These do not name a documented object:
nitpick_ignore_regex = [
    # the TypeVars of `-> Self` returns (``SelfMPO``, ``SelfCRR``, ...) and of generic functions
    ("py:class", r"sb3_lifelong\..*\.(Self\w+|BufferT)"),
    # Stable-Baselines3 objects that its documentation does not describe (no page to link to)
    (
        "py:class",
        r"stable_baselines3\.common\.(buffers\.ReplayBuffer|policies\.(BasePolicy|ContinuousCritic)"
        r"|policies\.BaseModel|torch_layers\.BaseFeaturesExtractor|type_aliases\.\w+)",
    ),
]

# SB3's type aliases spell some classes as strings (``GymEnv = Union[gym.Env, "VecEnv"]``): autodoc shows the bare
# name, resolved here to the class SB3 documents
_FORWARD_REFS = {
    "VecEnv": "stable_baselines3.common.vec_env.VecEnv",
    "BaseCallback": "stable_baselines3.common.callbacks.BaseCallback",
}


def _object(name: str) -> Any:
    """:return: the object the dotted ``name`` imports, or None"""
    parts = name.split(".")
    for split in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:split]))
        except ImportError:
            continue
        try:
            for attribute in parts[split:]:
                obj = getattr(obj, attribute)
        except AttributeError:
            return None
        return obj
    return None


def _canonical_name(name: str) -> Optional[str]:
    """:return: where the package object ``name`` is defined (``module.qualname``), or None if it is not one"""
    obj = _object(name)
    if inspect.ismodule(obj):
        return obj.__name__
    module, qualname = getattr(obj, "__module__", None), getattr(obj, "__qualname__", None)
    if module is None or qualname is None or not module.startswith("sb3_lifelong"):
        return None
    return f"{module}.{qualname}"


def _documented(domain: Any) -> list[str]:
    """:return: the names of the package's objects that the documentation describes"""
    return [name for name, entry in domain.objects.items() if name.startswith("sb3_lifelong") and not entry.aliased]


_DOCUMENTED_BY_ID: dict[int, str] = {}


def _same_object(domain: Any, candidate: str) -> Optional[str]:
    """:return: the documented name of the object ``candidate`` imports (a function or constant re-exported by a
    package is documented under its public name), or None"""
    obj = _object(candidate)
    if obj is None or inspect.ismodule(obj):
        return None
    if not _DOCUMENTED_BY_ID:  # references are resolved after every page is read: the objects are all known
        for name in _documented(domain):
            _DOCUMENTED_BY_ID.setdefault(id(_object(name)), name)
    return _DOCUMENTED_BY_ID.get(id(obj))


def _dataclass_defaults(app, what, name, obj, options, signature, return_annotation):  # type: ignore[no-untyped-def]
    """A dataclass field's ``default_factory`` shows as ``<factory>``, which is no Python: show ``...``."""
    if signature is not None and "<factory>" in signature:
        return signature.replace("<factory>", "..."), return_annotation
    return None


def _public_bases(app, name, obj, options, bases):  # type: ignore[no-untyped-def]
    """Show a class's documented bases: a private base by its own bases, and no mixin that nobody documents."""
    for index in reversed(range(len(bases))):
        base = bases[index]
        if base.__name__.startswith("_"):
            bases[index : index + 1] = list(base.__bases__)
        elif base.__name__ in _HIDDEN_BASES:
            del bases[index]


# Gymnasium's RecordConstructorArgs (a mixin of its wrappers) has no page in Gymnasium's documentation
_HIDDEN_BASES = {"RecordConstructorArgs"}


def _internals_summary(app, what, name, obj, options, lines):  # type: ignore[no-untyped-def]
    """On the Internals page, a docstring's first paragraph only: the page says what each piece is, the source the rest."""
    if app.env.docname == "api/internals" and "" in lines:
        del lines[lines.index("") :]


def _resolve(app, env, node, contnode):  # type: ignore[no-untyped-def]
    """
    Resolve what Python itself would: a name re-exported by a package (``sb3_lifelong.buffers.LifelongReplayBuffer``
    is documented where it is defined) or a name that the docstring's module imports (``:class:`MultiEnvEvalCallback```
    in a module that imports it); and SB3's forward references.
    """
    if node.get("refdomain") != "py":
        return None
    target = node["reftarget"]
    if target in _FORWARD_REFS:
        from sphinx.ext.intersphinx import missing_reference

        node["reftarget"] = _FORWARD_REFS[target]
        return missing_reference(app, env, node, contnode)
    module, cls = node.get("py:module"), node.get("py:class")
    scopes = [module, cls and f"{module}.{cls}"]
    parent = node.parent
    while parent is not None:  # the modules the docstrings around the reference come from
        if isinstance(parent, addnodes.desc):
            for signature in parent.findall(addnodes.desc_signature):
                documented = _object(f"{signature.get('module')}.{signature.get('fullname')}")
                for owner in getattr(documented, "__mro__", None) or [documented]:
                    scopes.append(getattr(owner, "__module__", None))
                    if inspect.isclass(owner):  # a method of the class or of a base
                        scopes.append(f"{owner.__module__}.{owner.__qualname__}")
                break
        parent = parent.parent
    candidates = [target] + [f"{scope}.{target}" for scope in scopes if scope]
    domain = env.get_domain("py")
    from sphinx.ext.intersphinx import missing_reference

    for candidate in candidates[1:]:  # a docstring inherited from another project's class (``:attr:`env```)
        if not candidate.startswith("sb3_lifelong"):
            node["reftarget"] = candidate
            resolved = missing_reference(app, env, node, contnode)
            node["reftarget"] = target
            if resolved is not None:
                return resolved
    for candidate in candidates:
        if not candidate.startswith("sb3_lifelong"):
            continue
        canonical = _canonical_name(candidate)
        if canonical is None or not (canonical in domain.objects or canonical in domain.modules):
            canonical = _same_object(domain, candidate)
        if canonical is not None and (canonical in domain.objects or canonical in domain.modules):
            return domain.resolve_xref(env, node["refdoc"], app.builder, node["reftype"], canonical, node, contnode)
    # a name the module cannot import (a circular import) but that only one documented object of the package has
    if not target.startswith(("sb3_lifelong", "stable_baselines3", "gymnasium", "torch", "numpy")):
        matches = [name for name in _documented(domain) if name.endswith(f".{target}")]
        if len(matches) == 1:
            return domain.resolve_xref(env, node["refdoc"], app.builder, node["reftype"], matches[0], node, contnode)
    return None


def setup(app):  # type: ignore[no-untyped-def]
    app.connect("missing-reference", _resolve)
    app.connect("autodoc-process-bases", _public_bases)
    app.connect("autodoc-process-docstring", _internals_summary)
    app.connect("autodoc-process-signature", _dataclass_defaults)


try:
    import sphinx_rtd_theme  # noqa: F401

    html_theme = "sphinx_rtd_theme"
except ImportError:
    html_theme = "alabaster"
html_static_path = ["_static"]
# wrapping table cells and code lines (the theme clips them), figures within the column; sphinx_copybutton puts a copy
# button on every code block (it leaves out the prompts and line numbers that Pygments marks)
html_css_files = ["css/readable.css"]

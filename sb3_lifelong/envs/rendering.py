"""
Rendering MuJoCo frames without choosing an OpenGL backend at import time.

MuJoCo binds its OpenGL backend when it is first imported, from ``MUJOCO_GL``; a backend whose library is missing
(``MUJOCO_GL=osmesa`` without libOSMesa) makes ``import mujoco`` itself fail. So this package never sets
``MUJOCO_GL``: training and evaluation need no OpenGL at all, and :func:`make_renderer` picks a backend only when
a frame is asked for.
"""

import importlib
import os
import sys
from typing import Any


def _headless_context(backend: str) -> Any:
    """:return: the ``GLContext`` class of a headless backend ("egl" or "osmesa"), importing it now"""
    if "OpenGL" in sys.modules and os.environ.get("PYOPENGL_PLATFORM", "") != backend:
        raise RuntimeError(f"PyOpenGL is already loaded for platform {os.environ.get('PYOPENGL_PLATFORM')!r}")
    os.environ.setdefault("PYOPENGL_PLATFORM", backend)
    return importlib.import_module(f"mujoco.{backend}").GLContext


def make_renderer(model: Any, height: int, width: int) -> Any:
    """
    A ``mujoco.Renderer`` with an OpenGL backend chosen now: the user's ``MUJOCO_GL`` when it is set, the
    default (GLFW) when a display exists, otherwise the first headless backend that works: EGL (libEGL, e.g.
    Debian's libegl1), then OSMesa (libosmesa6).

    :param model: the ``MjModel``
    :param height: frame height
    :param width: frame width
    :return: the renderer
    :raises RuntimeError: naming every backend tried, when none works
    """
    import mujoco

    if os.environ.get("MUJOCO_GL") or os.environ.get("DISPLAY"):
        try:
            return mujoco.Renderer(model, height, width)
        except Exception as e:
            raise RuntimeError(
                f"MuJoCo could not render with MUJOCO_GL={os.environ.get('MUJOCO_GL', '')!r} "
                f"(DISPLAY={os.environ.get('DISPLAY', '')!r}): {e}"
            ) from e
    classic: Any = importlib.import_module("mujoco.rendering.classic.gl_context")
    errors = []
    for backend in ("egl", "osmesa"):
        default = classic.GLContext
        try:
            classic.GLContext = _headless_context(backend)
            return mujoco.Renderer(model, height, width)
        except Exception as e:  # a missing library surfaces as ImportError, AttributeError or a GL error
            errors.append(f"{backend}: {type(e).__name__}: {e}")
        finally:
            classic.GLContext = default
    raise RuntimeError(
        "No OpenGL backend for MuJoCo rendering (no display; tried " + "; ".join(errors) + "). Install EGL "
        "(Debian: libegl1) or OSMesa (libosmesa6), or set MUJOCO_GL to a backend that works here."
    )

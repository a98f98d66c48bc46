"""Rendering MuJoCo environments without a display, for videos.

MuJoCo renders through OpenGL, and which OpenGL is chosen once per process, by the environment
variable ``MUJOCO_GL`` read when the first renderer is made (and ``PYOPENGL_PLATFORM`` when PyOpenGL is
first imported): ``glfw`` needs a display, ``egl`` renders headless on a GPU or with Mesa's software
EGL, ``osmesa`` renders headless in software. :func:`ensure_offscreen_gl` picks one before anything
renders: ``MUJOCO_GL`` when it is set; the default (``glfw``) when there is a display; otherwise the first
of ``egl`` and ``osmesa`` that renders a frame in a child process (a backend that fails to load cannot
spoil this one). On Debian or Ubuntu, ``apt-get install libegl1`` gives EGL and ``apt-get install
libosmesa6`` OSMesa.
"""

from __future__ import annotations

import os
import subprocess
import sys
from functools import cache

from mira.errors import MiraError

HEADLESS_BACKENDS = ("egl", "osmesa")

_PROBE = """
import mujoco
model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom size='1'/></worldbody></mujoco>")
data = mujoco.MjData(model)
mujoco.mj_forward(model, data)
renderer = mujoco.Renderer(model, 16, 16)
renderer.update_scene(data)
assert renderer.render().shape == (16, 16, 3)
"""


class RenderingUnavailable(MiraError):
    """No OpenGL backend can render MuJoCo here."""


def _renders(backend: str, timeout_s: float = 120.0) -> str | None:
    """None if a child process renders a frame with ``MUJOCO_GL=backend``, else the last line of its error."""
    env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
    try:
        proc = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, text=True,
                              timeout=timeout_s, stdin=subprocess.DEVNULL)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return str(exc)
    if proc.returncode == 0:
        return None
    lines = [ln for ln in proc.stderr.strip().splitlines() if ln.strip()]
    return lines[-1] if lines else f"exit status {proc.returncode}"


@cache
def ensure_offscreen_gl() -> str:
    """The OpenGL backend MuJoCo will render with in this process, set in ``MUJOCO_GL`` (and
    ``PYOPENGL_PLATFORM``) when it had to be chosen; :class:`RenderingUnavailable` with what to install
    when none works. Call it before the first environment with a render mode is made."""
    chosen = os.environ.get("MUJOCO_GL", "").strip().lower()
    if chosen:
        return chosen
    if os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return "glfw"
    failures = []
    for backend in HEADLESS_BACKENDS:
        error = _renders(backend)
        if error is None:
            os.environ["MUJOCO_GL"] = backend
            os.environ.setdefault("PYOPENGL_PLATFORM", backend)
            return backend
        failures.append(f"{backend}: {error}")
    raise RenderingUnavailable(
        "cannot render MuJoCo here: there is no display, and neither headless OpenGL backend works ("
        + "; ".join(failures) + "). Install one (Debian/Ubuntu: apt-get install libegl1 for EGL, or "
        "apt-get install libosmesa6 for OSMesa), or set MUJOCO_GL to a backend that works")


def ensure_video_writer() -> None:
    """Gymnasium's ``RecordVideo`` writes MP4s with MoviePy (which brings its own ffmpeg)."""
    import importlib.util

    if importlib.util.find_spec("moviepy") is None:
        raise RenderingUnavailable('recording videos needs MoviePy: pip install "mira-rl[video]" (or moviepy)')

"""Shared fixtures."""

import pytest


@pytest.fixture(scope="session")
def gl_renderer():
    """One OpenGL reference renderer for the session; skips when no headless EGL context can be made."""
    pytest.importorskip("moderngl", reason="moderngl is not installed (pip install meshseal[gl])")
    from meshseal.render.opengl import OpenGLRenderer

    renderer = OpenGLRenderer()
    try:
        renderer.ctx
    except RuntimeError as error:
        pytest.skip(f"no headless EGL OpenGL context: {error}")
    yield renderer
    renderer.release()

"""Shared fixtures."""

import os

import pytest

import meshseal.threads

# The suite's in-process commands apply the thread policy (`configure`); its count is not revisited
# mid-suite (`threads.revisit`, tested in subprocesses), so no result depends on the load of the moment.
meshseal.threads.REVISIT_SECONDS = float("inf")


@pytest.fixture(scope="session", autouse=True)
def mesh_cache_folder(tmp_path_factory):
    """The suite's load cache (`mesh.cache`) in a folder of its own, never the user's (subprocesses too)."""
    before = os.environ.get("MESHSEAL_CACHE")
    os.environ["MESHSEAL_CACHE"] = str(tmp_path_factory.mktemp("mesh_cache"))
    yield os.environ["MESHSEAL_CACHE"]
    if before is None:
        del os.environ["MESHSEAL_CACHE"]
    else:
        os.environ["MESHSEAL_CACHE"] = before


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

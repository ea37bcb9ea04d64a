"""The renderer's compiled (numba) kernels, loaded when they pay.

The first compiled call in a process costs about 0.4 s before any work (importing numba, setting up
its compiler's target context, loading the cached machine code): more than a camera-known reading of
one picture does in all. So the kernels (`njit` below, as `numba.njit`) are loaded on their first
call, and while they are not loaded, the small jobs that have a torch path doing the same arithmetic
in the same order (the z-buffer, the splat's forward pass, the blur: the same bits) run that instead.
Torch pays per operation, so those paths are several times slower per job; they are used for jobs of
at most SMALL_JOB values, and only until the seconds spent in them reach LOAD_SECONDS: then the
kernels are loaded, as a renter buys once the rent paid equals the price (never more than about
twice what the better choice in hindsight costs). A command that renders a few pictures never loads
numba; registration, which renders thousands of views, loads it at once (`load`), and training and
batches within their first second.
"""

from __future__ import annotations

import time
from contextlib import contextmanager

LOAD_SECONDS = 0.4  # about what loading the kernels costs a process (numba's import and first call)
PICTURES_TO_LOAD = 4  # `for_pictures`: a command reading this many pictures or more loads the kernels first
SMALL_JOB = 1 << 21  # values (pixels, times planes for a blur) of a job that may run in torch while they are not

_KERNELS: list = []  # every `_Lazy` made, in the order their modules defined them
_numba = None  # the numba module, once `load` ran
_spent = 0.0  # seconds spent in torch paths while the kernels were not loaded


def prange(*args):  # pragma: no cover - replaced by numba.prange in each kernel's module by `load`
    return range(*args)


class _Lazy:
    """A kernel to be compiled by numba with `options` on its first call (or any kernel's)."""

    def __init__(self, function, options: dict):
        self.function, self.options, self.dispatcher = function, options, None
        self.__name__, self.__doc__ = function.__name__, function.__doc__

    def __call__(self, *args):
        if self.dispatcher is None:
            load()
        return self.dispatcher(*args)


def njit(**options):
    """`numba.njit(**options)`, applied when the kernels are loaded. A kernel's module refers to the
    other kernels by their module names, and to `prange` imported from here: `load` puts numba's
    dispatchers and its prange there, so that each kernel compiles as if decorated at import."""

    def wrap(function):
        lazy = _Lazy(function, options)
        _KERNELS.append(lazy)
        if _numba is not None:  # a module imported after the kernels were loaded: compiled as usual
            _build(lazy)
            return lazy.dispatcher
        return lazy

    return wrap


def loaded() -> bool:
    """Whether the compiled kernels are loaded in this process."""
    return _numba is not None


def _build(kernel: _Lazy) -> None:
    space = kernel.function.__globals__
    if space.get("prange") is prange:
        space["prange"] = _numba.prange
    kernel.dispatcher = _numba.njit(**kernel.options)(kernel.function)
    space[kernel.__name__] = kernel.dispatcher


def load() -> None:
    """Import numba and make every kernel's dispatcher (each compiles, or loads its cached code, on
    its first call). numba takes the thread count torch has now (`meshseal.threads`)."""
    global _numba
    first = _numba is None
    if first:
        import numba

        _numba = numba
    for kernel in _KERNELS:
        if kernel.dispatcher is None:
            _build(kernel)
    if first:
        from .. import threads

        threads.numba_loaded()


def for_pictures(count: int) -> None:
    """Load the kernels at once where this process is about to read `count` pictures and their torch
    paths would take longer than a load: a camera-known picture spends about a third of LOAD_SECONDS
    there, so from PICTURES_TO_LOAD on (a command knows how many pictures it has; the rent rule above
    does not, and would load only after several slower readings)."""
    if count >= PICTURES_TO_LOAD:
        load()


def spare(size: int) -> bool:
    """Whether a job of `size` values (a raster's pixels, all the batch's) should take its torch
    path: the kernels are not loaded, the job is small and the torch paths have not yet cost what
    loading the kernels would."""
    return size <= SMALL_JOB and _spent < LOAD_SECONDS and not loaded()


@contextmanager
def in_torch():
    """Counts the seconds of a torch path taken instead of a kernel (see `spare`)."""
    global _spent
    start = time.perf_counter()
    try:
        yield
    finally:
        _spent += time.perf_counter() - start

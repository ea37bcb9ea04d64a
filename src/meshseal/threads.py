"""How many threads meshseal's work may use, and the settings that keep its thread pools from spinning
on cores other jobs are using.

torch's intra-op pool (OpenMP), MKL and numba's parallel kernels (its own OpenMP runtime, a second one)
each start one thread per core and, by default, keep idle threads spinning at every barrier. A
picture's work is thousands of small parallel operations; beside another busy process every one of them
waits for the thread that shares a core with it, and the spinning threads take that core's time too:
many times the work. The policy:

- one process (the command line, a script): as many threads as the cores this process may run on
  (`os.sched_getaffinity`) that other jobs are not already keeping busy (the load average and the
  number of runnable tasks now, whichever is higher), at least one;
- each worker of a pool: one thread (the pool has one worker per core);
- reading a picture of under a million pixels: one thread, unless the user gave a count
  (`reading_threads`): its operations are too small to share between sleeping threads;
- idle threads sleep instead of spinning (`OMP_WAIT_POLICY=PASSIVE`, `KMP_BLOCKTIME=0`);
- a long command (renders, a folder's pictures) looks again each second (`revisit`) and gives up a
  thread while other jobs run, and takes it back after;
- a count the user gives wins: `MESHSEAL_THREADS`, else `OMP_NUM_THREADS`.

numba keeps the threading layer it picks itself (OpenMP where TBB is not installed): with idle threads
asleep it no longer competes, and the other choice, `workqueue`, must not be entered from two threads at
once.

`configure()` writes the settings into the environment, which the OpenMP runtimes, MKL and numba read
when they start; call it before torch and numba are imported (the command line does, first thing).
Where they are already imported it also sets their thread counts directly (`torch.set_num_threads`,
`numba.set_num_threads`, up to the pool numba started with).
"""

from __future__ import annotations

import os
import sys
import time
from contextlib import contextmanager

ENV = "MESHSEAL_THREADS"
_GIVEN: int | None = None  # the count `configure` was given or found set (its own count goes into the environment)
_CONFIGURED = False
READ_ONE_THREAD_BELOW = 1024 * 1024  # pixels: a picture smaller than this is read on one thread (`reading_threads`)
_COUNTS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")
_PASSIVE = {"OMP_WAIT_POLICY": "PASSIVE", "KMP_BLOCKTIME": "0"}
REVISIT_SECONDS = 1.0  # a long command looks at the other jobs again at most this often (`revisit`)
_looks: list[int] = []  # `revisit`'s last few counts of other jobs' running threads
_next_look = 0.0
_pinned = 0  # `reading_threads` blocks holding one thread now


def available_cores() -> int:
    """The CPU cores this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def busy_cores() -> float:
    """Cores other jobs keep busy: the one-minute load average or the tasks runnable now (less this
    one), whichever is higher; 0 where the system does not say."""
    try:
        with open("/proc/loadavg") as file:
            fields = file.read().split()
        load, runnable = float(fields[0]), int(fields[3].split("/")[0]) - 1
    except (OSError, ValueError, IndexError):
        try:
            load, runnable = os.getloadavg()[0], 0
        except OSError:
            return 0.0
    return max(load, float(runnable), 0.0)


def requested() -> int | None:
    """The thread count the user set (`MESHSEAL_THREADS`, else `OMP_NUM_THREADS`), or None."""
    for name in (ENV, "OMP_NUM_THREADS"):
        text = os.environ.get(name, "").strip()
        if text:
            try:
                value = int(text)
            except ValueError:
                continue
            if value >= 1:
                return value
    return None


def policy_threads(worker: bool = False) -> int:
    """Threads for one process: 1 in a pool's worker, else the user's count, else the cores this
    process may use that other jobs leave free (at least 1)."""
    if worker:
        return 1
    given = requested()
    if given is not None:
        return given
    cores = available_cores()
    return max(1, min(cores, cores - int(busy_cores() + 0.5)))


def configure(threads: int | None = None, worker: bool = False) -> int:
    """Apply the policy to this process (and the processes it starts, through the environment);
    returns the thread count. `threads` overrides the policy's count."""
    global _GIVEN, _CONFIGURED
    if threads is not None or not _CONFIGURED:  # read before the policy's own count is written out
        _GIVEN = int(threads) if threads is not None else requested()
    _CONFIGURED = True
    n = int(threads) if threads is not None else policy_threads(worker)
    for name, value in _PASSIVE.items():
        os.environ.setdefault(name, value)
    own = worker or threads is not None or bool(os.environ.get(ENV, "").strip())
    for name in _COUNTS:
        if name == "NUMBA_NUM_THREADS" and "numba" in sys.modules:
            continue  # numba re-reads it and refuses a change once its pool runs: set_num_threads below
        if own or not os.environ.get(name, "").strip():
            os.environ[name] = str(n)
    if "torch" in sys.modules:
        import torch

        torch.set_num_threads(n)
    if "numba" in sys.modules:
        import numba

        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    return n


def worker_environment() -> dict[str, str]:
    """The environment settings a spawned pool worker needs before it imports anything: one thread,
    idle threads asleep."""
    return {**{name: "1" for name in _COUNTS}, ENV: "1", **{k: os.environ.get(k, v) for k, v in _PASSIVE.items()}}


@contextmanager
def reading_threads(pixels: int):
    """One thread (torch's and numba's) while a picture of `pixels` pixels is read, where it has fewer
    than READ_ONE_THREAD_BELOW and the user gave no count; the count before it afterwards.

    Reading and registering a picture of that size is thousands of small operations: with idle
    threads asleep (the policy above) each parallel one wakes the others and waits for them, which
    costs more than the second core gives, so one thread reads such a picture faster than two;
    threads that spin instead are faster on a quiet machine but lose several times that beside another
    job (`python benchmarks/contention.py --idle-policy`). A larger picture's operations are large
    enough to share.
    Several pictures are read in parallel by processes (`meshseal detect FOLDER`'s pool), one thread
    each."""
    global _pinned
    given = _GIVEN if _CONFIGURED else requested()
    if pixels >= READ_ONE_THREAD_BELOW or given is not None or "torch" not in sys.modules:
        yield
        return
    import torch

    before = torch.get_num_threads()
    numba = sys.modules.get("numba")
    numba_before = numba.get_num_threads() if numba is not None else 1
    if before <= 1 and numba_before <= 1:
        yield
        return
    torch.set_num_threads(1)
    if numba is not None:
        numba.set_num_threads(1)
    _pinned += 1
    try:
        yield
    finally:
        _pinned -= 1
        torch.set_num_threads(before)
        if numba is not None:
            numba.set_num_threads(numba_before)
        elif "numba" in sys.modules:  # loaded while the picture was read (`numba_loaded`): torch's count again
            numba_loaded()


def numba_loaded() -> None:
    """numba was imported just now (the renderer loads its compiled kernels on first use,
    `render.compiled`): it starts with torch's thread count of the moment (one while a small
    picture is read, `reading_threads`) rather than the count `configure` wrote for it."""
    torch, numba = sys.modules.get("torch"), sys.modules.get("numba")
    if torch is not None and numba is not None:
        count = torch.get_num_threads()
        numba.get_num_threads()  # starts numba's pool, which sets the shared OpenMP runtime's count to its own
        numba.set_num_threads(max(1, min(count, numba.config.NUMBA_NUM_THREADS)))
        torch.set_num_threads(count)


def others_running() -> int | None:
    """Threads of other processes running or waiting to run at this instant: the kernel's count of
    runnable tasks (/proc/loadavg) less this process's own running threads; None where the system
    does not say."""
    try:
        with open("/proc/loadavg") as file:
            runnable = int(file.read().split()[3].split("/")[0])
        own = 0
        for task in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{task}/stat") as file:
                    stat = file.read()
            except OSError:  # the thread ended meanwhile
                continue
            own += stat[stat.rindex(")") + 2] == "R"
    except (OSError, ValueError, IndexError):
        return None
    return max(runnable - own, 0)


def revisit() -> None:
    """Between units of a long command's work (each render, each picture read): at most every
    REVISIT_SECONDS, the policy's count again from the other jobs running now (the median of the last
    three looks, once there are two), so that a command started on an idle machine gives up a thread
    when other jobs start and takes it back when they end; `configure` chooses once, at the start.
    Only where `configure` applied the policy (not a count the user gave, nor a pool's worker, whose
    count is given) and not while a small picture is read on one thread (`reading_threads`)."""
    global _next_look
    if not _CONFIGURED or _GIVEN is not None or _pinned or "torch" not in sys.modules:
        return
    now = time.monotonic()
    if now < _next_look:
        return
    _next_look = now + REVISIT_SECONDS
    seen = others_running()
    if seen is None:
        return
    _looks.append(seen)
    del _looks[:-3]
    if len(_looks) < 2:
        return
    cores = available_cores()
    n = max(1, min(cores, cores - sorted(_looks)[len(_looks) // 2]))
    import torch

    if n != torch.get_num_threads():
        torch.set_num_threads(n)
        numba = sys.modules.get("numba")
        if numba is not None:
            numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))

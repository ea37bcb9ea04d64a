"""The thread policy (meshseal.threads): how many threads a process and a pool's worker use, what the
user's settings change, and that torch and numba start with it."""

from __future__ import annotations

import importlib
import json
import os
import subprocess
import sys

import pytest

from meshseal import threads

PROBE = """
import json, os, sys
from meshseal import threads
n = threads.configure(worker=%r)
import numba, torch
numba.njit(parallel=True)(lambda x: x.sum())(__import__("numpy").ones(4))
print(json.dumps({"n": n, "torch": torch.get_num_threads(), "numba": numba.get_num_threads(),
                  "wait": os.environ.get("OMP_WAIT_POLICY")}))
"""


def run_probe(worker: bool, **env) -> dict:
    environment = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "MKL_NUM_THREADS",
                                                                    "NUMBA_NUM_THREADS", threads.ENV)}
    out = subprocess.run([sys.executable, "-c", PROBE % (worker,)], env=environment | env, capture_output=True,
                         text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_a_pool_worker_uses_one_thread_whatever_the_machine(monkeypatch):
    monkeypatch.setenv(threads.ENV, "8")
    assert threads.policy_threads(worker=True) == 1


@pytest.mark.parametrize("cores, busy, expected", [(2, 0.0, 2), (2, 0.4, 2), (2, 1.0, 1), (2, 5.0, 1),
                                                   (8, 3.2, 5), (1, 0.0, 1)])
def test_a_process_uses_the_cores_other_jobs_leave_free(monkeypatch, cores, busy, expected):
    for name in ("OMP_NUM_THREADS", threads.ENV):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setattr(threads, "available_cores", lambda: cores)
    monkeypatch.setattr(threads, "busy_cores", lambda: busy)
    assert threads.policy_threads() == expected


def test_the_users_count_wins(monkeypatch):
    monkeypatch.setattr(threads, "busy_cores", lambda: 50.0)
    monkeypatch.delenv(threads.ENV, raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    assert threads.policy_threads() == 3
    monkeypatch.setenv(threads.ENV, "2")
    assert threads.policy_threads() == 2
    monkeypatch.setenv(threads.ENV, "nonsense")
    assert threads.policy_threads() == 3


def test_busy_cores_reads_the_system():
    assert threads.busy_cores() >= 0.0
    assert threads.available_cores() >= 1


@pytest.mark.heavy  # many seconds: CI's heavy tier keeps the default tier inside its five minutes
def test_torch_and_numba_start_with_the_policy():
    worker = run_probe(True)
    assert worker == {"n": 1, "torch": 1, "numba": 1, "wait": "PASSIVE"}
    given = run_probe(False, MESHSEAL_THREADS="1", OMP_WAIT_POLICY="ACTIVE")
    assert given == {"n": 1, "torch": 1, "numba": 1, "wait": "ACTIVE"}  # the user's wait policy stays


def test_the_command_line_applies_the_policy_before_the_command(monkeypatch, capsys):
    from meshseal.cli import main

    calls = []
    monkeypatch.setattr(threads, "configure", lambda *a, **k: calls.append("configure") or 1)
    import meshseal.commands.model as model

    monkeypatch.setattr(model, "run_models", lambda args: calls.append("run") or 0)
    main(["models", "--json"])
    assert calls == ["configure", "run"]


def test_worker_environment_is_one_thread():
    environment = threads.worker_environment()
    assert all(environment[name] == "1" for name in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"))
    assert environment["OMP_WAIT_POLICY"] in ("PASSIVE", os.environ.get("OMP_WAIT_POLICY"))


def test_the_dataset_builders_workers_start_with_one_thread(monkeypatch):
    """`meshseal data build`'s pools (spawned) set one thread in each worker before it imports torch,
    whatever the parent's count."""
    from concurrent.futures import ProcessPoolExecutor

    importlib.import_module("meshseal.data.build")  # the package's `build` is the function; the module is in sys.modules

    monkeypatch.setenv("OMP_NUM_THREADS", "2")
    monkeypatch.setenv("NUMBA_NUM_THREADS", "2")
    module = sys.modules["meshseal.data.build"]
    with ProcessPoolExecutor(max_workers=1, mp_context=module._SPAWN, **module._ONE_THREAD) as executor:
        seen = [executor.submit(os.getenv, name).result() for name in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS",
                                                                            "OMP_WAIT_POLICY")]
    assert seen[:2] == ["1", "1"] and seen[2] in ("PASSIVE", os.environ.get("OMP_WAIT_POLICY"))


RECONFIGURE = """
import os
for name in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MESHSEAL_THREADS"):
    os.environ.pop(name, None)
from meshseal import threads
threads.configure(1)
import numba, numpy as np

def total(x):
    s = 0.0
    for i in numba.prange(x.shape[0]):
        s += x[i]
    return s

numba.njit(parallel=True)(total)(np.ones(100))
threads.configure(2)  # a later command in the same process (tests call the command line in-process)
print(numba.njit(parallel=True)(total)(np.ones(100)), numba.get_num_threads())
"""


def test_a_second_policy_in_one_process_leaves_numbas_running_pool_alone():
    """numba refuses a new NUMBA_NUM_THREADS once its pool runs: a later `configure` (the load changed
    between two in-process commands) sets the count through numba.set_num_threads only."""
    out = subprocess.run([sys.executable, "-c", RECONFIGURE], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-1500:]
    assert out.stdout.split()[0] == "100.0"


READING = """
import json, os
for name in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MESHSEAL_THREADS"):
    os.environ.pop(name, None)  # (set by earlier in-process commands of the test session)
os.environ.update(%r)
from meshseal import threads
threads.available_cores = lambda: 2
threads.busy_cores = lambda: 0.0  # an idle two-core machine: the policy takes both cores
threads.configure()
import numba, torch
seen = {"start": [torch.get_num_threads(), numba.get_num_threads()]}
for pixels in (256 * 256, threads.READ_ONE_THREAD_BELOW):
    with threads.reading_threads(pixels):
        seen[str(pixels)] = [torch.get_num_threads(), numba.get_num_threads()]
seen["after"] = [torch.get_num_threads(), numba.get_num_threads()]
print(json.dumps(seen))
"""


@pytest.mark.parametrize("env, inside", [({}, 1), ({"MESHSEAL_THREADS": "2"}, 2)])
def test_a_small_picture_is_read_on_one_thread_unless_the_user_says(env, inside):
    """The policy's two threads on an idle machine; a picture under a million pixels is read on one
    (torch's and numba's), a larger one on both, and the count comes back after; a count the user
    gave stays throughout."""
    out = subprocess.run([sys.executable, "-c", READING % (env,)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-1500:]
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    big = str(threads.READ_ONE_THREAD_BELOW)
    assert seen == {"start": [2, 2], str(256 * 256): [inside, inside], big: [2, 2], "after": [2, 2]}


LOADED_WHILE_READING = """
import json, os, sys
for name in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MESHSEAL_THREADS"):
    os.environ.pop(name, None)
from meshseal import threads
threads.available_cores = lambda: 2
threads.busy_cores = lambda: 0.0
threads.configure()
import torch
from meshseal.render import compiled
seen = {"before": "numba" in sys.modules}
with threads.reading_threads(256 * 256):
    compiled.load()  # the renderer's kernels load during a small picture's reading
    import numba
    seen["inside"] = [torch.get_num_threads(), numba.get_num_threads()]
seen["after"] = [torch.get_num_threads(), numba.get_num_threads()]
print(json.dumps(seen))
"""


def test_numba_loaded_during_a_reading_takes_the_readings_count_then_the_policys():
    """The renderer imports numba on its first compiled call (`render.compiled`), which may come in
    the middle of a small picture's one-thread reading: numba starts on one thread there, and has the
    policy's two afterwards, as torch does."""
    out = subprocess.run([sys.executable, "-c", LOADED_WHILE_READING], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-1500:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == {"before": False, "inside": [1, 1], "after": [2, 2]}


REVISITED = """
import json, os, sys
for name in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MESHSEAL_THREADS"):
    os.environ.pop(name, None)
os.environ.update(%r)
from meshseal import threads
threads.available_cores = lambda: 2
threads.busy_cores = lambda: 0.0  # started on an idle two-core machine
threads.REVISIT_SECONDS = 0.0
threads.configure()
import torch
others = iter([0, 2, 2, 2, 0, 0, 0, 2, 2])
threads.others_running = lambda: next(others)
seen = []
for step in range(7):
    threads.revisit()
    seen.append(torch.get_num_threads())
with threads.reading_threads(256 * 256):  # a small picture's one thread is not revisited
    threads.revisit()
    threads.revisit()
    seen.append(torch.get_num_threads())
print(json.dumps(seen))
"""


@pytest.mark.parametrize("env, expected", [({}, [2, 1, 1, 1, 1, 2, 2, 1]), ({"MESHSEAL_THREADS": "2"}, [2] * 7 + [2])])
def test_a_long_command_gives_up_a_thread_while_other_jobs_run(env, expected):
    """`revisit` (each render, each picture read) counts the other jobs' running threads again: the
    policy's two threads become one while two other threads run (the median of the last three looks,
    once there are two) and two again once they stop; a count the user gave stays, and so does a small
    picture's one thread."""
    out = subprocess.run([sys.executable, "-c", REVISITED % (env,)], capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-1500:]
    assert json.loads(out.stdout.strip().splitlines()[-1]) == expected


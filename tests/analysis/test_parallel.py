"""The parallel map and the cached specialized kernel: identical results on 1 or 2 processes, on a
local Dask cluster (LocalCluster, 2 worker processes), and after a killed Dask worker.

Fast tier: the generated kernel against the generic one, its dependencies and fallback.  Process
tier: real worker processes (a local pool, a Dask cluster) under timeouts; every test stops what it
started.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from failclosed import import_or_require
from helpers.cli import tb_run

from testbed.analysis.parallel import Executor, run_batch, shutdown
from testbed.analysis.roa import nominal_roa
from testbed.analysis.sweep import sweep


def _sweep(sc, executor):
    return sweep(sc.make_plant(), sc.K, sc.quantizer, sc.x0, np.linspace(0.0, 2.0, 3), np.linspace(0.0, 0.4, 3),
                 kappa_F=1.0, kappa_D=0.2, seeds=2, horizon=10.0, executor=executor)


def _same_sweep(a, b):
    for k in a.kinds:
        for d in ("converged", "escaped", "lost"):
            np.testing.assert_array_equal(getattr(a, d)[k], getattr(b, d)[k])
    assert a.runs == b.runs


# ============================================================================ fast: the kernel cache
def test_specialized_kernel_is_cached_and_identical(paper):
    from testbed.sim import kernelcache
    from testbed.sim.batch import simulate_batch
    from testbed.sim.kernel import _batch_kernel

    plant = paper.make_plant()
    X0 = np.random.default_rng(1).uniform(-0.3, 0.3, (64, 2))
    th = paper.theta(120)[None]
    a = simulate_batch(plant, paper.K, paper.quantizer, X0, 120, theta=th)
    b = simulate_batch(plant, paper.K, paper.quantizer, X0, 120, theta=th, specialize=True)
    for f in ("x_final", "E_final", "status", "stop_k", "saturations", "mismatch", "max_norm", "attacked"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    run = kernelcache.specialized(_batch_kernel, {"rhs": type(plant).rhs, "rhs_m": type(plant).rhs})
    assert run is not _batch_kernel
    # the generated module is in the cache folder, named after a hash of its sources
    assert os.path.dirname(run.path) == str(kernelcache.cache_dir())
    assert run.dispatcher.stats.cache_path.startswith(str(kernelcache.cache_dir()))
    src = open(run.path).read()
    assert "rhs = _rhs_object.jit" in src and "def flow_into__rhs(" in src and "def zoom_update__rhs_m(" in src


def test_specialized_kernel_depends_on_every_source(paper):
    from testbed.sim import kernelcache
    from testbed.sim.kernel import _batch_kernel

    gen = kernelcache._Generator({"rhs": ("plants.lienard", "lienard_rhs"), "rhs_m": ("plants.lienard", "lienard_rhs")})
    gen.function(_batch_kernel, {"rhs": "rhs", "rhs_m": "rhs_m"}, top=True)
    root = os.path.dirname(os.path.dirname(os.path.dirname(kernelcache.__file__)))  # testbed/sim/kernelcache.py
    names = {os.path.relpath(f, root) for f in gen.files}
    for f in ("testbed/sim/kernel.py", "testbed/loop/quantizer.py", "testbed/loop/flow.py",
                              "testbed/loop/_dop853.py",
              "attackers/greedy.py"):
        assert f in names, f


_FLIP = r"""
import json, sys
from pathlib import Path
import plants
from testbed.sim import kernelcache
from testbed.sim.kernel import _batch_kernel

def flip(path):  # the case of the first letter of the file: one byte, and the source still parses
    data = bytearray(Path(path).read_bytes())
    i = next(i for i, c in enumerate(data) if chr(c).isalpha())
    data[i] ^= 0x20
    Path(path).write_bytes(bytes(data))

def path():
    kernelcache._memo.clear()  # the per-process memo is keyed on the objects, not on the sources
    p = plants.make("lienard")
    return kernelcache.specialized(_batch_kernel, {"rhs": type(p).rhs, "rhs_m": type(p).rhs}).path

base = path()
out = {"base": base, "flipped": {}}
for f in sys.argv[1:]:
    flip(f)
    out["flipped"][f] = path()
    flip(f)
    assert path() == base, f
print(json.dumps(out))
"""


@pytest.mark.slow  # a process per flipped source, each compiling the kernel
def test_a_flipped_byte_in_any_source_of_the_kernel_misses_the_cache(tmp_path):
    """A copy of the packages; one byte of each source the specialized kernel depends on flipped in turn
    (and flipped back): each flip gives a newly generated module (a cache miss), the flip back the first."""
    import shutil
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    for pkg in ("testbed", "plants", "attackers"):
        shutil.copytree(root / pkg, tmp_path / "src" / pkg, ignore=shutil.ignore_patterns("__pycache__"))
    src = tmp_path / "src"
    deps = [src / f for f in ("testbed/sim/kernel.py", "testbed/loop/quantizer.py", "testbed/loop/flow.py",
                              "testbed/loop/_dop853.py",
                              "attackers/greedy.py", "plants/lienard.py")]
    env = dict(os.environ, PYTHONPATH=str(src), TESTBED_CACHE_DIR=str(tmp_path / "cache"))
    r = subprocess.run([sys.executable, "-c", _FLIP, *map(str, deps)], capture_output=True, text=True, env=env,
                       cwd=tmp_path, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout)
    assert out["base"].startswith(str(tmp_path / "cache" / "kernels"))
    paths = [out["base"], *out["flipped"].values()]
    assert len(set(paths)) == len(deps) + 1, out  # every flip: another module
    assert set(os.listdir(tmp_path / "cache" / "kernels")) >= {os.path.basename(p) for p in paths}


def test_plant_without_module_level_rhs_falls_back(paper, caplog):
    from plants.base import rhs_function
    from testbed.sim import kernelcache
    from testbed.sim.kernel import _batch_kernel

    def local_rhs(x, u, p, dx):
        dx[0] = x[1]
        dx[1] = -x[0] + u[0]

    obj = rhs_function(local_rhs)
    with caplog.at_level(logging.WARNING, logger="testbed.sim.kernelcache"):
        assert kernelcache.specialized(_batch_kernel, {"rhs": obj, "rhs_m": obj}) is _batch_kernel
        assert kernelcache.specialized(_batch_kernel, {"rhs": obj, "rhs_m": obj}) is _batch_kernel
    lines = [r for r in caplog.records if "generic kernel" in r.getMessage()]
    assert len(lines) == 1 and "local_rhs" in lines[0].getMessage() and "module-level" in lines[0].getMessage()


def test_run_batch_chunks_do_not_change_results(paper):
    plant = paper.make_plant()
    rng = np.random.default_rng(2)
    X0 = rng.uniform(-0.5, 0.5, (40, 2))
    tab = rng.integers(0, 2, (5, 60)).astype(np.uint8)
    sidx = rng.integers(0, 5, 40)
    E0 = np.where(np.arange(40) % 3 == 0, 0.5, 0.1)
    one = run_batch(plant, paper.K, paper.quantizer, X0, 60, E0=E0, theta=tab, sched_idx=sidx, chunk=40)
    many = run_batch(plant, paper.K, paper.quantizer, X0, 60, E0=E0, theta=tab, sched_idx=sidx, chunk=7)
    for k in one:
        np.testing.assert_array_equal(one[k], many[k])


def test_workers_option_rejects_nonsense(capsys):
    from testbed.cli import main

    with pytest.raises(SystemExit) as e:
        main(["roa", "paper", "--workers", "0"])
    assert e.value.code == 2
    assert "--workers" in capsys.readouterr().err


# ============================================================================ process: local workers
@pytest.mark.process
def test_two_workers_match_one(paper):
    plant = paper.make_plant()
    try:
        ex = Executor(2)
        a = nominal_roa(plant, paper.K, paper.T, grid=31, horizon=20.0)
        b = nominal_roa(plant, paper.K, paper.T, grid=31, horizon=20.0, executor=ex, chunk=97)
        np.testing.assert_array_equal(a.inside, b.inside)
        assert a.digest == b.digest
        _same_sweep(_sweep(paper, None), _sweep(paper, ex))
    finally:
        shutdown()


@pytest.mark.process
def test_cli_roa_digest_is_the_same_for_1_and_2_workers():
    out = {}
    for w in ("1", "2"):
        p = tb_run("roa", "paper", "--grid", "41", "--horizon", "20", "--json", "--no-progress", "--workers", w,
                timeout=300)
        assert p.returncode == 0, p.stderr
        d = json.loads(p.stdout)
        assert d["parallel"]["workers"] == int(w)
        out[w] = d["roa"]["inside_digest"]
    assert out["1"] == out["2"] and out["1"].startswith("sha256:")


# ============================================================================ process: Dask
def _local_cluster():
    distributed = import_or_require("distributed", "dask")
    return distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0",
                                    env={"NUMBA_NUM_THREADS": "1"}, silence_logs=logging.ERROR)


def _worker_pids(client) -> dict:
    return client.run(os.getpid)


def _assert_gone(pids, timeout=30.0):
    t0 = time.monotonic()
    left = set(pids)
    while left and time.monotonic() - t0 < timeout:
        for p in list(left):
            try:
                os.kill(p, 0)
            except ProcessLookupError:
                left.discard(p)
            except PermissionError:
                pass
        if left:
            time.sleep(0.2)
    assert not left, f"Dask worker processes still running: {left}"


@pytest.mark.process
def test_dask_cluster_matches_one_worker(paper):
    plant = paper.make_plant()
    a = nominal_roa(plant, paper.K, paper.T, grid=31, horizon=20.0)
    sa = _sweep(paper, None)
    pids = {}
    with _local_cluster() as cluster:
        ex = Executor(scheduler=cluster.scheduler_address)
        try:
            assert ex.kind == "dask" and ex.workers == 2
            pids = _worker_pids(ex.client)
            b = nominal_roa(plant, paper.K, paper.T, grid=31, horizon=20.0, executor=ex, chunk=97)
            sb = _sweep(paper, ex)
        finally:
            ex.close()
    np.testing.assert_array_equal(a.inside, b.inside)
    _same_sweep(sa, sb)
    _assert_gone(pids.values())


@pytest.mark.process
def test_killed_dask_worker_chunks_are_retried(paper):
    plant = paper.make_plant()
    a = nominal_roa(plant, paper.K, paper.T, grid=41, horizon=30.0)
    killed = []
    pids = {}
    with _local_cluster() as cluster:
        ex = Executor(scheduler=cluster.scheduler_address)
        try:
            pids = _worker_pids(ex.client)
            sched = cluster.scheduler

            def kill_one(done, total):
                # after the first chunk: SIGKILL a worker that is running a chunk right now
                if killed or done >= total:
                    return
                t0 = time.monotonic()
                while time.monotonic() - t0 < 20:
                    for addr, ws in list(sched.workers.items()):
                        if ws.processing and addr in pids:
                            os.kill(pids[addr], signal.SIGKILL)
                            killed.append(pids[addr])
                            return
                    time.sleep(0.01)

            b = nominal_roa(plant, paper.K, paper.T, grid=41, horizon=30.0, executor=ex, chunk=60,
                            progress=kill_one)
            pids = _worker_pids(ex.client) | pids  # the nanny's replacement too
        finally:
            ex.close()
    assert killed, "no worker was running a chunk when the first one finished"
    np.testing.assert_array_equal(a.inside, b.inside)
    _assert_gone(pids.values())


@pytest.mark.process
def test_scheduler_that_does_not_answer_is_bad_input(capsys):
    import_or_require("distributed", "dask")
    from testbed.cli import main

    assert main(["roa", "paper", "--grid", "5", "--no-progress", "--scheduler", "tcp://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err
    assert "Dask scheduler" in err and len(err.strip().splitlines()) == 1

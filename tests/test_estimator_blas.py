"""The Python API's free run limits BLAS threads itself (``GPNARX.simulate`` in ``gpnarx.runtime.free_run_blas``),
as the CLI and the service do for their process, and gives the caller's settings back after."""
from __future__ import annotations

import numpy as np
import pytest
from threadpoolctl import threadpool_info, threadpool_limits

from gpnarx import runtime
from gpnarx.model.estimator import GPNARX


def blas_counts() -> set[int]:
    return {int(i["num_threads"]) for i in threadpool_info() if i.get("user_api") == "blas"}


@pytest.fixture()
def undecided(monkeypatch):
    """A process whose BLAS threads nobody set (a user's script), whatever tests ran before in this one."""
    monkeypatch.setattr(runtime, "_DECIDED", [])
    monkeypatch.delenv(runtime.BLAS_THREADS_ENV, raising=False)


def _spy(monkeypatch):
    seen = []
    step = GPNARX._run  # the free run itself (freerun.run through the estimator)

    def spied(self, *a, **kw):
        seen.append(blas_counts())
        return step(self, *a, **kw)

    monkeypatch.setattr(GPNARX, "_run", spied)
    return seen


def test_simulate_runs_on_one_blas_thread_and_restores_the_callers(sdof_model, sdof_data, undecided, monkeypatch):
    seen = _spy(monkeypatch)
    u = sdof_data["u2"][:120]
    with threadpool_limits(limits=3, user_api="blas"):  # what the caller has (OpenBLAS's default: every core)
        assert blas_counts() == {3}
        run = sdof_model.simulate(u, n_paths=8, seed=0)
        assert seen == [{1}]  # the free run: one thread (GPNARX_BLAS_THREADS' default)
        assert blas_counts() == {3}  # given back
        monkeypatch.setenv(runtime.BLAS_THREADS_ENV, "2")
        sdof_model.simulate(u, n_paths=8, seed=0)
        monkeypatch.setenv(runtime.BLAS_THREADS_ENV, "0")  # 0: BLAS as the caller has it
        sdof_model.simulate(u, n_paths=8, seed=0)
        assert seen[1:] == [{2}, {3}] and blas_counts() == {3}
    assert np.isfinite(run.mean).all()


def test_simulate_restores_the_callers_threads_when_it_raises(sdof_model, undecided, monkeypatch):
    def boom(self, *a, **kw):
        assert blas_counts() == {1}
        raise RuntimeError("step failed")

    monkeypatch.setattr(GPNARX, "_run", boom)
    with threadpool_limits(limits=3, user_api="blas"):
        with pytest.raises(RuntimeError, match="step failed"):
            sdof_model.simulate(np.zeros(50), n_paths=4)
        assert blas_counts() == {3}


def test_a_process_tuned_by_the_cli_or_service_is_left_alone(sdof_model, sdof_data, undecided, monkeypatch):
    seen = _spy(monkeypatch)
    monkeypatch.setattr(runtime, "_DECIDED", [0])  # e.g. --blas-threads 0: BLAS as it is
    with threadpool_limits(limits=3, user_api="blas"):
        sdof_model.simulate(sdof_data["u2"][:60], n_paths=4, seed=0)
    assert seen == [{3}]


def test_nested_and_concurrent_blocks_share_one_limit(undecided):
    with threadpool_limits(limits=3, user_api="blas"):
        with runtime.free_run_blas():
            with runtime.free_run_blas():
                assert blas_counts() == {1}
            assert blas_counts() == {1}  # the outer block still runs
        assert blas_counts() == {3}

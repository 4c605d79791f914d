"""The one parser of GPNARX_BLAS_THREADS / GPNARX_MMAP_THRESHOLD (gpnarx.runtime), shared by the
CLI, the Dask workers and the service settings."""
from __future__ import annotations

import pytest

from gpnarx.runtime import MiB, blas_threads_from_env, env_int, mmap_threshold_from_env
from gpnarx.service.settings import Settings


def test_defaults_and_values():
    assert blas_threads_from_env({}) == 1 and mmap_threshold_from_env({}) == 32 * MiB
    assert blas_threads_from_env({"GPNARX_BLAS_THREADS": " 0 "}) == 0
    assert blas_threads_from_env({"GPNARX_BLAS_THREADS": ""}) == 1
    assert mmap_threshold_from_env({"GPNARX_MMAP_THRESHOLD": "1_048_576"}) == MiB
    assert env_int("X", None, {"X": "-2"}, minimum=None) == -2


@pytest.mark.parametrize("raw, match", [("two", "must be an integer"), ("-1", "must be >= 0"),
                                        ("1.5", "must be an integer")])
def test_bad_values_name_the_variable(raw, match):
    with pytest.raises(ValueError, match=f"GPNARX_BLAS_THREADS {match}"):
        blas_threads_from_env({"GPNARX_BLAS_THREADS": raw})


def test_service_settings_read_the_same_way():
    env = {"GPNARX_BLAS_THREADS": "3", "GPNARX_MMAP_THRESHOLD": "1_048_576"}
    s = Settings.from_env(env)
    assert (s.blas_threads, s.mmap_threshold) == (blas_threads_from_env(env), mmap_threshold_from_env(env))
    with pytest.raises(ValueError, match="GPNARX_BLAS_THREADS must be an integer"):
        Settings.from_env({"GPNARX_BLAS_THREADS": "two"})

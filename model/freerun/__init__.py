"""The free run (section 2.2 step 3): the model's predicted output over a record, each predicted output fed back
as a lagged regressor, with its uncertainty propagated.

A run reads a ``Predictor``, the fitted model (posterior, scalers, lags, divergence limit; built once by
``GPNARX.predictor()``), and a ``RunSpec``, the call (method, backend, paths, seed, confidence, start, options);
``run(predictor, u, spec)`` hands both to the runner of (method, backend) in ``RUNNERS``:

* ``mc``, Monte Carlo (``mc``): P paths advance together, each step drawing y ~ N(mu, sigma_f^2 + sigma_y^2) from
  eq. 8-9 at every path (by a checked local model, ``mc_local``) and feeding it back; seeded. The band: the
  paths' quantiles (0.5 % and 99.5 % at 99 %).
* ``linear``, linearised (``linear``): first-order propagation of the lagged outputs' mean and covariance through
  the GP mean's Jacobian, var(y_i) = sigma_f^2 + sigma_y^2 + J S J^T; the band mean -/+ z std.

Both on numpy, or on JAX as compiled programs (``jax_backend``). Every run returns a ``FreeRun`` (``results``):
mean, std, the predictive band for the measured output y (sigma_y^2 included) and the latent band for the
noise-free output f, in output units, and the ``FreeRunState`` the next chunk of the record continues from.
``horizon.run_horizon``: the k-step-ahead prediction, the run restarted from the measured outputs every k samples
(``GPNARX.simulate(u, y=y, horizon=k)``; imported by the estimator, not a runner of ``RUNNERS``).
``simulate_mc`` and ``simulate_linear`` take a posterior, its scalers and lags instead of the predictor, and the
spec's fields as keywords. ``reference`` holds the Monte Carlo loop with eq. 8-9 at every path: the tests' and
benchmarks' baseline.
"""
from .linear import run_linear, simulate_linear
from .mc import run_mc, simulate_mc
from .results import FreeRun, FreeRunState, check_state
from .runners import METHODS, RUNNERS, check_method, run
from .spec import LAG_CLIP, VAR_CAP, Predictor, RunSpec

__all__ = ["FreeRun", "FreeRunState", "LAG_CLIP", "METHODS", "Predictor", "RUNNERS", "RunSpec", "VAR_CAP",
           "check_method", "check_state", "run", "run_linear", "run_mc", "simulate_linear", "simulate_mc"]

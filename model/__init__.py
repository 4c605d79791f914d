"""GP-NARX surrogate core (numpy/scipy only): the method.

Implements Teloli et al., "On the use of the GP-NARX model for predicting hysteresis effects of
bolted joint structures", MSSP 159 (2021) 107751, equations (1)-(14): NARX regressors, kernels,
ML-II, posteriors, free runs, metrics, cycles, novelty, PSD, restoring force. Files and objects
(bundles, the registry, fsspec, atomic writes, record files) are ``gpnarx.storage``.
Nothing in this package imports ``storage``, ``training`` or ``service``.
"""

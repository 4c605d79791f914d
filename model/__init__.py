"""GP-NARX surrogate core (numpy/scipy only).

Implements Teloli et al., "On the use of the GP-NARX model for predicting hysteresis effects of
bolted joint structures", MSSP 159 (2021) 107751, equations (1)-(14).
Nothing in this package imports ``training`` or ``service``.
"""

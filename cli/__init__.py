"""The ``gpnarx`` command line: one module per subcommand, on top of ``gpnarx.training`` and
``gpnarx.service``.

Every command builds the whole parser (all subcommand modules), so a subcommand module imports its
implementation (the pipeline, the simulators, the FastAPI app: scipy, scikit-learn, FastAPI) inside
the function that runs it: ``gpnarx --help`` or ``gpnarx simulate`` do not pay for ``gpnarx serve``.
Function-level imports in this package marked "start-up" follow that rule.
"""

"""The ``gpnarx`` command line: one module per subcommand, on top of ``gpnarx.training`` and
``gpnarx.service``."""

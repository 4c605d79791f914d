"""``python -m gpnarx``: the same as the ``gpnarx`` console script."""
import sys

from gpnarx.cli.main import main

sys.exit(main())

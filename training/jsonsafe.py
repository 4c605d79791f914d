"""Re-export of ``gpnarx.model.jsonsafe`` (the one JSON converter) for the training modules."""
from __future__ import annotations

from gpnarx.model.jsonsafe import to_json_safe

__all__ = ["to_json_safe"]

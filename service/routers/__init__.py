"""The service's routes, one router per group (``service.app.create_app`` includes them all).

==========  =================================================================================
health      GET /health/live, /health/ready, /metrics (open even when an API key is set)
models      GET /v1/models, /v1/models/{name}, /v1/models/{name}/versions/{version}
predict     POST /v1/models/{name}[/versions/{version}]/{predict|loops|novelty}
batch       POST /v1/batch
admin       POST /v1/admin/reload
history     GET /v1/models/{name}/novelty/history (novelty verdicts read back from the audit trail)
ui          GET /ui, /docs, /redoc, /static/...; GET .../report; POST /v1/records/parse
==========  =================================================================================
"""
from __future__ import annotations

from . import admin, batch, health, history, models, predict, ui

#: in the order the app includes them
ROUTERS = [health.router, models.router, history.router, predict.router, batch.router, admin.router, ui.pages,
           ui.router]

__all__ = ["ROUTERS", "admin", "batch", "health", "history", "models", "predict", "ui"]

"""What the training pipeline and the lag surface both build from a dataset config: the unfitted
model with the config's ``[model]`` settings, and records cut short for quick runs."""
from __future__ import annotations

from gpnarx.model.estimator import GPNARX
from gpnarx.model.record import Record, allowing_gaps
from gpnarx.training.config import ConfigError, DatasetConfig


def model_from_config(cfg: DatasetConfig, ny: int | None = None, nu: int | None = None, **overrides) -> GPNARX:
    """An unfitted GPNARX with the config's [model] settings (lags overridable)."""
    m = dict(cfg.model)
    m.update({k: v for k, v in overrides.items() if v is not None})
    ny = ny if ny is not None else m.get("ny")
    nu = nu if nu is not None else m.get("nu")
    if ny is None or nu is None:
        raise ConfigError(f"{cfg.path}: [model] ny and nu are required (choose them with 'gpnarx lags')")
    return GPNARX(ny=int(ny), nu=int(nu), kernel=m.get("kernel", "matern32+cubic"), mode=m.get("mode", "exact"),
                  n_inducing=int(m.get("inducing", 256)), max_train_points=m.get("max_train_points", 2000),
                  selection=m.get("selection", "stride"), n_restarts=int(m.get("restarts", 2)),
                  seed=int(m.get("seed", 0)), hyper=m.get("hyper", "subset"),
                  fit_backend=m.get("fit_backend", "numpy"))


def shorten(rec: Record, seconds: float) -> Record:
    """The first ``seconds`` of a record (the whole record when shorter); clean_y follows."""
    n = int(round(seconds * rec.fs))
    if n >= rec.n:
        return rec
    meta = dict(rec.meta)
    if meta.get("clean_y") is not None:
        meta["clean_y"] = meta["clean_y"][:n]
    with allowing_gaps():  # a part of a record already read: its NaN are the gaps the config allowed it
        return Record(rec.u[:n], None if rec.y is None else rec.y[:n], rec.fs, dict(rec.units), rec.name, meta)

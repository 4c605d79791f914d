"""The estimator parameter protocol of scikit-learn, without importing scikit-learn.

``sklearn.base.clone``, grid searches and pipelines need two methods of an estimator: ``get_params`` (the
``__init__`` keyword arguments, read back from the attributes of the same names) and ``set_params``. Inheriting
``sklearn.base.BaseEstimator`` gives them, but importing it loads scipy.stats and most of scikit-learn, about
half a second of every ``gpnarx`` command's start-up; ``ParamsMixin`` gives the same two methods with the
same behaviour (scikit-learn's documented duck-typed estimator API), so scikit-learn is imported only where a
user's own code uses it.
"""
from __future__ import annotations

import inspect


class ParamsMixin:
    """``get_params`` / ``set_params`` for a class whose ``__init__`` takes keyword-only parameters and stores
    each under its own name (scikit-learn's estimator convention)."""

    @classmethod
    def _param_names(cls) -> list[str]:
        """The names of ``__init__``'s parameters, sorted (as scikit-learn lists them)."""
        sig = inspect.signature(cls.__init__)
        names = []
        for p in list(sig.parameters.values())[1:]:
            if p.kind in (p.VAR_POSITIONAL, p.VAR_KEYWORD):
                raise TypeError(f"{cls.__name__}.__init__ must not take *args or **kwargs ({p})")
            names.append(p.name)
        return sorted(names)

    def get_params(self, deep: bool = True) -> dict:
        """The estimator's parameters, name -> value. ``deep``: also the parameters of parameters that are
        estimators themselves, as ``name__sub``."""
        out = {}
        for name in self._param_names():
            value = getattr(self, name)
            if deep and hasattr(value, "get_params") and not isinstance(value, type):
                out.update((f"{name}__{k}", v) for k, v in value.get_params().items())
            out[name] = value
        return out

    def set_params(self, **params):
        """Set parameters (``name__sub`` sets a parameter of a parameter); returns self. An unknown name is a
        ValueError naming the valid ones."""
        if not params:
            return self
        valid = self.get_params(deep=True)
        nested: dict[str, dict] = {}
        for key, value in params.items():
            name, sep, sub = key.partition("__")
            if name not in valid:
                raise ValueError(f"invalid parameter {name!r} for estimator {type(self).__name__}; valid "
                                 f"parameters are: {self._param_names()}")
            if sep:
                if not hasattr(valid[name], "set_params"):
                    raise ValueError(f"invalid parameter {key!r} for estimator {type(self).__name__}: {name} "
                                     f"({type(valid[name]).__name__}) has no parameters of its own")
                nested.setdefault(name, {})[sub] = value
            else:
                setattr(self, name, value)
                valid[name] = value
        for name, sub_params in nested.items():
            valid[name].set_params(**sub_params)
        return self

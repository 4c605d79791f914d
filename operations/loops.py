"""The loops operation: restoring-force loops of the predicted response, its band edges and the measured record,
and per-cycle dissipated energy and secant stiffness with intervals (a stream's cycles by ``cycle_stream``)."""
from __future__ import annotations

import math

import numpy as np

from gpnarx.model.cycles import cov_window_for, cycles
from gpnarx.model.restoring import loop_area, loop_units, restoring_force

from .base import CONFLICT, Operation, OperationError, carried, finite_or_none, head, is_stream
from .cycle_stream import STREAM_COV_WINDOW
from .cycle_stream import advance as stream_cycles


def physics_of(bundle) -> dict:
    """The bundle's physical constants for the restoring force: ``mass`` [kg, > 0], ``input_gain`` (force per
    input unit, default 1) and ``output`` ('displacement' or 'velocity'), with its other scalar entries."""
    phys = bundle.manifest.get("physics") or {}
    try:
        mass = float(phys["mass"])
    except (KeyError, TypeError, ValueError):
        raise OperationError(f"model {bundle.name}:{bundle.version} has no physical constants (mass) for the "
                             f"restoring force; loops are not available for it", kind=CONFLICT) from None
    gain = phys.get("input_gain", 1.0)
    output = phys.get("output", "displacement")
    if not (mass > 0 and math.isfinite(mass)) or output not in ("displacement", "velocity"):
        raise OperationError(f"model {bundle.name}:{bundle.version} has unusable physical constants "
                             f"(mass={mass!r}, output={output!r})", kind=CONFLICT)
    try:
        gain = float(gain)
    except (TypeError, ValueError):
        raise OperationError(f"model {bundle.name}:{bundle.version} has an unusable input_gain",
                             kind=CONFLICT) from None
    return {**{k: v for k, v in phys.items() if isinstance(v, (int, float, str, bool))},
            "mass": mass, "input_gain": gain, "output": output}


class Loops(Operation):
    name = "loops"

    def check_bundle(self, bundle) -> None:
        physics_of(bundle)

    def run_options(self, plan, req, u):
        # per-cycle energy intervals need every path / the covariance band
        model = plan.bundle.model
        window = (STREAM_COV_WINDOW if is_stream(plan, req)  # a stream's chunks keep one window
                  else cov_window_for(u, plan.bundle.fs, model.ny))
        return {"keep_paths": True} if plan.method == "mc" else {"cov_window": max(window, model.ny)}

    def answer(self, plan, req, u, y, run, common, flags, checkpoint):
        b = plan.bundle
        phys = physics_of(b)
        kw = dict(fs=b.fs, mass=phys["mass"], input_gain=phys["input_gain"], output=phys["output"])

        def loop(yy):
            x, r = restoring_force(u, yy, **kw)
            if not (np.all(np.isfinite(x)) and np.all(np.isfinite(r))):
                raise OperationError(*self.culprit(plan, req, u, "the restoring force is not finite for this "
                                                                 "record: "))
            return {"x": x, "force": r, "area": loop_area(x, r)}

        out = {**head(b), **common, "n_samples": int(u.size), "physics": phys,
               "units": loop_units(b.manifest.get("units"), phys),
               "predicted": loop(run.mean), "lower": loop(run.lower), "upper": loop(run.upper)}
        if y is not None:
            out["measured"] = loop(y)
        if checkpoint is not None:
            checkpoint()
        carry = None
        if is_stream(plan, req):  # the cycles completed so far, cut causally (cycle_stream)
            before = carried(plan, "loops") or {"position": int(run.state.position) - int(u.size)}
            try:
                done, carry = stream_cycles(before, u, run.mean, fs=b.fs, physics=phys, y=y, paths=run.paths,
                                            cov_band=run.cov_band, confidence=float(run.confidence))
            except ValueError as exc:
                raise OperationError(str(exc), "state") from None
            cyc = {"cycles": done, "basis": "stream", "frequency": None, "n_cycles": len(done), "steady_from": 0}
        else:
            cyc = cycles(u, b.fs, phys, run.mean, paths=run.paths, cov_band=run.cov_band, y=y,
                         confidence=float(run.confidence))
        out["cycles"] = [{k: (finite_or_none(v) if isinstance(v, float) else v) for k, v in c.items()}
                         for c in cyc["cycles"]]
        out["cycle_basis"] = {k: cyc[k] for k in ("basis", "frequency", "n_cycles", "steady_from")}
        return out, None, carry

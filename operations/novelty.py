"""The novelty operation: a measured record's score against the bundle's calibrated threshold, its verdict, and for
a stream the verdict over its rolling window (``novelty_window``)."""
from __future__ import annotations

from gpnarx.model.novelty import UnusableProbeContract, assess_novelty

from .base import CONFLICT, Operation, OperationError, carried, head, is_stream
from .novelty_window import HTTP_WINDOW_SECONDS, RollingWindow


def novelty_of(bundle) -> dict:
    """The bundle's novelty calibration (a dict with a numeric ``threshold``)."""
    nov = bundle.manifest.get("novelty")
    if not isinstance(nov, dict) or not isinstance(nov.get("threshold"), (int, float)):
        raise OperationError(f"model {bundle.name}:{bundle.version} has no novelty calibration: give it a threshold "
                             f"with 'gpnarx calibrate' on healthy records (or train it with 'healthy' records), or "
                             f"use a monitor bundle (the default registry's bert-real-monitor and "
                             f"bert-standin-monitor have one)", "name", kind=CONFLICT)
    return nov


class Novelty(Operation):
    name = "novelty"
    start = "measured"  # as the threshold was calibrated: from the record's measured start
    mc_paths_from = ("novelty", "predict")  # the paths the threshold was calibrated with, first

    def validate(self, req, bundle) -> None:
        if req.y is None:
            raise OperationError("y is required for novelty: the measured output record to score", "y")

    def check_bundle(self, bundle) -> None:
        novelty_of(bundle)

    def answer(self, plan, req, u, y, run, common, flags, checkpoint):
        b = plan.bundle
        nov = novelty_of(b)
        try:
            # a stream's later chunk continues a run begun by the probe's rule: no new start-up to judge
            rule = "measured" if plan.state is not None else self.started(plan, req)
            a = assess_novelty(nov, u, req.y, b.fs, run, start=rule, flags=flags)
        except UnusableProbeContract as exc:  # a malformed contract in the manifest: say so rather than guess
            raise OperationError(f"model {b.name}:{b.version} has an unusable probe contract: {exc}",
                                 kind=CONFLICT) from None
        except ValueError as exc:
            raise OperationError(f"cannot score this record: {exc}", "y") from None
        probe = {k: a.pop(k) for k in ("probe_match", "probe_reasons", "drive")}
        flagged = a.pop("out_of_range")
        out = {**head(b), **a, **common, "out_of_range": flagged, **probe}
        if not is_stream(plan, req):
            return out, None, None
        try:  # the stream's rolling window (novelty_window), carried in the token
            window = RollingWindow.from_carry(carried(plan, "novelty"), int(round(HTTP_WINDOW_SECONDS * b.fs)))
            window.add(u, req.y, run.mean, run.std, flags)
            out["novelty_window"] = window.assess(nov, b.fs)
        except UnusableProbeContract as exc:
            raise OperationError(f"model {b.name}:{b.version} has an unusable probe contract: {exc}",
                                 kind=CONFLICT) from None
        except ValueError as exc:
            raise OperationError(f"cannot score the stream's rolling window: {exc}", "state") from None
        return out, None, window.as_carry()

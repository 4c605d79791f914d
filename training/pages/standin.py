"""docs/standin.md, the BERT stand-in's page, from its stored calibration run (docs/runs/standin/calibration.json:
``calibration_table()`` of training/simulators/bert_standin.py against the real records, written by
``python -m studies.standin_page run docs/runs/standin``). Every figure on the page is a value of that run or computed
from it here (tests/test_results_pages.py re-renders the page)."""
from __future__ import annotations

from gpnarx.training.simulators.bert_standin import format_calibration_table


def render(calibration: dict) -> str:
    rows = calibration["rows"]
    worst = max(rows, key=lambda r: abs(r["error_pct"]))
    rest = [r for r in rows if r is not worst]
    near = min(rows, key=lambda r: abs(r["freq"] - 9.0))
    h3 = [r for r in rows if 6.0 <= r["freq"] <= 6.75]
    h3_ratio = sum(r["standin_h3"] for r in h3) / sum(r["real_h3"] for r in h3) if h3 else None
    page = (
        "# The BERT stand-in\n\n"
        "Rendered by `python -m studies.standin_page render docs/runs/standin docs/standin.md` from the stored "
        "calibration run (`docs/runs/standin/calibration.json`); do not edit by hand (a test re-renders this page). "
        "The simulator behind [results-bert-standin.md](results-bert-standin.md) "
        "(`training/simulators/bert_standin.py`, `gpnarx simulate bert-standin`); the protocol's own figures, and "
        "the bolt-loosening study of its monitor, are on that results page, from its run.\n\n"
        "**Stand-in numbers, never the rig's.** The real records are in [results-bert-real.md]"
        "(results-bert-real.md).\n\n"
        "## The simulator\n\n"
        "The lab subset lacks the paper's sweeps, torques and 50 realizations, so the product ships a documented "
        "stand-in: a single-mode hysteretic model (Bouc-Wen slip elements, softening, even contact term, a linear "
        "second mode) calibrated against the real records (`calibration_table()` recomputes this table from them: "
        "`python -m studies.standin_page run docs/runs/standin`). Fundamental velocity v1 at the rig's measured "
        "drive amplitude (least-squares harmonic fit over the steady part of each real record) and the 2x and 3x "
        "super-harmonics relative to it:\n\n"
        + format_calibration_table(rows) + "\n\n"
        f"- Largest amplitude error {worst['error_pct']:+.1f} % at {worst['freq']:.2f} Hz; the other sines within "
        f"{max(abs(r['error_pct']) for r in rest):.1f} %.\n"
        f"- The 2x super-harmonic at {near['freq']:.2f} Hz (the monitoring probe's frequency): stand-in "
        f"{near['standin_h2']:.2f} of the fundamental, rig {near['real_h2']:.2f}.\n")
    if h3_ratio is not None:
        page += (f"- The 3x super-harmonic at {h3[0]['freq']:.2f}-{h3[-1]['freq']:.2f} Hz is {100 * h3_ratio:.0f} % "
                 "of the rig's level.\n")
    page += (
        "\nThe torque law (5/7/9 N m) is assumed, not calibrated: loosening is modelled as LOWER torque (more slip, "
        "lower stiffness). Realization scatter: each realization draws its parameters log-normally around the "
        "nominal ones (the spreads and why they are small: the simulator's docstring, \"Why so small\"); "
        "`--scatter` (or `scatter` in a config `simulate` table) widens them to study larger day-to-day drift.\n\n"
        "## The monitoring probe\n\n"
        "`gpnarx reproduce bert-standin` also trains a monitoring bundle, `configs/bert-standin-monitor.toml` (a "
        "default bundle, so `gpnarx serve` offers its `novelty` route), probed by a steady sine at the rig's "
        "`Sine_09Hz` test: near half the first resonance the joint's even contact nonlinearity drives the 2x "
        "super-harmonic above, and the stand-in's torque law changes that term far more than realizations scatter "
        "it. The score is the RMS standardised residual of the measured record under the free-run band, started "
        "from the record's first ny measured outputs (`gpnarx.model.novelty`); the threshold is the (1 - "
        "false-alarm rate) quantile of a log-normal fit to healthy realizations, never below the largest of their "
        "scores. Its calibration and detection rates are on [results-bert-standin.md](results-bert-standin.md). "
        "Studies run by hand around this protocol (training-point selection, a larger realization scatter, other "
        "probes and scores) have no stored run; their figures are history, in "
        "[CHANGELOG.md](../CHANGELOG.md#history-of-published-figures).\n")
    return page

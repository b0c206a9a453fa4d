"""Dev helper (session 13) for ``dev_halmstad_sides.py`` and ``dev_regime_regs.py``: wraps MFR's
final fit so a registration keeps its one-sided and two-sided fits (``CAPTURE["one"]`` /
``["two"]``), and can answer with the one-sided fit alone (``MODE["answer"] = "one"``: the
two-sided fit is skipped, as if degenerate). Importing it installs the wrapper."""

from __future__ import annotations

from frslam_graph.registration.mfr import register as mfr_register

MODE = {"answer": "two"}
CAPTURE: dict = {}
_orig_final = mfr_register.fine.refine_final


def _final(pm, obs, screened, opts, *, walls=False):
    if walls and MODE["answer"] == "one":
        return screened  # -> the one-sided answer
    r = _orig_final(pm, obs, screened, opts, walls=walls)
    CAPTURE["two" if walls else "one"] = r
    return r


mfr_register.fine.refine_final = _final

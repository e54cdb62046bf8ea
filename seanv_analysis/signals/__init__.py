"""Signals of a run: alignment onto one clock (:mod:`.align`), the derived flow
and pressures (:mod:`.derive`) and the paper's run filters (:mod:`.filters`)."""
from .align import align_run, align_streams, interp_sorted

__all__ = ["align_run", "align_streams", "interp_sorted"]

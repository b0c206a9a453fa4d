"""Wheel-to-scan time offset: estimated online from the heading steps, applied only where significant.

A scan and the wheel pose logged with it need not describe the same instant. FR079's laser lines
carry the wheel pose of their stamp, but the scan was taken ~0.14 s earlier (a SICK LMS's serial
transfer of 180 beams takes ~0.1 s); ACES's scans ~0.09 s earlier than their stamp (its ODOM
records interpolated at the stamps). With the offset τ (s: the scan stamped t shows the robot the
wheels put at t + τ), each wheel heading step u_t between scans is off by τ (r_t - r_{t-1}), r the
wheels' turn rate over a step (rad/s): 5-8° per step on FR079 at a third of its scan rate.

Estimate (the linearised cross-correlation of the scan-matched and the wheel turn rates): the
scan-matched heading step s_t minus u_t regressed on x_t = r_t - r_{t-1}. Ordinary least squares
is biased: a wheel step's own noise enters x_t and, negated, the residual s_t - u_t (the
simulator, which has no offset, gave -0.019 s). The regressor is therefore instrumented by
z_t = r_{t+1} - r_{t-2}, the rate change measured on the neighbouring steps, which shares no step
noise with x_t or s_t - u_t (the simulator: |τ| < 0.001 s, within one sigma). Its uncertainty is
robust to correlated residuals (sums over blocks of ``BLOCK`` steps). The offset is applied only
when its two-sided ``LEVEL`` confidence interval (Student t over the blocks) excludes 0, from
``MIN_BLOCKS`` blocks on; else the wheel poses are used as logged.

Only a negative offset is applied: the wheel pose of the scan's instant then lies between the last
two logged ones (interpolation, which also averages their step noise). A positive one (the scan
shows a later instant than its wheel pose: ACES's laser-line poses, stale copies of the last ODOM
record, +0.10 ± 0.02 s) is estimated and reported, not applied: that wheel pose is not logged
yet, and extrapolating the last step by f = τ/dt of it multiplies the step noise's variance by
(1 + f)² + f² (ACES's laser-line poses with it: 0.0395 -> 0.0632 m).
"""

from __future__ import annotations

from collections import deque

import numpy as np

from frslam_graph.se2 import compose, exp, log

BLOCK = 25  # steps per block of the uncertainty's sums (longer than the residuals' correlation)
MIN_BLOCKS = 20  # blocks before the offset is tested (and applied)
LEVEL = 0.999  # two-sided confidence of the test that the offset is not 0
OUTLIER = np.deg2rad(10.0)  # rad; a larger scan-vs-wheel heading step is a wheel fault, not timing


class WheelTimeOffset:
    """Online estimate of the wheel-to-scan time offset τ (s) and the re-timing of wheel poses."""

    def __init__(self) -> None:
        self._hist: deque[tuple[float, float] | None] = deque(maxlen=4)  # (r, y) of recent steps
        self._n = 0  # samples in the open block
        self._bzx = self._bzy = 0.0  # open block: sum z x, sum z y
        self._szx = self._szy = 0.0  # closed blocks: sum z x, sum z y
        self._cxx = self._cxy = self._cyy = 0.0  # closed blocks: sums of block-sum products
        self.blocks = 0
        self.estimate = 0.0  # s
        self.sigma = 0.0  # s, standard error of estimate (0 before two blocks)
        self.applied = 0.0  # s, the offset the wheel poses are re-timed by

    def add(self, rate: float | None, residual: float = 0.0) -> None:
        """One step: the wheels' turn rate over it (rad/s) and the scan-matched heading step minus
        the wheel's (rad); ``rate`` None for a step that cannot tell (no wheel step taken, scan
        not held, unsteady clock): it breaks the sequence."""
        ok = rate is not None and np.isfinite(rate) and abs(residual) < OUTLIER
        self._hist.append((float(rate), float(residual)) if ok else None)
        if len(self._hist) < 4 or any(h is None for h in self._hist):
            return
        (r0, _), (r1, _), (r2, y), (r3, _) = self._hist  # steps t-2, t-1, t, t+1
        x, z = r2 - r1, r3 - r0
        self._bzx += z * x
        self._bzy += z * y
        self._n += 1
        if self._n == BLOCK:
            self._close_block()

    def _close_block(self) -> None:
        bx, by = self._bzx, self._bzy
        self._szx += bx
        self._szy += by
        self._cxx += bx * bx
        self._cxy += bx * by
        self._cyy += by * by
        self._n, self._bzx, self._bzy = 0, 0.0, 0.0
        self.blocks += 1
        if self._szx == 0.0:
            return
        tau = self._szy / self._szx
        ss = max(self._cyy - 2.0 * tau * self._cxy + tau * tau * self._cxx, 0.0)
        self.estimate, self.sigma = (
            tau,
            float(np.sqrt(ss * self.blocks / max(self.blocks - 1, 1))) / abs(self._szx),
        )
        self.applied = 0.0
        if self.blocks >= MIN_BLOCKS and tau < 0.0:
            from scipy.stats import t as student_t  # noqa: PLC0415

            if -tau > float(student_t.ppf(0.5 + LEVEL / 2.0, self.blocks - 1)) * self.sigma:
                self.applied = tau

    def retime(self, wheel: np.ndarray, step: np.ndarray, dt: float) -> np.ndarray:
        """The wheel pose at the scan's time: ``wheel`` (x, y, θ in odom) moved along its last step
        ``step`` (body frame, over ``dt`` s) back by the applied offset (< 0), at most one step."""
        if self.applied == 0.0 or dt <= 0.0:
            return wheel
        f = max(self.applied / dt, -1.0)
        return compose(wheel, exp(f * log(step)))

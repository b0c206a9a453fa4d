"""When to register the floor plan next (paper Alg. 3's registration triggers).

:class:`RegistrationSchedule` owns the attempt counters and answers :meth:`next_trigger` at each
keyframe from the mapped area (m²), the distance travelled (m) and the obstruction. Triggers, in
order: the first registration once the mapped area reaches ``first_register_area_m2``; the map
grew by ``register_min_growth_m2`` and ``REGISTER_GROWTH_FRAC``; progress obstructed (the map
grew by ``obstructed_min_growth_m2``, doubling by ``register_retry_backoff`` after each attempt an
obstruction triggered: a robot that stops often must not spend the run's ``max_registrations``
on maps that hardly grew); a quick recheck ``register_recheck_distance`` metres after
a match the checks rejected while none is accepted (up to ``register_recheck_max`` in a row); a
retry every ``register_retry_distance`` metres while none is accepted (doubling by
``register_retry_backoff`` on a map that has not grown, up to ``register_retry_max_distance``;
every other retry on the map of the last ``LOCAL_MAP_DISTANCE`` metres); a refinement every
``register_refine_distance`` metres once one is accepted (at most ``register_refine_max``);
``inconsistent_run`` relocalisations in a row inconsistent with the estimate.
"""

from __future__ import annotations

from dataclasses import dataclass

from frslam_graph.config import UpdatesConfig

# Fixed settings (config fields until issue 20; never changed by a test, tool or doc):
# fraction of the mapped area the map must also grow by before another registration; larger = fewer attempts
REGISTER_GROWTH_FRAC = 0.2
# m; every other retry registers on the map of the keyframes of the last this much travel (the whole map may
# have drifted too far)
LOCAL_MAP_DISTANCE = 40.0


@dataclass(frozen=True, slots=True)
class Trigger:
    """Why to register now; ``local``: on the map of the last ``LOCAL_MAP_DISTANCE`` metres;
    ``quick``: a quick recheck (counts towards ``register_recheck_max`` in a row);
    ``obstructed``: progress obstructed (the next one needs more growth)."""

    reason: str
    local: bool = False
    quick: bool = False
    obstructed: bool = False


class RegistrationSchedule:
    """The registration triggers and their counters (see the module docstring)."""

    #: relocalisations in a row inconsistent with the estimate that trigger a registration
    inconsistent_run: int = 5
    #: m² the map must have grown since the last attempt for the first obstruction to trigger one
    #: (times ``register_retry_backoff`` per obstruction-triggered attempt before)
    obstructed_min_growth_m2: float = 1.0

    def __init__(self, config: UpdatesConfig) -> None:
        self.config = config
        self.attempts = 0
        self._area_at_attempt = 0.0
        self.dist_at_attempt = 0.0
        self._retries = 0  # retries while none is accepted (every other one on the local map)
        self._stale_retries = 0  # retries in a row on a map that had not grown (backoff)
        self._recheck = False  # the last attempt matched but was rejected: retry soon
        self._recheck_run = 0  # quick retries in a row (register_recheck_max)
        self._refines = 0  # registrations triggered by register_refine_distance
        self._inconsistent = 0  # relocalisations in a row inconsistent with the estimate
        self._obstructed_attempts = 0  # attempts an obstruction triggered (their growth backs off)

    def next_trigger(self, area: float, dist: float, obstructed: bool, accepted: bool) -> Trigger | None:
        """The trigger of a registration at this keyframe, or None (it counts as taken)."""
        cfg = self.config
        if self.attempts >= cfg.max_registrations:
            return None
        if self.attempts == 0:
            if area >= cfg.first_register_area_m2:
                return Trigger(f"mapped area {area:.1f} m² reached the first-registration threshold")
            return None
        grown = area - self._area_at_attempt
        since = dist - self.dist_at_attempt
        if grown >= cfg.register_min_growth_m2 and grown >= REGISTER_GROWTH_FRAC * max(
            self._area_at_attempt, 1e-9
        ):
            self._stale_retries = 0
            return Trigger(f"mapped area grew by {grown:.1f} m² to {area:.1f} m²")
        if obstructed and grown >= self.obstructed_growth_m2():
            return Trigger("progress obstructed", obstructed=True)
        if self._recheck and cfg.register_recheck_distance > 0.0 and since >= cfg.register_recheck_distance:
            return Trigger(
                f"the last registration matched but was rejected; retry after {since:.0f} m", quick=True
            )
        if not accepted and since >= self._retry_distance():
            # the map has not grown since the last attempt: the next retry waits longer
            self._stale_retries = self._stale_retries + 1 if grown < cfg.register_min_growth_m2 else 0
            # the whole map may have drifted too far to match: alternate with the map of the last
            # LOCAL_MAP_DISTANCE metres
            local = self._retries % 2 == 1 and dist > LOCAL_MAP_DISTANCE
            self._retries += 1
            return Trigger(f"no registration accepted yet; retry after {since:.0f} m", local=local)
        if (
            accepted
            and cfg.register_refine_distance > 0.0
            and self._refines < cfg.register_refine_max
            and since >= cfg.register_refine_distance
        ):
            # the priors have corrected the map since: a registration on it may refine the
            # accepted one or show it wrong (retraction)
            self._refines += 1
            return Trigger(f"registration accepted; register again after {since:.0f} m")
        if self._inconsistent >= self.inconsistent_run:
            run, self._inconsistent = self._inconsistent, 0
            return Trigger(f"{run} relocalisations in a row inconsistent with the estimate")
        return None

    def attempted(self, trigger: Trigger, area: float, dist: float) -> None:
        """A registration is attempted now (any other trigger than a quick recheck starts a new
        run of rechecks)."""
        self.attempts += 1
        self._obstructed_attempts += trigger.obstructed
        self._recheck = False
        self._recheck_run = self._recheck_run + 1 if trigger.quick else 0
        self._area_at_attempt = area
        self.dist_at_attempt = dist

    def rejected(self, matched: bool, accepted: bool) -> None:
        """The attempt's registration was rejected: a match the checks rejected (wrong, or right on
        a map that drifted) gets a quick recheck on a map a few metres larger, while none is
        accepted (with one accepted, quick rechecks drew more wrong matches than they gained)."""
        self._recheck = matched and not accepted and self._recheck_run < self.config.register_recheck_max

    def relocalised(self, consistent: bool) -> None:
        """A relocalisation's prior passed the chi² gate (consistent) or failed it."""
        self._inconsistent = 0 if consistent else self._inconsistent + 1

    def obstructed_growth_m2(self) -> float:
        """m² the map must have grown since the last attempt for an obstruction to trigger one."""
        return self.obstructed_min_growth_m2 * self.config.register_retry_backoff**self._obstructed_attempts

    def _retry_distance(self) -> float:
        """Metres after an attempt before a retry while none is accepted."""
        cfg = self.config
        d = cfg.register_retry_distance * cfg.register_retry_backoff**self._stale_retries
        return min(d, max(cfg.register_retry_max_distance, cfg.register_retry_distance))


__all__ = ["RegistrationSchedule", "Trigger"]

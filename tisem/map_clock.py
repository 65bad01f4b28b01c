"""The map's clock: the time the decay runs on, and what a scan's stamp may do to it.

Map time is seconds since the map's first scan. The kernels see it as float32 (the scan's
time_rel_s, every voxel's t_last_rel), which resolves 1 ms for the first 2.3 hours, 1/64 s for
the first 36 hours and 1/8 s at MAX_MAP_SECONDS, the longest a map's clock may run.

A stamp (finite seconds, any epoch: `tisem.scan.checked_stamp`) moves map time as follows:

- forward by at most `max_step_s`: map time follows it exactly (stamp - t0);
- backward by at most `max_step_s` (messages out of order): no time passes;
- a jump of more than `max_step_s` either way is refused (ValueError), so one bad stamp costs
  that one scan: the decay cannot wipe the map, nor leave voxels stamped in the far future or
  past. When the next scan lands within `max_step_s` of the refused one, the jump was real and
  the clock takes it: forward, the gap counts (the map decays as over any gap); backward (a
  clock reset), no time passes.

`max_step_s` = max(MIN_STEP_S, tau ln 100): after the longest step taken unconfirmed at least
1 % of a voxel's evidence remains (for tau >= 2.2 s); unlimited when nothing decays (tau = 0
or inf), as the stamps then weigh nothing.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

MAX_MAP_SECONDS = float(2**20)  # ~12 days: float32 map times keep 1/8 s up to here
MIN_STEP_S = 10.0  # the shortest jump that needs a second scan to confirm it
KEEP_AT_LEAST = 0.01  # evidence left after the longest unconfirmed step


def max_step_for(decay_tau_s: float) -> float:
    """The longest stamp step a scan may take without a second scan confirming it."""
    if decay_tau_s == 0 or math.isinf(decay_tau_s):
        return math.inf
    return max(MIN_STEP_S, decay_tau_s * math.log(1.0 / KEEP_AT_LEAST))


@dataclass
class ClockState:
    """What the clock remembers (plain values: a checkpoint saves them).

    t0: the first scan's stamp (None before it); offset_s: map time minus (stamp - t0), changed
    only by a confirmed clock reset; latest_s: map time of the latest mapped scan; pending_s:
    (stamp - t0) + offset_s of a scan just refused for its jump, or None.
    """

    t0: float | None = None
    offset_s: float = 0.0
    latest_s: float = 0.0
    pending_s: float | None = None


class MapClock:
    """Map time for a stream of stamps: `time_of` checks a stamp and says its map time,
    `advance` records a mapped scan (nothing changes until then, so a scan refused for any
    other reason leaves the clock as it was)."""

    def __init__(self, decay_tau_s: float, state: ClockState | None = None):
        self.max_step_s = max_step_for(decay_tau_s)
        self.state = state or ClockState()

    @property
    def started(self) -> bool:
        return self.state.t0 is not None

    def time_of(self, stamp_s: float, where: str) -> float:
        """Map time of a scan at `stamp_s`; ValueError naming the scan (`where`) for a jump
        not confirmed yet (remembered, so that the next scan can confirm it) or a clock that
        would run past MAX_MAP_SECONDS."""
        st = self.state
        if st.t0 is None:
            return 0.0
        rel = (stamp_s - st.t0) + st.offset_s
        step = rel - st.latest_s
        if abs(step) > self.max_step_s:
            # (by another scan: the refused one tried again confirms nothing)
            confirmed = (
                st.pending_s is not None
                and rel != st.pending_s
                and abs(rel - st.pending_s) <= self.max_step_s
            )
            if not confirmed:
                st.pending_s = rel
                way = "after" if step > 0 else "before"
                raise ValueError(
                    f"{where}: stamp {stamp_s:.6f} s jumps {abs(step):.6g} s {way} the previous "
                    f"scan's; a jump over {self.max_step_s:.4g} s is taken only when the next "
                    f"scan confirms it (one bad stamp must not decay the map away)"
                )
            if step < 0:  # a clock reset: how much time passed is unknown, so none does
                return st.latest_s
        elif step < 0:  # a little out of order: no time passes
            return st.latest_s
        if rel > MAX_MAP_SECONDS:
            raise ValueError(
                f"{where}: the map's clock would reach {rel:.6g} s; a map spans at "
                f"most {MAX_MAP_SECONDS:.0f} s (~12 days: its times are float32 "
                f"seconds since the first scan); start a new map"
            )
        return rel

    def advance(self, stamp_s: float, map_time_s: float) -> None:
        """Record a mapped scan at `stamp_s` whose map time `time_of` gave as `map_time_s`."""
        st = self.state
        if st.t0 is None:
            st.t0 = float(stamp_s)
        else:
            # a confirmed reset moves the offset so that the stamp reads as map_time_s
            rel = (stamp_s - st.t0) + st.offset_s
            if rel < map_time_s - self.max_step_s:
                st.offset_s += map_time_s - rel
        st.latest_s = float(map_time_s)
        st.pending_s = None

    def to_dict(self) -> dict:
        return asdict(self.state)

    @classmethod
    def from_dict(cls, decay_tau_s: float, saved: dict) -> MapClock:
        """The clock `to_dict()` saved; ValueError for values that are not finite numbers."""
        state = ClockState()
        for key in ("t0", "offset_s", "latest_s", "pending_s"):
            value = saved.get(key, getattr(state, key))
            if value is None and key in ("t0", "pending_s"):
                continue
            if (
                isinstance(value, bool)
                or not isinstance(value, (int, float))
                or not math.isfinite(value)
            ):
                raise ValueError(f"map clock: {key} must be a finite number, got {value!r}")
            setattr(state, key, float(value))
        return cls(decay_tau_s, state)

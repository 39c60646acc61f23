"""Map a device's free-running clock onto the host clock the control loop runs on.

A device stamps each reading with its own counter (``device_time_us``, wrapping at 2**32 µs); the
host knows only when the bytes reached it. ``host_rx - device_time`` is the clock offset plus the
transport delay, and the delay is never negative, so the smallest value seen recently (the lower
envelope) is the offset plus the *minimum* delay. Mapping ``device_time + envelope`` therefore puts a
reading at the earliest instant it could have been seen, never in the future and never later than
its own arrival, and the loop's age of the reading includes the unavoidable transport latency.

The envelope is a minimum over a sliding window (``window_s``) rather than over all time, so it
follows crystal drift between the two clocks: at 100 ppm over a 2 s window the mapping errs by at
most 0.2 ms, against a stale-data limit of tens of ms.
"""

from __future__ import annotations

from collections import deque

from hardware.serial_tactile.driver import U32


class DeviceClock:
    def __init__(self, tick_s: float = 1e-6, wrap: int = U32, window_s: float = 2.0):
        if tick_s <= 0 or wrap <= 1 or window_s <= 0:
            raise ValueError("tick_s and window_s must be > 0 and wrap > 1")
        self.tick_s = tick_s
        self.wrap = wrap
        self.window_s = window_s
        self._raw: int | None = None
        self._ticks = 0  # unwrapped device time
        self._lags: deque[tuple[float, float]] = deque()  # (host_rx_s, host_rx_s - device_s), lags increasing
        self._last_mapped = float("-inf")

    def reset(self) -> None:
        """Forget the device's time base (it was replugged or restarted)."""
        self._raw = None
        self._ticks = 0
        self._lags.clear()

    def unwrap(self, raw: int) -> int:
        """Device time as an ever-increasing count (a step back of less than half a wrap is a step back)."""
        if self._raw is None:
            self._ticks = raw
        else:
            delta = (raw - self._raw) % self.wrap
            if delta >= self.wrap // 2:
                delta -= self.wrap
            self._ticks += delta
        self._raw = raw
        return self._ticks

    def map(self, raw: int, host_rx_s: float) -> float:
        """Host time of the device instant ``raw``, given that its reading arrived by ``host_rx_s``."""
        device_s = self.unwrap(raw) * self.tick_s
        lag = host_rx_s - device_s
        lags = self._lags
        while lags and lags[-1][1] >= lag:
            lags.pop()
        lags.append((host_rx_s, lag))
        horizon = host_rx_s - self.window_s
        while lags[0][0] < horizon:
            lags.popleft()
        mapped = min(device_s + lags[0][1], host_rx_s)
        # a newer reading never maps before an older one, whatever the envelope did meanwhile
        mapped = max(mapped, min(self._last_mapped, host_rx_s))
        self._last_mapped = mapped
        return mapped

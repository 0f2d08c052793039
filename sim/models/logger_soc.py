"""The SoC peripherals of the transaction-level logger model (hw/peripherals.py and the
top's ``logger`` window): LEDs with hardware activity, the debounced button, the RTC, the
watchdog, the GPS time capture, the events, and their registers.

:class:`SocPeripherals` is a mixin of :class:`~maglog.sim.models.logger.LoggerModel`: it
keeps its state on the model and uses the model's clock and event queue.
"""

from __future__ import annotations

import math

from ...hw.top import EVENT_NAMES, LOGGER_ID
from ...sw.bus import HardwareReset


__all__ = ["SocPeripherals"]

_INF = math.inf


class SocPeripherals:
    """The peripherals' behaviour and register handlers (``_r_<window>_<register>`` returns
    a read's fields, ``_w_<window>_<register>`` takes a write's)."""

    # -- behaviour -----------------------------------------------------------------------

    def _event(self, name):
        """An event's pulse: its bit in ``events.status`` is set until written with 1."""
        self._events.add(name)

    def _activity(self, k):
        """A kept frame of channel ``k`` lights its activity LED for the stretch (from the
        next clock; a new one starts the stretch again)."""
        self._act_until[k] = self.now + 1 + self._stretch
        self._update_leds()
        if not self._act_pending[k]:
            self._act_pending[k] = True
            self._schedule(self._act_until[k], self._activity_end, k)

    def _activity_end(self, k):
        if self.now < self._act_until[k]:
            self._schedule(self._act_until[k], self._activity_end, k)
            return
        self._act_pending[k] = False
        self._update_leds()

    def _update_leds(self):
        """``led`` as hw/peripherals.py's Leds drive it, recorded when it changes."""
        value = self._led_value
        lit = [self.now < until for until in self._act_until]
        led = (value & 0b1001) | ((value >> 1 & 1 | lit[0]) << 1) | \
            ((value >> 2 & 1 | lit[1]) << 2)
        if led != self._leds[-1][1]:
            self._leds.append((self.now_s, led))

    def _button_input(self, level):
        """The button pin changes; two clocks later the synchroniser's output follows."""
        self._schedule(self.now + 2, self._button_synced, level, hardware=False)

    def _button_synced(self, level):
        """The synchronised level changes: it must hold for the debounce time."""
        self._btn_sync = level
        self._btn_gen += 1
        if level != self._btn_level:
            self._schedule(self.now + self._debounce, self._button_settle, self._btn_gen)

    def _button_settle(self, generation):
        """The synchronised level has held for the debounce time (unless it changed since):
        the debounced level follows, and a rise is a press."""
        if generation != self._btn_gen:
            return
        self._btn_level = self._btn_sync
        if self._btn_level:
            self._event("button")

    def _watchdog_fire(self):
        """The watchdog expires: it resets all else, and the firmware."""
        self._wd_enable, self._wd_cause = 0, 1
        self._wd_deadline = _INF
        self.resets += 1
        self._reset_hardware()
        raise HardwareReset(f"watchdog reset at {self.now_s} s")

    def _watchdog_restart(self):
        """A kick or a write of ``control``: the count starts again (the watchdog is
        outside the logger's reset, so its expiry is kept apart from the event queue)."""
        self._wd_deadline = self.now + self._wd_timeout * self._prescaler + 2 \
            if self._wd_enable else _INF
        self._next_due = min(self._next_due, self._wd_deadline)

    # -- registers -----------------------------------------------------------------------

    # window logger
    def _r_logger_id(self):
        return {"magic": LOGGER_ID}

    def _r_logger_control(self):
        return {"record": self._record}

    def _w_logger_control(self, f):
        self._record = f["record"]

    def _r_logger_status(self):
        return {"in_frame": self._in_frame, "sdram_ready": int(self.now >= self._sdram_ready_at),
                "button": self._btn_level}

    def _r_logger_fw_status(self):
        return dict(self._fw_status)

    def _w_logger_fw_status(self, f):
        self._fw_status = {name: f[name] for name in ("state", "error", "file")}

    # window leds, button
    def _r_leds_value(self):
        return {"value": self._led_value}

    def _w_leds_value(self, f):
        self._led_value = f["value"]
        self._update_leds()

    def _r_button_status(self):
        return {"level": self._btn_level}

    # window rtc
    def _rtc_millis(self):
        return (self.now - self._rtc_set) // self._prescaler

    def _r_rtc_seconds(self):
        millis = self._rtc_millis()
        self._rtc_latched = millis % 1000
        return {"value": (self._rtc_base + millis // 1000) & 0xFFFFFFFF}

    def _w_rtc_seconds(self, f):
        self._rtc_base, self._rtc_set = f["value"], self.now

    def _r_rtc_subsec(self):
        return {"millis": self._rtc_latched}

    # window watchdog
    def _r_watchdog_control(self):
        return {"enable": self._wd_enable, "timeout_ms": self._wd_timeout}

    def _w_watchdog_control(self, f):
        self._wd_enable, self._wd_timeout = f["enable"], f["timeout_ms"]
        self._watchdog_restart()

    def _w_watchdog_kick(self, f):
        if f["kick"] and self._wd_enable:
            self._watchdog_restart()

    def _r_watchdog_status(self):
        return {"reset_cause": self._wd_cause}

    # window events
    def _r_events_status(self):
        return {name: int(name in self._events) for name in EVENT_NAMES}

    def _w_events_status(self, f):
        for name, value in f.items():
            if value:
                self._events.discard(name)

    # window gps
    def _r_gps_time(self):
        hour, minute, second = self._gps[:3] if self._gps else (0, 0, 0)
        return {"hour": hour, "minute": minute, "second": second}

    def _r_gps_date(self):
        day, month, year = self._gps[3:] if self._gps else (0, 0, 0)
        return {"day": day, "month": month, "year": year}

    def _r_gps_status(self):
        return {"valid": int(self._gps is not None)}

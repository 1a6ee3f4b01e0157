"""systemd's notification protocol (sd_notify), without a dependency: a datagram to the
socket in $NOTIFY_SOCKET. Outside systemd every call is a no-op."""

from __future__ import annotations

import os
import socket
import time


class Notifier:
    def __init__(self) -> None:
        address = os.environ.get("NOTIFY_SOCKET", "")
        self.enabled = bool(address)
        self._address = "\0" + address[1:] if address.startswith("@") else address
        self._socket = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) if self.enabled else None
        usec = int(os.environ.get("WATCHDOG_USEC", "0") or 0)
        # feed the watchdog at half its period, as sd_watchdog_enabled(3) advises
        self.watchdog_interval_s = usec / 2e6 if usec and self.enabled else 0.0
        self._last_feed = 0.0

    def notify(self, message: str) -> None:
        if self.enabled:
            try:
                self._socket.sendto(message.encode(), self._address)
            except OSError:
                pass

    def ready(self, status: str = "") -> None:
        self.notify("READY=1" + (f"\nSTATUS={status}" if status else ""))

    def stopping(self) -> None:
        self.notify("STOPPING=1")

    def feed(self, now: float | None = None) -> None:
        """Call from the control loop: pets the watchdog when due (so a hung loop is
        restarted by systemd)."""
        if self.watchdog_interval_s:
            now = time.monotonic() if now is None else now
            if now - self._last_feed >= self.watchdog_interval_s:
                self._last_feed = now
                self.notify("WATCHDOG=1")

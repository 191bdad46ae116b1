"""A clean stop on SIGINT or SIGTERM for the long-running commands (serve, record, the
server's ranks): a flag the main loop polls, set by the signal handler."""

from __future__ import annotations

import signal
import time


class SignalStop:
    """Set by SIGINT or SIGTERM: a clean stop (logs closed, sessions closed); `wait` and
    `is_set` as a threading.Event's. Not an Event: a signal handler runs in the main thread
    between two bytecodes, possibly inside Event.wait while it holds the event's lock, and
    Event.set would then wait for that lock forever (`serve --ranks 2` hung so on Ctrl-C)."""

    POLL_S = 0.05

    def __init__(self) -> None:
        self._set = False

    def set(self) -> None:
        self._set = True

    def is_set(self) -> bool:
        return self._set

    def wait(self, timeout: float | None = None) -> bool:
        deadline = None if timeout is None else time.monotonic() + timeout
        while not self._set:
            left = self.POLL_S if deadline is None else min(self.POLL_S,
                                                             deadline - time.monotonic())
            if left <= 0:
                break
            time.sleep(left)
        return self._set


def stop_on_signals() -> SignalStop:
    """A SignalStop that SIGINT and SIGTERM set from now on."""
    stop = SignalStop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop

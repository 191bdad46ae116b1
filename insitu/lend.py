"""Lent steps: `InSitu.publish(..., copy=False)` hands the caller's arrays to the sender
thread without copying them, as an ADIOS2 deferred put or an MPI_Isend does: the caller
must not change them until `InSitu.reclaim` returns (the sender has copied what the step's
messages read, on its own thread, or dropped them). Its fields may then also be functions of no argument that
return the array (e.g. `lambda: x - x0`), called on the sender thread, so the caller's
thread neither allocates nor computes them.

What a copied step checks in the caller's thread before `publish` returns (finite values,
ids >= 0, the shape of a computed field), a lent step's sender checks before it builds. A
bad lent step is not sent: the next `publish`, `reclaim` or `close` raises its ValueError.

`check_array`, `check_field` and `check_finite` are the checks both paths share.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable

import numpy as np

from minority.insitu.payload import BufferPool, Particles


class BadStep(ValueError):
    """A lent step whose arrays were bad (named in the message); it was not sent."""


def check_array(what: str, values) -> np.ndarray:
    """values as an array of real numbers; ValueError naming `what` otherwise."""
    a = values if isinstance(values, np.ndarray) else np.asarray(values)
    if a.dtype.kind not in "fiu":  # float, signed or unsigned integer
        raise ValueError(f"{what} must hold real numbers, got dtype {a.dtype}")
    return a


def check_field(name: str, values, n: int) -> np.ndarray:
    """A field's values as an [n] or [n, k] array of real numbers (n: the positions' count)."""
    a = check_array(f"field {name!r}", values)
    if a.ndim not in (1, 2) or a.shape[0] != n:
        raise ValueError(f"field {name!r} must be [n] or [n, k] with n = {n} (the positions' "
                         f"count), got shape {a.shape}")
    return a


def check_finite(what: str, a: np.ndarray) -> None:
    """Raise naming the first particle with a NaN or infinite value; one summing pass when
    all are finite (a sum that overflows is checked element by element)."""
    if not np.issubdtype(a.dtype, np.floating) or math.isfinite(float(a.sum())):
        return
    bad = ~np.isfinite(a.reshape(len(a), -1)).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{what}: particle {i} (row {i}) is not finite: {a[i].tolist()} "
                         f"({int(bad.sum())} such rows)")


def check_ids(ids: np.ndarray) -> None:
    if len(ids) and ids.min() < 0:
        raise ValueError(f"ids must be >= 0, got {int(ids.min())}")


def computed(p: Particles) -> Particles:
    """`p` with every field given as a function replaced by its array (called here, checked
    for shape and type); the rest as given."""
    if not any(callable(v) for v in p.fields.values()):
        return p
    fields = {name: check_field(name, v(), p.n) if callable(v) else v
              for name, v in p.fields.items()}
    return Particles(p.positions, p.ids, fields)


def checked(p: Particles) -> Particles:
    """`computed(p)`, with finite positions and fields and ids >= 0; ValueError naming the
    first bad one."""
    p = computed(p)
    check_finite("positions", p.positions)
    for name, values in p.fields.items():
        check_finite(f"field {name!r}", values)
    check_ids(p.ids)
    return p


class LentStep:
    """A lent step's particles, for the sender thread. The first `get` computes the field
    functions, copies what the step's messages read (`names`, into `pool`'s arrays), gives
    the caller's arrays back (`release`, the loan's, called once), then checks the copy
    (BadStep naming the step when it is bad): so the solver's next write waits for that copy
    alone, not for the culling and encoding. `use` once per message that reads the step,
    `done` when that message no longer needs it (built or dropped): the loan also ends once
    no message needs the step."""

    def __init__(self, step: int, particles: Particles, names, pool: BufferPool,
                 release: Callable[[], None]):
        self.step = step
        self._given: Particles | None = particles
        self._names = tuple(names)
        self._pool = pool
        self._release: Callable[[], None] | None = release
        self._users = 0
        self._lock = threading.Lock()
        self._ready: Particles | None = None
        self._error: BadStep | None = None
        # what the copy will hold at most: the caller's arrays it reads
        self.nbytes = particles.positions.nbytes + particles.ids.nbytes + sum(
            v.nbytes for v in particles.fields.values() if not callable(v))

    def use(self) -> Callable[[], None]:
        """One more message reads the step; returns its `done`."""
        with self._lock:
            self._users += 1
        return self.done

    def done(self) -> None:
        with self._lock:
            self._users -= 1
            last = self._users <= 0
        if last:
            self._give_back()

    def settle(self) -> None:
        """After the caller queued its messages: no message reads the step (none was
        made, e.g. Stats without a velocity): the loan ends now."""
        with self._lock:
            unused = self._users <= 0
        if unused:
            self._give_back()

    def _give_back(self) -> None:
        with self._lock:
            release, self._release, self._given = self._release, None, None
        if release is not None:
            release()

    def _copy(self) -> Particles:
        """What the step's messages read, copied (the functions' results kept: computed
        here); the caller's arrays are given back whether or not it succeeds."""
        try:
            given = self._given
            owned = {k for k, v in given.fields.items() if callable(v)}
            return computed(given).snapshot(self._names, self._pool, owned)
        finally:
            self._give_back()

    def get(self) -> Particles:
        if self._ready is None and self._error is None:
            try:
                self._ready = checked(self._copy())
            except ValueError as exc:
                self._error = BadStep(f"step {self.step}: {exc}")
        if self._error is not None:
            raise self._error
        return self._ready


class Loans:
    """How many queued messages still read lent arrays, and the first bad lent step not yet
    raised. `lend` once per message; its release function once when the message no longer
    reads them (built, dropped or discarded)."""

    def __init__(self):
        self._cond = threading.Condition()
        self._out = 0
        self._error: BadStep | None = None

    def lend(self) -> Callable[[], None]:
        with self._cond:
            self._out += 1
        done = False

        def release() -> None:
            nonlocal done
            with self._cond:
                if not done:
                    done = True
                    self._out -= 1
                    self._cond.notify_all()

        return release

    def bad(self, exc: BadStep) -> None:
        with self._cond:
            if self._error is None:
                self._error = exc

    def take_bad(self) -> BadStep | None:
        """The first bad lent step not taken yet (then forgotten)."""
        with self._cond:
            exc, self._error = self._error, None
        return exc

    def raise_bad(self) -> None:
        """Raise the first bad lent step not raised yet."""
        exc = self.take_bad()
        if exc is not None:
            raise exc

    def wait(self, timeout_s: float | None) -> float:
        """Wait until no message reads lent arrays; the seconds waited (0.0 when none did).
        TimeoutError when timeout_s (s) ran out first."""
        with self._cond:
            if not self._out:
                return 0.0
        t0 = time.perf_counter()
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        with self._cond:
            while self._out:
                left = None if deadline is None else deadline - time.monotonic()
                if left is not None and left <= 0:
                    raise TimeoutError(f"{self._out} message(s) still read lent arrays after "
                                       f"{timeout_s} s")
                self._cond.wait(left)
        return time.perf_counter() - t0

    @property
    def out(self) -> int:
        with self._cond:
            return self._out

"""The live view (`minority serve --http HOST:PORT`): what the render server's process shows
of each run as it happens, served over HTTP by render_server.live_http.

- The daemon calls `LiveView.observe` (its `ServerOptions.observer`) with the spec, every
  Frame, Timing, Event and Stats of each run, on its receive and render threads. The call only
  updates bounded state under a short lock and enqueues small messages: the newest frame per
  view (its PNG kept in memory, served at /live/{run}/{view}.png), per-step rows of Stats
  summed over ranks and of Timing summed over views (at most MAX_STEPS each), the last
  MAX_EVENTS events.
- Each browser subscribes its own bounded queue (live_http.ClientQueue). Frames and events
  are pushed as they come; the timeline (the Stats series against the spec's predicted
  events, and the timing series) is recomputed on the pusher thread, at most once per
  PUSH_INTERVAL_S, and pushed whole.

Moving particles follow the oracle's rule (gns.events, which render_server does not import):
faster than MOVING_SPEED_FRACTION of the peak speed scale, the SPEED_QUANTILE of the speeds,
here read from the Stats histograms and the peak taken over the run so far.
"""

from __future__ import annotations

import collections
import socket
import threading
from pathlib import Path
from typing import NamedTuple

import numpy as np

from minority.protocol.flow import MOVING_SPEED_FRACTION, histogram_quantile, moving_count
from minority.protocol.messages import SPEED_BINS, Event, Frame, Stats, Timing
from minority.protocol.spec import Spec
from minority.render_server.live_http import CLIENT_CAPACITY, ClientQueue, LiveServer, is_loopback, sse

MAX_RUNS = 16  # runs kept in memory (the oldest forgotten first)
MAX_STEPS = 2000  # Stats and Timing rows kept per run (the oldest steps forgotten first)
MAX_EVENTS = 200  # events kept per run
MAX_CLIENTS = 32  # browsers streaming at once (more: 503)
PUSH_INTERVAL_S = 0.5  # a run's timeline is pushed at most this often


class _StatsRow:
    """Stats of one step summed over the ranks that sent them."""

    __slots__ = ("time_s", "ranks", "count", "speed_sq", "max_disp", "hist")

    def __init__(self, time_s: float):
        self.time_s = time_s
        self.ranks: set[int] = set()
        self.count = 0
        self.speed_sq = 0.0  # m^2/s^2
        self.max_disp = 0.0  # m
        self.hist = np.zeros(SPEED_BINS, np.int64)


class _RunState:
    def __init__(self, seq: int, name: str):
        self.seq = seq  # order of first sight
        self.name = name  # the run instance: {run}, {run}.1, ...
        self.run = name
        self.views: list[dict] = []
        self.predicted: list[dict] = []
        self.frames: dict[str, Frame] = {}
        self.stats: collections.OrderedDict[int, _StatsRow] = collections.OrderedDict()
        self.timing: collections.OrderedDict[int, list] = collections.OrderedDict()
        self.events: collections.deque[dict] = collections.deque(maxlen=MAX_EVENTS)


def _frame_json(run: str, f: Frame) -> dict:
    return {"run": run, "view": f.view, "step": f.step, "time_s": f.time_s, "width": f.width,
            "height": f.height, "url": f"/live/{run}/{f.view}.png?step={f.step}"}


def _rounded(a) -> list[float]:
    return [float(f"{v:.6g}") for v in np.asarray(a, dtype=np.float64)]


def _put_bounded(rows: collections.OrderedDict, step: int, make):
    """The row of `step`, made when new (the oldest step forgotten past MAX_STEPS)."""
    row = rows.get(step)
    if row is None:
        row = rows[step] = make()
        if len(rows) > MAX_STEPS:
            rows.popitem(last=False)
    return row


class _Series(NamedTuple):
    """A run's rows, copied: Stats per step (summed over ranks) and Timing per step."""

    steps: list[int]
    time_s: np.ndarray  # [k] s
    count: np.ndarray  # [k] particles
    speed_sq: np.ndarray  # [k] sum |v|^2, m^2/s^2
    max_disp: np.ndarray  # [k] m
    ranks: list[int]  # [k] ranks that sent the step's stats
    hist: np.ndarray  # [k, SPEED_BINS] speed histogram
    timing_steps: list[int]
    timing: np.ndarray  # [j, 4] time_s, receive_s, setup_s, render_s


def _series(state: _RunState) -> _Series:
    steps = sorted(state.stats)
    rows = [state.stats[s] for s in steps]
    cols = np.array([(r.time_s, r.count, r.speed_sq, r.max_disp) for r in rows],
                    np.float64).reshape(-1, 4)
    tsteps = sorted(state.timing)
    return _Series(steps, cols[:, 0], cols[:, 1], cols[:, 2], cols[:, 3],
                   [len(r.ranks) for r in rows],
                   np.array([r.hist for r in rows], np.int64).reshape(-1, SPEED_BINS), tsteps,
                   np.array([state.timing[s][:4] for s in tsteps], np.float64).reshape(-1, 4))


def _timeline(name: str, s: _Series) -> dict:
    """Stats summed over ranks per step: time (s), particles, kinetic energy per unit
    particle mass 1/2 sum |v|^2 (J/kg), moving share, max displacement (m); timing per step:
    receive, setup and render (s, setup and render summed over the views)."""
    scale = histogram_quantile(s.hist) if s.steps else np.zeros(0)
    threshold = MOVING_SPEED_FRACTION * float(scale.max()) if s.steps else 0.0
    moving = moving_count(s.hist, threshold) if threshold > 0 else np.zeros(len(s.steps))
    return {"run": name,
            "stats": {"step": s.steps, "time_s": _rounded(s.time_s),
                      "particles": [int(c) for c in s.count], "ranks": s.ranks,
                      "kinetic_j_per_kg": _rounded(0.5 * s.speed_sq),
                      "moving_share": _rounded(moving / np.maximum(s.count, 1)),
                      "max_displacement_m": _rounded(s.max_disp),
                      "moving_speed_m_s": threshold},
            "timing": {"step": s.timing_steps, "time_s": _rounded(s.timing[:, 0]),
                       "receive_s": _rounded(s.timing[:, 1]), "setup_s": _rounded(s.timing[:, 2]),
                       "render_s": _rounded(s.timing[:, 3])}}


class LiveView:
    """The HTTP server and the state it shows; binds at construction (OSError: the address is
    in use or not this host's; ValueError: a host name that does not resolve)."""

    def __init__(self, out_dir: Path, host: str = "127.0.0.1", port: int = 0, *,
                 client_capacity: int = CLIENT_CAPACITY,
                 push_interval_s: float = PUSH_INTERVAL_S):
        self.out_dir = Path(out_dir)
        self.client_capacity = client_capacity
        self.push_interval_s = push_interval_s
        self._lock = threading.Lock()  # the run states and the client list
        self._runs: dict[str, _RunState] = {}
        self._seq = 0
        self._clients: list[ClientQueue] = []
        self.dropped_by_gone = 0  # drops of clients that have left
        self._dirty: set[str] = set()
        self._cond = threading.Condition()
        self._closing = threading.Event()
        self.httpd = LiveServer(host, port, self)
        self.loopback = is_loopback(host)
        self._threads = [threading.Thread(target=self.httpd.serve_forever, args=(0.2,),
                                          name="minority-live-http", daemon=True),
                         threading.Thread(target=self._push_loop, name="minority-live-push",
                                          daemon=True)]
        for t in self._threads:
            t.start()

    @property
    def url(self) -> str:
        host, port = self.httpd.server_address[:2]
        return f"http://{f'[{host}]' if ':' in host else host}:{port}/"

    @property
    def dropped(self) -> int:
        """Messages dropped for slow browsers, in all."""
        with self._lock:
            return self.dropped_by_gone + sum(c.dropped for c in self._clients)

    # --- the daemon's observer (returns at once) ---------------------------------------
    def observe(self, run_name: str, key: str, message: object) -> None:
        """ServerOptions.observer: take one message of run `run_name` (a run instance)."""
        with self._lock:
            state = self._state(run_name)
            if isinstance(message, Frame):
                state.frames[message.view] = message
                self._broadcast("frame", _frame_json(run_name, message))
            elif isinstance(message, Stats):
                row = _put_bounded(state.stats, message.step, lambda: _StatsRow(message.time_s))
                if message.rank not in row.ranks:  # a rank's stats count once per step
                    row.ranks.add(message.rank)
                    row.count += message.count
                    row.speed_sq += message.speed_sq_sum_m2_s2
                    row.max_disp = max(row.max_disp, message.max_displacement_m)
                    row.hist += message.hist_in_regions
                    row.hist += message.hist_elsewhere
                self._mark(run_name)
            elif isinstance(message, Timing):
                # time_s, receive_s, setup_s and render_s summed over the views, views
                row = _put_bounded(state.timing, message.step,
                                   lambda: [message.time_s, 0.0, 0.0, 0.0, 0])
                row[1] = max(row[1], message.receive_s)  # one receive per step
                row[2] += message.setup_s
                row[3] += message.render_s
                row[4] += 1
                self._mark(run_name)
            elif isinstance(message, Event):
                event = {"run": run_name, "event": str(message.kind), "rank": message.rank,
                         "message": message.message, "detail": message.detail,
                         "sent_ns": message.sent_ns}
                state.events.append(event)
                self._broadcast("event", event)
            elif isinstance(message, Spec):
                state.run = message.run
                state.views = [{"name": v.name, "width": v.width, "height": v.height,
                                "field": v.field} for v in message.views]
                state.predicted = [e.to_dict() for e in message.events]
                self._broadcast("run", self._run_json(state))

    def _state(self, name: str) -> _RunState:
        state = self._runs.get(name)
        if state is None:
            self._seq += 1
            state = self._runs[name] = _RunState(self._seq, name)
            if len(self._runs) > MAX_RUNS:
                del self._runs[min(self._runs.values(), key=lambda s: s.seq).name]
        return state

    def _broadcast(self, event: str, data: dict) -> None:
        message = sse(event, data)
        for client in self._clients:
            client.put(message)

    def _mark(self, name: str) -> None:
        with self._cond:
            self._dirty.add(name)
            self._cond.notify()

    # --- the timeline, on the pusher thread --------------------------------------------
    def _push_loop(self) -> None:
        while True:
            with self._cond:
                while not self._dirty and not self._closing.is_set():
                    self._cond.wait()
                dirty, self._dirty = self._dirty, set()
            if self._closing.is_set():
                return
            for name in sorted(dirty):
                timeline = self.timeline(name)
                if timeline is not None:
                    message = sse("timeline", timeline)
                    with self._lock:
                        for client in self._clients:
                            client.put(message)
            self._closing.wait(self.push_interval_s)  # at most one push per interval

    def timeline(self, name: str) -> dict | None:
        """The run's series as the page draws them (None for an unknown run)."""
        with self._lock:  # only copied under the lock: the observer waits for no arithmetic
            state = self._runs.get(name)
            series = None if state is None else _series(state)
        return None if series is None else _timeline(name, series)

    def state(self) -> dict:
        """Every run the server has seen (oldest first), with its newest frames and series."""
        with self._lock:
            runs = self._snapshot()
        return self._state_json(runs)

    def _snapshot(self) -> list[dict]:
        """Each run's state, its series copied, not computed (under the lock)."""
        return [{**self._run_json(s), "series": _series(s)}
                for s in sorted(self._runs.values(), key=lambda s: s.seq)]

    def _state_json(self, runs: list[dict]) -> dict:
        for r in runs:
            r["timeline"] = _timeline(r["name"], r.pop("series"))
        return {"runs": runs, "moving_speed_fraction": MOVING_SPEED_FRACTION,
                "out": str(self.out_dir)}

    @staticmethod
    def _run_json(state: _RunState) -> dict:
        return {"name": state.name, "run": state.run, "seq": state.seq, "views": state.views,
                "predicted": state.predicted, "events": list(state.events),
                "frames": {v: _frame_json(state.name, f) for v, f in state.frames.items()}}

    def newest_png(self, run: str, view: str) -> bytes | None:
        with self._lock:
            state = self._runs.get(run)
            frame = state.frames.get(view) if state is not None else None
            return None if frame is None else frame.png

    # --- browsers ------------------------------------------------------------------------
    def subscribe(self, connection: socket.socket | None = None) -> ClientQueue | None:
        """A new stream's queue, the full state queued first (None: MAX_CLIENTS streaming)."""
        with self._lock:
            if len(self._clients) >= MAX_CLIENTS or self._closing.is_set():
                return None
            client = ClientQueue(self.client_capacity, connection)
            self._clients.append(client)
            runs = self._snapshot()
        client.put_front(sse("state", self._state_json(runs)))  # before what came since
        return client

    def unsubscribe(self, client: ClientQueue) -> None:
        with self._lock:
            if client in self._clients:
                self._clients.remove(client)
                self.dropped_by_gone += client.dropped
        client.close()

    def close(self) -> None:
        """Stop serving: end every stream, the pusher and the listener (idempotent)."""
        if self._closing.is_set():
            return
        with self._cond:
            self._closing.set()
            self._cond.notify_all()
        with self._lock:
            clients = list(self._clients)
        for c in clients:
            c.close()
        self.httpd.shutdown()
        self.httpd.server_close()
        for t in self._threads:
            t.join()

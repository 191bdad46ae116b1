"""The live view's HTTP side (render_server.live holds the state it serves): the listener,
one thread per request, and each browser's bounded queue of server-sent events.

- GET /: the page (live_page.html); GET /events: the stream (ClientQueue: a full queue drops
  its oldest message and counts the drop, so a slow or vanished browser never slows the
  daemon; a keep-alive comment every KEEPALIVE_S); GET /api/state: every run's state as JSON
  (what /events sends first); GET /live/{run}/{view}.png: the newest frame; GET /api/index and
  /files/...: the --out directory, read-only (render_server.live_files).
- A server bound to loopback answers only requests whose Host header names loopback (no
  DNS-rebinding page reads it).
"""

from __future__ import annotations

import collections
import json
import socket
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlsplit

from minority.render_server import live_files

if TYPE_CHECKING:
    from minority.render_server.live import LiveView

CLIENT_CAPACITY = 256  # messages queued per browser
KEEPALIVE_S = 15.0  # an idle stream gets a comment line this often
SOCKET_TIMEOUT_S = 30.0  # a browser that takes no bytes this long is dropped
LOOPBACK_NAMES = {"localhost", "127.0.0.1", "::1"}


def is_loopback(host: str) -> bool:
    """`host` (a name or address, no port) names this machine's loopback."""
    return host in LOOPBACK_NAMES or host.startswith("127.")


def parse_address(text: str) -> tuple[str, int]:
    """'PORT', 'HOST:PORT' or '[IPV6]:PORT' -> (host, port); the host defaults to 127.0.0.1.
    Raises ValueError naming the problem."""
    host, sep, port = text.strip().rpartition(":")
    if not sep:
        host, port = "127.0.0.1", text.strip()
    if host.startswith("[") and host.endswith("]"):
        host = host[1:-1]
    elif ":" in host:
        raise ValueError(f"--http {text!r}: write an IPv6 address in brackets, [::1]:PORT")
    if not port.isdigit() or int(port) > 65535:
        raise ValueError(f"--http {text!r}: the port must be a number from 0 to 65535 (0: a "
                         "free one)")
    if not host:
        raise ValueError(f"--http {text!r}: no host before the colon (HOST:PORT or PORT)")
    return host, int(port)


class ClientQueue:
    """One browser's bounded queue of encoded server-sent events: a full queue drops its
    oldest message (counted in `dropped`); `written` counts what went to the socket."""

    def __init__(self, capacity: int = CLIENT_CAPACITY, connection: socket.socket | None = None):
        self.capacity = capacity
        self.connection = connection
        self.dropped = 0
        self.written = 0
        self.closed = False
        self._items: collections.deque[bytes] = collections.deque()
        self._cond = threading.Condition()

    def put(self, data: bytes) -> None:
        with self._cond:
            if self.closed:
                return
            if len(self._items) >= self.capacity:
                self._items.popleft()
                self.dropped += 1
            self._items.append(data)
            self._cond.notify()

    def put_front(self, data: bytes) -> None:
        """Queue `data` before everything queued (a full queue drops its oldest other)."""
        with self._cond:
            if len(self._items) >= self.capacity:
                self._items.popleft()
                self.dropped += 1
            self._items.appendleft(data)
            self._cond.notify()

    def get(self, timeout: float) -> bytes | None:
        """The next message, or None after `timeout` s or once closed."""
        with self._cond:
            if not self._items and not self.closed:
                self._cond.wait(timeout)
            return self._items.popleft() if self._items and not self.closed else None

    def __len__(self) -> int:
        return len(self._items)

    def close(self) -> None:
        """Wake the stream's thread and end its connection (a blocked write fails)."""
        with self._cond:
            self.closed = True
            self._items.clear()
            self._cond.notify_all()
        if self.connection is not None:
            try:
                self.connection.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass


def sse(event: str, data: dict) -> bytes:
    """One server-sent event (JSON data on one line)."""
    return f"event: {event}\ndata: {json.dumps(data, separators=(',', ':'), default=str)}\n\n".encode()


class LiveServer(ThreadingHTTPServer):
    """The listener of a LiveView (binds at construction; ValueError: a host name that does
    not resolve)."""

    daemon_threads = True

    def __init__(self, host: str, port: int, live: LiveView):
        try:
            info = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM)
        except socket.gaierror as exc:
            raise ValueError(f"--http: cannot resolve the host {host!r}: {exc.strerror}") from None
        self.address_family = info[0][0]
        self.live = live
        self.page = resources.files("minority.render_server").joinpath(
            "live_page.html").read_bytes()
        super().__init__(info[0][4][:2], _Handler)


class _Handler(BaseHTTPRequestHandler):
    server: LiveServer
    timeout = SOCKET_TIMEOUT_S
    server_version = "minority-live"

    def log_message(self, format, *args) -> None:  # noqa: A002 - the base class's name
        pass  # a request log would drown the daemon's own lines

    def do_GET(self) -> None:  # noqa: N802 - http.server's name
        live = self.server.live
        path = urlsplit(self.path).path
        if live.loopback and not self._local_host():
            return self._send(403, b"this live view answers to localhost only\n", "text/plain")
        if path in ("/", "/index.html"):
            return self._send(200, self.server.page, "text/html; charset=utf-8")
        if path == "/events":
            return self._stream(live)
        if path == "/api/state":
            return self._json(live.state())
        if path == "/api/index":
            return self._json(live_files.run_index(live.out_dir))
        if path.startswith("/live/") and path.endswith(".png") and path.count("/") == 3:
            _, _, run, view = path.split("/")
            png = live.newest_png(run, view.removesuffix(".png"))
            if png is not None:
                return self._send(200, png, "image/png")
        elif path == "/files" or path.startswith("/files/"):
            return self._file(live.out_dir, path.removeprefix("/files").lstrip("/"))
        self._send(404, b"not found\n", "text/plain")

    def _local_host(self) -> bool:
        """The Host header names this machine's loopback (no DNS-rebinding page reads it)."""
        host = (self.headers.get("Host") or "").strip()
        if host.startswith("["):
            host = host[1:host.find("]")]
        else:
            host = host.rsplit(":", 1)[0]
        return is_loopback(host)

    def _send(self, status: int, body: bytes, ctype: str, extra: dict | None = None) -> None:
        self.send_response(status)
        self.send_header("Content-Type", ctype)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", "no-store")
        self.send_header("X-Content-Type-Options", "nosniff")
        for k, v in (extra or {}).items():
            self.send_header(k, v)
        self.end_headers()
        self.wfile.write(body)

    def _json(self, obj: dict) -> None:
        self._send(200, json.dumps(obj, separators=(",", ":")).encode(), "application/json")

    def _stream(self, live: LiveView) -> None:
        client = live.subscribe(self.connection)
        if client is None:
            return self._send(503, b"too many live streams\n", "text/plain")
        try:
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(b"retry: 2000\n\n")
            reported = 0
            while not client.closed:
                data = client.get(KEEPALIVE_S)
                if client.closed:
                    break
                if client.dropped != reported:  # tell the page it missed some
                    reported = client.dropped
                    self.wfile.write(sse("dropped", {"dropped": reported}))
                self.wfile.write(data if data is not None else b": keep-alive\n\n")
                client.written += data is not None
        except OSError:  # the browser left, or took nothing for SOCKET_TIMEOUT_S
            pass
        finally:
            live.unsubscribe(client)

    def _file(self, root: Path, rel: str) -> None:
        target = live_files.resolve_in(root, rel)
        if target is None:
            return self._send(404, b"no such file under the output directory\n", "text/plain")
        if target.is_dir():
            if rel and not rel.endswith("/"):
                return self._send(301, b"", "text/plain", {"Location": self.path + "/"})
            return self._send(200, live_files.directory_page(root, target),
                              "text/html; charset=utf-8")
        try:
            f = open(target, "rb")  # noqa: SIM115 - closed below, after the response
        except OSError:
            return self._send(404, b"cannot read that file\n", "text/plain")
        with f:
            size = f.seek(0, 2)
            span = live_files.byte_range(self.headers.get("Range"), size)
            if span == "unsatisfiable":
                return self._send(416, b"", "text/plain", {"Content-Range": f"bytes */{size}"})
            start, end = span or (0, size)
            self.send_response(206 if span else 200)
            self.send_header("Content-Type", live_files.content_type(target))
            self.send_header("Content-Length", str(end - start))
            self.send_header("Accept-Ranges", "bytes")
            self.send_header("X-Content-Type-Options", "nosniff")
            if span:
                self.send_header("Content-Range", f"bytes {start}-{end - 1}/{size}")
            self.end_headers()
            f.seek(start)
            left = end - start
            while left > 0 and (block := f.read(min(left, 1 << 16))):
                self.wfile.write(block)  # a browser that leaves: the server ends the request
                left -= len(block)

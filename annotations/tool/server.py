"""HTTP front of the annotation tool, on h11 (a maintained, strict HTTP/1.1 implementation) and the standard
library's threaded TCP server: one thread per connection, at most :attr:`AnnotationServer.max_connections`.

Security model (the tool edits files on the annotator's disk):

* binds ``127.0.0.1`` by default;
* every request's ``Host`` header must name this server (``127.0.0.1:PORT``, ``localhost:PORT``,
  ``[::1]:PORT`` or the bound address): a DNS-rebinding page cannot talk to it;
* every write (``POST``) needs the per-launch token in the ``X-Bench4d-Token`` header, a JSON body,
  and, when the browser sends an ``Origin``, this server's own origin;
* bound to a loopback address, reads (the page, frames, masks, state) need no token: only this
  machine can connect. Bound to any other address, **every** request needs the token: the
  ``X-Bench4d-Token`` header, or the ``HttpOnly``, ``SameSite=Strict`` cookie the server sets when
  the page is opened with the printed ``/?token=...`` address (so that ``<img>`` loads carry it);
  the cookie alone never authorises a write;
* no CORS headers are ever sent (``OPTIONS`` is refused), so other origins cannot read responses;
* on loopback the page gets the token from the URL fragment the server prints (never sent over the
  network);
* clients name frames by index and queries by id; the server never opens a path a client sends.

Hostile or faulty clients (a request is bytes from anyone who can reach the port):

* framing is h11's (RFC 9112): a malformed request line or header (``Transfer-Encoding : chunked``, a
  space before the colon, a NUL, a line without a colon), an invalid or repeated ``Content-Length`` and
  an oversized head (:attr:`AnnotationServer.max_head_bytes`) are a 400 and the connection closes; a
  ``Transfer-Encoding`` of any kind is refused the same way (bodies carry a ``Content-Length``). A body
  the server does not accept is read and dropped when small and quick, else the connection closes:
  it is never parsed as a second request;
* time: the request line and headers must arrive within :attr:`AnnotationServer.header_timeout` seconds
  in all (not per read: a client trickling bytes is cut too); a body within
  :attr:`AnnotationServer.body_timeout` plus its size over :attr:`AnnotationServer.body_min_rate`; a
  refused body within :attr:`AnnotationServer.drain_seconds`;
* connections: a connection is *trusted* once one of its requests has shown the token. Connections not
  (yet) trusted are capped apart: at most :attr:`AnnotationServer.max_unauthenticated` of them, and at
  most :attr:`AnnotationServer.max_unauthenticated_per_client` from one address. When a new connection
  finds its pool full, the oldest untrusted connection that is only waiting (for a request, or for a
  refused body) is closed to make room; when every one is busy serving a request, the new connection is
  admitted on probation and served only if its first request shows the token: however many connections
  other local processes open, hold or keep busy, the token holder's next connection is served. Trusted
  connections are never closed for another;
* size: a body is at most :data:`MAX_BODY_BYTES` (an import: its upload limit in base64); its JSON is
  parsed strictly (:func:`parse_json_body`: no key twice, bounded nesting, no ``NaN`` or infinities,
  and lists, objects, strings and fractions counted before parsing, so that a body costs at most about
  eight times its bytes in memory, and bodies over a MiB are parsed one at a time); a route reads only its own keys (another key, or ``Box`` beside ``box``, is a 400);
* numbers in paths, queries and headers are ASCII digits; masks are checked before any decoder sees
  them; any malformed input is a 4xx with a one-line JSON error, never a traceback.
"""

from __future__ import annotations

import errno
import hmac
import ipaddress
import json
import math
import re
import secrets
import signal
import socket
import socketserver
import sys
import threading
import time
import traceback
from http import HTTPStatus
from pathlib import Path
from typing import Any, Callable, Optional
from urllib.parse import parse_qs, urlsplit

import h11

from benchmark.core.errors import InputError
from benchmark.core.imageio import NATIVE_STDERR_LOCK
from benchmark.core.strict import check_keys, container_budget, count_containers, loads

from .session import AnnotationSession, Conflict

STATIC_DIR = Path(__file__).resolve().parent / "static"
_CONTENT_TYPES = {".html": "text/html; charset=utf-8", ".js": "text/javascript; charset=utf-8",
                  ".css": "text/css; charset=utf-8", ".svg": "image/svg+xml"}
_SECURITY_HEADERS = {
    "Content-Security-Policy": ("default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob: data:; "
                                "connect-src 'self'; font-src 'none'; frame-ancestors 'none'; base-uri 'none'; "
                                "form-action 'none'"),
    "X-Content-Type-Options": "nosniff",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "Cross-Origin-Resource-Policy": "same-origin",
    "Cross-Origin-Opener-Policy": "same-origin",
}
MAX_BODY_BYTES = 16 * 1024 * 1024
"""Largest body of a write other than an import: a save of a checkerboard mask of a Neu3D frame (5.5 M
pixels, a run a pixel) is about 11 MiB; real masks need a few KiB."""
MAX_JSON_DEPTH = 32
"""Deepest nesting a request body may have (the deepest legitimate one, a save, has 5 levels)."""
BODY_CONTAINER_BYTES = 32
"""A body may hold one list or object per this many bytes (plus 4096): a save holds one list per mask."""
BODY_TEXT_BYTES = 16
"""A body may hold one string, and one non-integer number, per this many bytes (plus 65536 each): a save's
masks are lists of integers (run lengths; small ones are shared objects in Python), its strings are keys and
its fractions a box or clicks, while a list of short strings or fractions costs 10 to 20 bytes of memory per
byte of JSON."""
LARGE_BODY_BYTES = 1024 * 1024
"""Bodies above this size are parsed one at a time (a parsed body costs several times its bytes)."""
_LARGE_BODY_PARSE = threading.Lock()
DRAIN_BYTES = 1024 * 1024
"""A refused body up to this size is read and dropped (the connection stays usable); a larger one
closes the connection instead."""
TOKEN_HEADER = "X-Bench4d-Token"
_MAX_ERROR_CHARS = 400
_DIGITS = re.compile(r"[0-9]{1,15}")  # ASCII only: str.isdigit() also accepts '²' and '١'
_OBS_FOLD = re.compile(rb"\n[ \t]")
_HEAD_END = re.compile(rb"\r?\n\r?\n")
_CONTENT_LENGTH = re.compile(rb"(?im)^content-length[ \t]*:([^\r\n]*)")

ROUTE_KEYS = {
    "/api/save": ("revision", "changes", "timing"),
    "/api/queries/add": ("revision", "text", "kind", "base", "level"),
    "/api/queries/delete": ("revision", "query"),
    "/api/queries/reviewed": ("revision", "query"),
    "/api/segment": ("frame", "box", "clicks", "current"),
    "/api/propagate": ("query", "frame", "direction", "count"),
    "/api/export": ("format",),
    "/api/import": ("revision", "format", "filename", "data"),
}
"""The keys each write route reads (what the page sends); any other key is a 400."""


def _static_files() -> dict[str, Path]:
    """The whitelist of files the page may load: every file in ``static/``, by name."""
    return {p.name: p for p in STATIC_DIR.iterdir() if p.is_file() and p.suffix in _CONTENT_TYPES}


def needs_read_token(address: str) -> bool:
    """Whether a server bound to ``address`` must ask for the token on reads too: yes unless the
    address is a loopback one (then only this machine can connect). Unknown forms count as exposed."""
    try:
        ip = ipaddress.ip_address(address.strip("[]").split("%", 1)[0])
    except ValueError:
        return address != "localhost"
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return not ip.is_loopback


def _is_loopback(address: str) -> bool:
    try:
        ip = ipaddress.ip_address(address.split("%", 1)[0])
    except ValueError:
        return False
    if isinstance(ip, ipaddress.IPv6Address) and ip.ipv4_mapped is not None:
        ip = ip.ipv4_mapped
    return ip.is_loopback


def _ascii_int(text: Optional[str], field: str) -> Optional[int]:
    """``None`` for a missing value, else the value as ASCII digits (an :class:`InputError` if not)."""
    if text is None:
        return None
    if not _DIGITS.fullmatch(text):
        raise InputError(None, field, "expected a non-negative integer in ASCII digits")
    return int(text)


def _finite_numbers(obj: Any) -> bool:
    """No NaN or infinity anywhere in a parsed body (iterative: no recursion)."""
    stack = [obj]
    while stack:
        node = stack.pop()
        if isinstance(node, float):
            if not math.isfinite(node):
                return False
        elif isinstance(node, dict):
            stack.extend(node.values())
        elif isinstance(node, list):
            stack.extend(node)
    return True


def parse_json_body(raw: bytes | bytearray | str) -> Any:
    """Strict JSON of a request body (:func:`benchmark.core.strict.loads`): UTF-8, no key twice, nesting at
    most :data:`MAX_JSON_DEPTH`, lists and objects counted before parsing (at most one per
    :data:`BODY_CONTAINER_BYTES` bytes), no ``NaN`` or infinities; else :class:`InputError` on ``body``."""
    try:
        text = raw if isinstance(raw, str) else raw.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(None, "body", "not valid JSON (not UTF-8)") from None
    budget = container_budget(len(text), BODY_CONTAINER_BYTES, 4096)
    if count_containers(text) > budget:
        raise InputError(None, "body", f"more than {budget} lists and objects for {len(text)} bytes: not a "
                                       "request this server reads")
    values = container_budget(len(text), BODY_TEXT_BYTES, 65536)
    strings = text.count('"') // 2  # an upper bound (escaped quotes count too)
    fractions = text.count(".") + text.count("e") + text.count("E")  # an upper bound on non-integer numbers
    if strings > values or fractions > values:
        raise InputError(None, "body", f"more than {values} strings or fractions for {len(text)} bytes: not a "
                                       "request this server reads")
    try:
        obj = loads(text, None, max_depth=MAX_JSON_DEPTH, containers=budget)
    except InputError as err:
        raise InputError(None, "body", f"not valid JSON ({err.message}"
                                       f"{'' if not err.field else ' at ' + err.field})") from None
    if not _finite_numbers(obj):
        raise InputError(None, "body", "not valid JSON (NaN and infinities are not JSON numbers)")
    return obj


def _one_line(text: str) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= _MAX_ERROR_CHARS else text[:_MAX_ERROR_CHARS - 3] + "..."


class _Refused(Exception):
    """A request answered with an error before its body was read."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


class _Closed(Exception):
    """The peer closed the connection (or it was closed to make room for another)."""


class _Connection:
    """One accepted connection, as the server's bookkeeping sees it."""

    def __init__(self, sock: socket.socket, peer: str):
        self.sock = sock
        self.peer = peer
        self.trusted = False
        """Whether one of its requests has shown the token (then it is never closed for another)."""
        self.waiting = True
        """Whether it only waits (for a request, for a refused body to end, or for the client to take an
        answer): then, untrusted, it may be closed for another."""
        self.opened = time.monotonic()
        self.closed = False
        self.probation = False
        """Admitted past a full untrusted pool whose connections were all busy: its first request must show
        the token (it then joins the trusted pool) or it is answered 503 and closed unserved."""

    def close_for_another(self) -> None:
        """Wake its thread with end-of-stream (``shutdown``): it ends without another request."""
        self.closed = True
        try:
            self.sock.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass


class AnnotationServer(socketserver.ThreadingMixIn, socketserver.TCPServer):
    """A threaded HTTP server bound to one :class:`AnnotationSession` (module docstring)."""

    daemon_threads = True
    allow_reuse_address = True
    request_queue_size = 64
    header_timeout = 10.0
    """Seconds a client has to send the request line and headers (and a kept-alive connection may idle)."""
    body_timeout = 30.0
    """Seconds a client has to send a body, plus its size divided by :attr:`body_min_rate`."""
    body_min_rate = 1024 * 1024
    """Bytes per second a large upload must at least average."""
    drain_seconds = 2.0
    """Seconds a refused body (small enough to drop) has to arrive; past them the connection closes."""
    write_timeout = 60.0
    """Seconds the server waits for a client to take one response."""
    max_connections = 64
    """Connections served at once, trusted and not (each holds a thread); a browser opens about six."""
    max_unauthenticated: Optional[int] = None
    """Connections not (yet) trusted served at once; ``None``: half of :attr:`max_connections`. The rest are
    kept for the token holder's."""
    max_unauthenticated_per_client: Optional[int] = None
    """Untrusted connections from one address other than a loopback one; ``None``: half of
    :attr:`max_unauthenticated` (at least 1). Every local process shares the loopback address, the token
    holder's browser among them: there the pool's eviction rule alone applies."""
    probation_connections = 4
    """Connections admitted past a full untrusted pool whose connections are all busy (serving requests,
    not waiting): each must show the token in its first request. However busy other processes keep their
    connections, the token holder's next connection is served."""
    max_head_bytes = 16 * 1024
    """Largest request line plus headers."""
    linger_seconds = 1.0
    """After refusing a body it does not read, the server reads and drops what is in flight this
    long before closing, so that the client gets the answer instead of a reset connection."""

    def __init__(self, session: AnnotationSession, host: str = "127.0.0.1", port: int = 0,
                 token: Optional[str] = None, extra_hosts: tuple[str, ...] = (), *,
                 read_token: Optional[bool] = None):
        if ":" in host.strip("[]"):
            self.address_family = socket.AF_INET6
        self._conns: list[_Connection] = []
        self._conn_of: dict[int, _Connection] = {}
        self._conns_lock = threading.Lock()
        super().__init__((host.strip("[]"), port), _Handler)
        self.session = session
        self.token = token or secrets.token_urlsafe(24)
        self.host = host
        self.port = self.server_address[1]
        self.read_token = needs_read_token(str(self.server_address[0])) if read_token is None else bool(read_token)
        """Whether reads need the token too (off loopback; see the module docstring)."""
        self.cookie_name = f"bench4d_token_{self.port}"  # cookies ignore ports: one name per server
        names = {"127.0.0.1", "localhost", "[::1]", host if ":" not in host else f"[{host.strip('[]')}]"}
        names.update(extra_hosts)
        self.allowed_hosts = {f"{n}:{self.port}".lower() for n in names}
        self.static = _static_files()

    @property
    def url(self) -> str:
        """Address to open. On loopback the token is in the fragment (the browser never sends it
        anywhere); off loopback it is in the query, which the server swaps for a cookie at once."""
        shown = self.host if ":" not in self.host else f"[{self.host.strip('[]')}]"
        if shown in ("0.0.0.0", "[::]"):
            shown = "127.0.0.1"
        if self.read_token:
            return f"http://{shown}:{self.port}/?token={self.token}"
        return f"http://{shown}:{self.port}/#token={self.token}"

    # -- the connection pools --------------------------------------------------------------------
    def _untrusted_caps(self) -> tuple[int, int]:
        pool = self.max_unauthenticated if self.max_unauthenticated is not None else max(1, self.max_connections // 2)
        pool = max(1, min(pool, self.max_connections))
        per = self.max_unauthenticated_per_client
        per = max(1, pool // 2) if per is None else max(1, min(per, pool))
        return pool, per

    def _admit(self, sock: socket.socket, peer: str) -> Optional[_Connection]:
        """Register a new (untrusted) connection, closing the oldest waiting untrusted one of its client or
        of the pool to make room. Where every one of them is busy, the new connection is admitted on
        probation (:attr:`_Connection.probation`), closing the oldest waiting probation connection if those
        are all taken; ``None`` only when they are all busy too."""
        pool, per = self._untrusted_caps()
        victim = None
        probation = False
        with self._conns_lock:
            live = [c for c in self._conns if not c.closed]
            untrusted = [c for c in live if not c.trusted and not c.probation]
            same = [c for c in untrusted if c.peer == peer]
            crowd = None
            if len(untrusted) >= pool or len(live) >= self.max_connections:
                crowd = untrusted
            elif len(same) >= per and not _is_loopback(peer):
                crowd = same
            if crowd is not None:
                idle = [c for c in crowd if c.waiting]
                if not idle:  # all busy: on probation, in a small pool of its own
                    probation = True
                    on_probation = [c for c in live if c.probation and not c.trusted]
                    if len(on_probation) >= self.probation_connections:  # full: its oldest waiting one goes
                        idle = [c for c in on_probation if c.waiting]
                        if not idle:
                            return None
                if idle:
                    victim = min(idle, key=lambda c: c.opened)
                    victim.closed = True
            conn = _Connection(sock, peer)
            conn.probation = probation
            self._conns.append(conn)
        if victim is not None:
            victim.close_for_another()
        return conn

    def _trust(self, conn: _Connection) -> bool:
        """Move ``conn`` to the trusted pool (it showed the token); False when that pool is full."""
        pool, _ = self._untrusted_caps()
        with self._conns_lock:
            if conn.trusted:
                return True
            trusted = sum(1 for c in self._conns if c.trusted and not c.closed)
            if trusted >= max(1, self.max_connections - pool):
                return False
            conn.trusted = True
            conn.probation = False
            return True

    def _forget(self, conn: _Connection) -> None:
        with self._conns_lock:
            self._conn_of.pop(id(conn.sock), None)
            conn.closed = True
            if conn in self._conns:
                self._conns.remove(conn)

    def process_request(self, request, client_address) -> None:
        peer = str(client_address[0]) if isinstance(client_address, tuple) and client_address else "?"
        conn = self._admit(request, peer)
        if conn is None:
            self._refuse_connection(request)
            return
        with self._conns_lock:
            self._conn_of[id(request)] = conn  # taken by the connection's handler
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._forget(conn)
            raise

    def _refuse_connection(self, request: socket.socket) -> None:
        """503 on the accepting thread: short, and never blocking it for long."""
        body = b'{"error":"too many connections; retry"}'
        try:
            request.settimeout(0.2)
            request.sendall(b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json\r\n"
                            b"Content-Length: %d\r\nRetry-After: 1\r\nConnection: close\r\n\r\n%s" % (len(body), body))
        except OSError:
            pass
        self.shutdown_request(request)

    def handle_error(self, request, client_address) -> None:
        # a client that vanishes mid-request is routine; anything else is a bug worth a traceback
        if isinstance(sys.exc_info()[1], OSError):
            return
        super().handle_error(request, client_address)


class _Request:
    """What the routes see of one request."""

    def __init__(self, event: h11.Request):
        self.command = event.method.decode("ascii", "replace")
        self.path = event.target.decode("ascii", "replace")
        self.headers: dict[str, list[str]] = {}
        for name, value in event.headers:
            self.headers.setdefault(name.decode("ascii").lower(), []).append(value.decode("latin-1"))

    def header(self, name: str) -> Optional[str]:
        values = self.headers.get(name.lower())
        return values[0] if values else None

    def all(self, name: str) -> list[str]:
        return self.headers.get(name.lower(), [])


class _Handler(socketserver.BaseRequestHandler):
    """One connection: requests read with h11 until it closes."""

    server: AnnotationServer

    # -- the connection --------------------------------------------------------------------------
    def setup(self) -> None:
        with self.server._conns_lock:
            conn = self.server._conn_of.pop(id(self.request), None)
        self.conn: _Connection = conn or _Connection(self.request, "?")
        self.h11 = h11.Connection(h11.SERVER, max_incomplete_event_size=self.server.max_head_bytes)
        self.req: Optional[_Request] = None
        self._linger = False
        self._head = b""
        """The bytes of the request head being read (for the checks h11 leaves to the server)."""
        self._reading_head = False

    def finish(self) -> None:
        self.server._forget(self.conn)
        if self._linger:
            self._linger_close()

    def handle(self) -> None:
        try:
            while not self.conn.closed:
                if not self._one_request():
                    break
        except (_Closed, OSError):
            pass

    def _recv(self, deadline: float) -> None:
        left = deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("request not received in time")
        self.request.settimeout(min(left, 3600.0))
        try:
            data = self.request.recv(65536)
        except socket.timeout:
            raise TimeoutError("request not received in time") from None
        if self.conn.closed:
            raise _Closed()
        if self._reading_head and len(self._head) <= self.server.max_head_bytes:
            self._head += data
        self.h11.receive_data(data)

    def _next_event(self, deadline: float):
        """The next h11 event, reading until ``deadline``; a malformed stream raises :class:`_Refused` (400)."""
        while True:
            try:
                event = self.h11.next_event()
            except h11.RemoteProtocolError as err:
                status = err.error_status_hint if 400 <= err.error_status_hint < 500 else 400
                # h11's reason without the bytes it quotes (a request is never echoed back)
                raise _Refused(status, f"malformed request: {str(err).split(':', 1)[0][:80]}") from None
            if event is h11.NEED_DATA:
                self._recv(deadline)
                continue
            return event

    def _one_request(self) -> bool:
        """Read and answer one request; False when the connection is to close."""
        self.conn.waiting = True
        self.req = None
        self._head = bytes(self.h11.trailing_data[0])  # what an earlier read brought of this request
        self._reading_head = True
        try:
            event = self._next_event(time.monotonic() + self.server.header_timeout)
        except TimeoutError:
            started = bool(self.h11.trailing_data[0])
            if started:  # part of a request arrived: say why it ends
                self._send_error_and_close(HTTPStatus.REQUEST_TIMEOUT, "request not received in time")
            return False
        except _Refused as err:
            self._send_error_and_close(err.status, str(err))
            return False
        finally:
            self._reading_head = False
        if not isinstance(event, h11.Request):  # ConnectionClosed, or the end of a stream
            return False
        blank = _HEAD_END.search(self._head)  # the first empty line, whatever mix of CRLF and LF ends it
        end = blank.start() if blank else len(self._head)
        self._head = self._head[:end]
        self.req = _Request(event)
        if len(self._head) > self.server.max_head_bytes:  # h11 bounds only a head still incomplete
            self._send_error_and_close(HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE,
                                       f"request line and headers beyond {self.server.max_head_bytes} bytes")
            return False
        self.conn.waiting = False
        problem = self._framing_problem()
        if problem:
            self._send_error_and_close(HTTPStatus.BAD_REQUEST, problem)
            return False
        if self.conn.probation and not (self._host_ok() and self._token_ok(cookie=True)
                                        and self.server._trust(self.conn)):
            self._send_error_and_close(HTTPStatus.SERVICE_UNAVAILABLE, "too many connections; retry")
            return False
        method = self.req.command
        handler = {"GET": self._do_get, "HEAD": self._do_get, "POST": self._do_post}.get(method)
        if handler is None:
            self._dispatch(lambda: self._refuse(HTTPStatus.METHOD_NOT_ALLOWED,
                                                "no CORS here" if method == "OPTIONS" else "use GET or POST"))
        else:
            self._dispatch(handler)
        return self._end_of_request()

    def _framing_problem(self) -> Optional[str]:
        """What h11 accepts that this server does not: obsolete line folding (a header line starting with a
        space or tab, RFC 9112 5.2: rejected rather than joined), any Transfer-Encoding, a Content-Length
        other than one run of ASCII digits (``5, 5`` included)."""
        if _OBS_FOLD.search(self._head):
            return "a header line starts with white space (obsolete line folding)"
        if self.req.all("transfer-encoding"):
            return "Transfer-Encoding is not supported; send Content-Length"
        lengths = _CONTENT_LENGTH.findall(self._head)  # as sent: h11 reads "5, 5" as 5
        if len(lengths) > 1 or len(self.req.all("content-length")) > 1:
            return "more than one Content-Length"
        if lengths and not _DIGITS.fullmatch(lengths[0].strip(b" \t").decode("latin-1")):
            return "Content-Length must be one number in ASCII digits"
        origin_form = self.req.path.startswith("/") and not self.req.path.startswith("//")  # "//host/..." names a host
        if not (origin_form or (self.req.command == "OPTIONS" and self.req.path == "*")):
            return "the request target must be a path (origin form, RFC 9112 3.2.1): no scheme or host"
        if self.req.command == "POST" and not lengths:
            return "Content-Length required (a POST without one has no body: what follows would be a request)"
        return None

    def _body_length(self) -> int:
        value = self.req.header("content-length")
        return int(value) if value is not None else 0  # h11 has checked it is digits

    def _end_of_request(self) -> bool:
        """After the answer: drop a small unread body quickly (the connection stays usable) or close."""
        h = self.h11
        if h.our_state is h11.MUST_CLOSE or h.our_state is h11.ERROR:
            return False
        if h.their_state is h11.SEND_BODY:
            if self._body_length() > DRAIN_BYTES:
                self._linger = True
                return False
            self.conn.waiting = True  # dropping a refused body: it may be closed for another
            deadline = time.monotonic() + min(self.server.drain_seconds, self.server.body_timeout)
            try:
                while True:
                    event = self._next_event(deadline)
                    if isinstance(event, h11.EndOfMessage):
                        break
                    if isinstance(event, h11.ConnectionClosed):
                        return False
            except (TimeoutError, _Refused):
                self._linger = True
                return False
        if h.our_state is h11.DONE and h.their_state is h11.DONE:
            h.start_next_cycle()
            return True
        return False

    def _linger_close(self) -> None:
        """Half-close, then drop what the client still sends for a moment, so that closing with
        unread bytes does not reset the connection before the client has read the answer."""
        sock = self.request
        try:
            sock.shutdown(socket.SHUT_WR)
            end = time.monotonic() + self.server.linger_seconds
            dropped = 0
            while dropped < DRAIN_BYTES and not self.conn.closed:
                left = end - time.monotonic()
                if left <= 0:
                    break
                sock.settimeout(left)
                chunk = sock.recv(65536)
                if not chunk:
                    break
                dropped += len(chunk)
        except OSError:
            pass

    # -- answers ------------------------------------------------------------------------------------
    def _write(self, data: bytes) -> None:
        self.request.settimeout(self.server.write_timeout)
        # a client that does not take its answer only waits: an untrusted one may be closed for another
        self.conn.waiting = True
        try:
            self.request.sendall(data)
        finally:
            self.conn.waiting = False
        if self.conn.closed:
            raise _Closed()

    def _send(self, status: int, body: bytes, content_type: str, cache: str = "no-store",
              extra: Optional[dict] = None, close: bool = False) -> None:
        headers = [("Content-Type", content_type), ("Cache-Control", cache),
                   *[(k, v) for k, v in {**_SECURITY_HEADERS, **(extra or {})}.items()]]
        if int(status) not in (204, 304):
            headers.append(("Content-Length", str(len(body))))
        if close:
            headers.append(("Connection", "close"))
        h = self.h11
        out = h.send(h11.Response(status_code=int(status), headers=headers,
                                  reason=HTTPStatus(int(status)).phrase.encode()))
        if body and self.req is not None and self.req.command != "HEAD" and int(status) not in (204, 304):
            out += h.send(h11.Data(data=body))
        out += h.send(h11.EndOfMessage())
        self._write(out)
        self._log(status)

    def _log(self, status: int) -> None:
        if getattr(self.server, "quiet", True) or self.req is None:
            return
        line = f"{self.req.command} {self.req.path} {int(status)}".replace(self.server.token, "<token>")
        with NATIVE_STDERR_LOCK:  # never into a decoder's capture on another thread
            sys.stderr.write(f"{self.client_address[0]} - {_one_line(line)}\n")
            sys.stderr.flush()

    def _json(self, status: int, obj: Any, close: bool = False) -> None:
        self._send(status, json.dumps(obj, separators=(",", ":")).encode("utf-8"), "application/json", close=close)

    def _error(self, status: int, message: str, **extra: Any) -> None:
        close = self.h11.their_state is h11.SEND_BODY and self._body_length() > DRAIN_BYTES
        self._json(status, {"error": _one_line(message), **extra}, close=close)

    def _send_error_and_close(self, status: int, message: str) -> None:
        """An error answer on a stream whose framing is unknown or broken: answer if h11 still can, then close."""
        self._linger = True
        if self.h11.our_state not in (h11.IDLE, h11.SEND_RESPONSE):
            return
        body = json.dumps({"error": _one_line(message)}, separators=(",", ":")).encode()
        try:
            out = self.h11.send(h11.Response(status_code=int(status), reason=HTTPStatus(int(status)).phrase.encode(),
                                             headers=[("Content-Type", "application/json"),
                                                      ("Content-Length", str(len(body))), ("Connection", "close"),
                                                      *_SECURITY_HEADERS.items()]))
            out += self.h11.send(h11.Data(data=body)) + self.h11.send(h11.EndOfMessage())
        except h11.LocalProtocolError:
            out = (b"HTTP/1.1 %d %s\r\nContent-Type: application/json\r\nContent-Length: %d\r\nConnection: close"
                   b"\r\n\r\n%s" % (int(status), HTTPStatus(int(status)).phrase.encode(), len(body), body))
        try:
            self._write(out)
        except OSError:
            pass

    def _refuse(self, status: int, message: str) -> None:
        raise _Refused(status, message)

    # -- checks ---------------------------------------------------------------------------------------
    def _host_ok(self) -> bool:
        hosts = self.req.all("host")
        return len(hosts) == 1 and hosts[0].strip().lower() in self.server.allowed_hosts

    def _origin_ok(self) -> bool:
        origin = self.req.header("origin")
        if origin is None:  # not a browser cross-origin request (browsers send Origin on POST)
            return True
        try:
            parts = urlsplit(origin)
        except ValueError:
            return False
        return parts.scheme == "http" and parts.netloc.lower() in self.server.allowed_hosts

    def _token_ok(self, *, cookie: bool, query: Optional[str] = None) -> bool:
        """The header token; for reads also the cookie, or ``query`` (the printed address's)."""
        expected = self.server.token.encode()
        given = self.req.header(TOKEN_HEADER)
        if given is None and query is not None:
            given = query
        if given is None and cookie:
            for header in self.req.all("cookie"):
                for part in header.split(";"):
                    name, _, value = part.strip().partition("=")
                    if name == self.server.cookie_name:
                        given = value.strip()
        return given is not None and hmac.compare_digest(given.encode("utf-8", "replace"), expected)

    def _trusted(self) -> None:
        """This request showed the token: its connection joins the trusted pool."""
        if not self.server._trust(self.conn):
            raise _Refused(HTTPStatus.SERVICE_UNAVAILABLE, "too many connections; retry")

    def _url(self):
        """The parsed request target, or ``None`` (``urlsplit`` refuses e.g. ``http://[x``)."""
        try:
            return urlsplit(self.req.path)
        except ValueError:
            return None

    def _guard(self, write: bool, url=None) -> None:
        """Host, then (writes) Origin and the header token, or (reads off loopback) any token."""
        if not self._host_ok():
            raise _Refused(HTTPStatus.FORBIDDEN, "unexpected Host header")
        if write:
            if not self._origin_ok():
                raise _Refused(HTTPStatus.FORBIDDEN, "cross-origin write refused")
            if not self._token_ok(cookie=False):
                raise _Refused(HTTPStatus.FORBIDDEN, "missing or wrong token (open the address the server printed)")
            self._trusted()
            return
        query = None
        if url is not None and url.path in ("/", "/index.html"):
            query = (parse_qs(url.query).get("token") or [None])[0]
        if self._token_ok(cookie=True, query=query):
            self._trusted()
        elif self.server.read_token:
            raise _Refused(HTTPStatus.FORBIDDEN, "this server is reachable from the network: every request "
                                                 "needs the token (open the address the server printed)")

    def _body_limit(self, path: str) -> int:
        if path == "/api/import":  # the upload in base64, plus the request's other keys
            return self.server.session.config.max_import_bytes * 4 // 3 + 64 * 1024
        return MAX_BODY_BYTES

    def _read_json(self, path: str) -> Any:
        """The body, once the request has passed every check that needs no body."""
        if self.req.header("content-length") is None:
            raise _Refused(HTTPStatus.LENGTH_REQUIRED, "Content-Length required")
        n = self._body_length()
        limit = self._body_limit(path)
        if n > limit:
            raise _Refused(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"body of {n} bytes; at most {limit} here")
        ctype = (self.req.header("content-type") or "").split(";")[0].strip().lower()
        if ctype != "application/json":
            raise _Refused(HTTPStatus.BAD_REQUEST, "Content-Type: expected application/json")
        if self.h11.they_are_waiting_for_100_continue:
            self._write(self.h11.send(h11.InformationalResponse(status_code=100, headers=[])))
        deadline = time.monotonic() + self.server.body_timeout + n / self.server.body_min_rate
        raw = bytearray(n)
        got = 0
        while True:
            try:
                event = self._next_event(deadline)
            except TimeoutError:
                raise
            if isinstance(event, h11.Data):
                raw[got:got + len(event.data)] = event.data
                got += len(event.data)
            elif isinstance(event, h11.EndOfMessage):
                break
            else:  # the client closed before the whole body
                self._linger = True
                raise InputError(None, "body", f"ended after {got} of the {n} bytes announced")
        try:
            text = raw.decode("utf-8")
        except UnicodeDecodeError:
            raise InputError(None, "body", "not valid JSON (not UTF-8)") from None
        del raw  # the text alone from here: a body costs a bounded multiple of its size
        if len(text) <= LARGE_BODY_BYTES:
            return parse_json_body(text)
        with _LARGE_BODY_PARSE:  # one large body parsed at a time: their peaks never add up
            return parse_json_body(text)

    def _dispatch(self, work: Callable[[], None]) -> None:
        """Run one request; every failure becomes a one-line JSON error (the traceback, for a
        server fault only, goes to the terminal, never to the client)."""
        try:
            work()
        except _Refused as err:
            self._error(err.status, str(err))
        except Conflict as err:
            self._error(HTTPStatus.CONFLICT, str(err), revision=err.current)
        except InputError as err:
            self._error(HTTPStatus.BAD_REQUEST, str(err))
        except TimeoutError:  # the body's deadline passed
            self._send_error_and_close(HTTPStatus.REQUEST_TIMEOUT, "request body not received in time")
        except (_Closed, OSError):
            self._linger = False
            raise
        except MemoryError:  # the machine's memory, not the request: retry later
            self._error(HTTPStatus.SERVICE_UNAVAILABLE, "out of memory; retry")
        except Exception as err:  # noqa: BLE001 - report, keep serving
            with NATIVE_STDERR_LOCK:
                traceback.print_exc()
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"{type(err).__name__}: {err}")

    # -- methods --------------------------------------------------------------------------------
    def _do_get(self) -> None:
        url = self._url()
        self._guard(write=False, url=url)
        if url is None:
            raise InputError(None, "path", "not a valid request target")
        self._route_get(url)

    def _do_post(self) -> None:
        self._guard(write=True)
        url = self._url()
        if url is None:
            raise _Refused(HTTPStatus.BAD_REQUEST, "path: not a valid request target")
        body = self._read_json(url.path)
        if not isinstance(body, dict):
            raise InputError(None, "body", "expected a JSON object")
        if url.path in ROUTE_KEYS:
            check_keys(body, ROUTE_KEYS[url.path], None, "body", allow_unknown=False)
        self._route_post(url.path, body)

    # -- routes ---------------------------------------------------------------------------------
    def _route_get(self, url) -> None:
        s = self.server.session
        path = url.path
        if path == "/favicon.ico":
            self._send(HTTPStatus.NO_CONTENT, b"", "image/x-icon", cache="max-age=86400")
            return
        if path in ("/", "/index.html"):
            if self.server.read_token and "token" in parse_qs(url.query):
                self._hand_over_token(url)
                return
            self._static("index.html")
            return
        m = re.fullmatch(r"/static/([A-Za-z0-9_.-]+)", path)
        if m:
            self._static(m.group(1))
            return
        if path == "/api/state":
            self._json(HTTPStatus.OK, s.state())
            return
        m = re.fullmatch(r"/api/frame/([0-9]{1,9})\.jpg", path)
        if m:
            self._send(HTTPStatus.OK, s.frame_jpeg(int(m.group(1))), "image/jpeg", cache="private, max-age=3600")
            return
        m = re.fullmatch(r"/api/masks/([0-9]{1,9})", path)
        if m:
            self._json(HTTPStatus.OK, s.masks_of_frame(int(m.group(1))))
            return
        m = re.fullmatch(r"/api/thumb/([0-9]{1,9})\.jpg", path)
        if m:
            query = parse_qs(url.query).get("query")
            qid = _ascii_int(query[0], "query") if query else None
            self._send(HTTPStatus.OK, s.thumb_jpeg(int(m.group(1)), qid), "image/jpeg")
            return
        if path == "/api/review":
            self._json(HTTPStatus.OK, {"findings": s.review()})
            return
        self._error(HTTPStatus.NOT_FOUND, "not found")

    def _hand_over_token(self, url) -> None:
        """``/?token=T`` (the printed address, off loopback; ``_guard`` has checked T): a cookie the
        page's scripts cannot read and other sites cannot send, then the page, token in the fragment."""
        token = self.server.token
        cookie = f"{self.server.cookie_name}={token}; Path=/; HttpOnly; SameSite=Strict"
        self._send(HTTPStatus.SEE_OTHER, b"", "text/plain", extra={"Set-Cookie": cookie,
                                                                   "Location": f"{url.path}#token={token}"})

    def _static(self, name: str) -> None:
        p = self.server.static.get(name)
        if p is None:
            self._error(HTTPStatus.NOT_FOUND, "not found")
            return
        self._send(HTTPStatus.OK, p.read_bytes(), _CONTENT_TYPES[p.suffix], cache="no-cache")

    def _route_post(self, path: str, body: dict) -> None:
        s = self.server.session
        if path == "/api/save":
            rev = s.apply(body.get("revision"), body.get("changes"), body.get("timing"))
            self._json(HTTPStatus.OK, {"revision": rev})
        elif path == "/api/queries/add":
            qid, rev = s.add_query(body.get("revision"), body.get("text"), body.get("kind", "agnostic"),
                                   body.get("base"), body.get("level"))
            self._json(HTTPStatus.OK, {"id": qid, "revision": rev, "state": s.state()})
        elif path == "/api/queries/delete":
            rev = s.delete_query(body.get("revision"), body.get("query"))
            self._json(HTTPStatus.OK, {"revision": rev, "state": s.state()})
        elif path == "/api/queries/reviewed":
            rev = s.mark_reviewed(body.get("revision"), body.get("query"))
            self._json(HTTPStatus.OK, {"revision": rev, "state": s.state()})
        elif path == "/api/segment":
            self._json(HTTPStatus.OK, s.segment(body.get("frame"), body.get("box"), body.get("clicks", []),
                                                body.get("current")))
        elif path == "/api/propagate":
            self._json(HTTPStatus.OK, s.propagate(body.get("query"), body.get("frame"), body.get("direction", 1),
                                                  body.get("count", 10)))
        elif path == "/api/export":
            self._json(HTTPStatus.OK, s.export(body.get("format")))
        elif path == "/api/import":
            out = s.import_data(body.get("revision"), body.get("format"), body.get("filename"), body.get("data"))
            self._json(HTTPStatus.OK, {**out, "state": s.state()})
        else:
            self._error(HTTPStatus.NOT_FOUND, "not found")


def _terminate(signum, frame) -> None:  # noqa: ARG001 - signal handler signature
    raise KeyboardInterrupt


def _bind_problem(host: str, port: int, err: BaseException) -> str:
    if isinstance(err, socket.gaierror):
        return f"cannot resolve {host!r} ({err.strerror or err}); give an address such as 127.0.0.1"
    if isinstance(err, OSError) and err.errno == errno.EADDRINUSE:
        return f"port {port} on {host} is in use; pick another --port, or 0 for a free one"
    if isinstance(err, OSError) and err.errno == errno.EADDRNOTAVAIL:
        return f"{host} is not an address of this machine"
    if isinstance(err, OSError) and err.errno == errno.EACCES:
        return f"not allowed to listen on {host}:{port} (ports below 1024 need privileges)"
    reason = err.strerror if isinstance(err, OSError) and err.strerror else str(err)
    return f"cannot listen on {host}:{port}: {reason}"


def start_server(session: AnnotationSession, host: str = "127.0.0.1", port: int = 0, *,
                 token: Optional[str] = None, read_token: Optional[bool] = None, quiet: bool = True,
                 announce: Callable[[str], Any] = print) -> AnnotationServer:
    """Bind and announce (not yet serving). If binding fails, the session (and its lock file) is
    closed and the failure is an :class:`InputError` in one line."""
    try:
        httpd = AnnotationServer(session, host, port, token, read_token=read_token)
    except (OSError, OverflowError, ValueError) as err:  # in use, unresolvable, not ours, bad port
        session.close()
        raise InputError(None, "--host/--port", _one_line(_bind_problem(host, port, err))) from None
    except BaseException:
        session.close()
        raise
    httpd.quiet = quiet  # type: ignore[attr-defined]
    announce(f"bench4d annotate: {session.scene.name} -> {session.path}")
    removed = getattr(session, "removed_temp_files", [])
    if removed:
        announce(f"removed {len(removed)} temporary file(s) left by an interrupted save")
    announce(f"open {httpd.url}")
    if httpd.read_token:
        announce(f"listening on {host}, reachable from the network: every request, reads included, needs the "
                 "token (the address above sets it); anyone who has the token can read and edit")
    return httpd


def serve(session: AnnotationSession, host: str = "127.0.0.1", port: int = 0, *, token: Optional[str] = None,
          quiet: bool = True, ready: Optional[threading.Event] = None, announce=print,
          read_token: Optional[bool] = None) -> None:
    """Run the server until interrupted; prints the address first. Releases the session's lock."""
    httpd = start_server(session, host, port, token=token, read_token=read_token, quiet=quiet, announce=announce)
    try:
        sys.stdout.flush()
        if ready is not None:
            ready.set()
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, _terminate)  # a plain kill still releases the lock file
        httpd.serve_forever(poll_interval=0.2)
    except KeyboardInterrupt:
        pass
    finally:
        httpd.server_close()
        session.close()

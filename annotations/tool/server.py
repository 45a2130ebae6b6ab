"""HTTP front of the annotation tool (standard library only: ``http.server``).

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

* request framing is strict: one ``Content-Length`` of ASCII digits, no ``Transfer-Encoding``; a
  body the server does not accept is read and dropped (small) or the connection is closed (large),
  so it is never parsed as a second request;
* the request line and headers must arrive within :attr:`AnnotationServer.header_timeout` seconds
  in all (not per read: a client trickling bytes is cut too), a body within
  :attr:`AnnotationServer.body_timeout` plus its size over :attr:`AnnotationServer.body_min_rate`;
  at most :attr:`AnnotationServer.max_connections` connections are served at once, the rest get 503;
* numbers in paths, queries and headers are ASCII digits; JSON bodies are bounded in size and
  nesting and may not hold ``NaN`` or infinities; masks are checked before any decoder sees them;
  any malformed input is a 400 with a one-line JSON error, never a traceback.
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
import sys
import threading
import time
import traceback
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, Callable, Optional
from urllib.parse import parse_qs, urlsplit

from benchmark.core.errors import InputError

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
MAX_BODY_BYTES = 400 * 1024 * 1024
MAX_JSON_DEPTH = 32
"""Deepest nesting a request body may have (the deepest legitimate one, a save, has 5 levels)."""
DRAIN_BYTES = 1024 * 1024
"""A refused body up to this size is read and dropped (the connection stays usable); a larger one
closes the connection instead."""
TOKEN_HEADER = "X-Bench4d-Token"
_MAX_ERROR_CHARS = 400
_DIGITS = re.compile(r"[0-9]{1,15}")  # ASCII only: str.isdigit() also accepts '²' and '١'


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


def _ascii_int(text: Optional[str], field: str) -> Optional[int]:
    """``None`` for a missing value, else the value as ASCII digits (an :class:`InputError` if not)."""
    if text is None:
        return None
    if not _DIGITS.fullmatch(text):
        raise InputError(None, field, "expected a non-negative integer in ASCII digits")
    return int(text)


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not a JSON number")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text[:20]} is out of range")
    return value


def _json_depth_ok(obj: Any, limit: int) -> bool:
    """Iterative (a recursive check would hit the recursion limit it guards against); only
    containers are stacked, so a long list of run lengths costs no extra memory."""
    if not isinstance(obj, (dict, list)):
        return True
    stack = [(obj, 1)]
    while stack:
        item, depth = stack.pop()
        if depth > limit:
            return False
        values = item.values() if isinstance(item, dict) else item
        stack.extend((v, depth + 1) for v in values if isinstance(v, (dict, list)))
    return True


def parse_json_body(raw: bytes) -> Any:
    """Strict JSON of a request body: UTF-8, no NaN or infinities, bounded nesting; else InputError."""
    try:
        obj = json.loads(raw.decode("utf-8"), parse_constant=_reject_constant, parse_float=_finite_float)
    except (UnicodeDecodeError, ValueError, RecursionError, OverflowError) as err:
        # json's own messages name a position; deep nesting and 5000-digit numbers land here too
        detail = "nested too deeply" if isinstance(err, RecursionError) else str(err).splitlines()[0][:120]
        raise InputError(None, "body", f"not valid JSON ({detail})") from None
    if not _json_depth_ok(obj, MAX_JSON_DEPTH):
        raise InputError(None, "body", f"nested deeper than {MAX_JSON_DEPTH} levels")
    return obj


def _one_line(text: str) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= _MAX_ERROR_CHARS else text[:_MAX_ERROR_CHARS - 3] + "..."


class _Refused(Exception):
    """A request answered with an error before its body was read."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


class _DeadlineReader:
    """The handler's ``rfile``: every read is bounded by one deadline for the whole phase (request
    line and headers, or body), not per ``recv``; a client sending a byte at a time is cut too.

    Each step does at most one ``recv`` (``peek`` / ``read1`` on the buffered socket file), with the
    socket timeout set to the time left, so the phase can never outlast its deadline by more than
    one scheduling delay.
    """

    def __init__(self, raw, sock: socket.socket):
        self._raw = raw
        self._sock = sock
        self._deadline = math.inf

    def start(self, seconds: float) -> None:
        self._deadline = time.monotonic() + seconds

    def _arm(self) -> None:
        left = self._deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("request not received in time")
        self._sock.settimeout(min(left, 3600.0))

    def readline(self, limit: int = -1) -> bytes:
        out = bytearray()
        while limit < 0 or len(out) < limit:
            self._arm()
            chunk = self._raw.peek(1)
            if not chunk:
                break
            want = len(chunk) if limit < 0 else min(len(chunk), limit - len(out))
            nl = chunk.find(b"\n", 0, want)
            out += self._raw.read(want if nl < 0 else nl + 1)  # from the buffer: no recv
            if nl >= 0:
                break
        return bytes(out)

    def read(self, n: int = -1) -> bytes:
        out = bytearray()
        while n < 0 or len(out) < n:
            self._arm()
            chunk = self._raw.read1(65536 if n < 0 else min(65536, n - len(out)))
            if not chunk:
                break
            out += chunk
        return bytes(out)

    def close(self) -> None:
        self._raw.close()

    @property
    def closed(self) -> bool:
        return self._raw.closed


class AnnotationServer(ThreadingHTTPServer):
    """A threaded HTTP server bound to one :class:`AnnotationSession`."""

    daemon_threads = True
    request_queue_size = 64
    header_timeout = 10.0
    """Seconds a client has to send the request line and headers (and a kept-alive connection may idle)."""
    body_timeout = 30.0
    """Seconds a client has to send a body, plus its size divided by :attr:`body_min_rate`."""
    body_min_rate = 1024 * 1024
    """Bytes per second a large upload must at least average."""
    write_timeout = 60.0
    """Seconds the server waits for a client to take one response."""
    max_connections = 64
    """Connections served at once (each holds a thread); a browser opens about six."""
    linger_seconds = 1.0
    """After refusing a body it does not read, the server reads and drops what is in flight this
    long before closing, so that the client gets the answer instead of a reset connection."""

    def __init__(self, session: AnnotationSession, host: str = "127.0.0.1", port: int = 0,
                 token: Optional[str] = None, extra_hosts: tuple[str, ...] = (), *,
                 read_token: Optional[bool] = None):
        if ":" in host.strip("[]"):
            self.address_family = socket.AF_INET6
        self._active = 0
        self._active_lock = threading.Lock()
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

    # -- one thread per connection, at most max_connections of them -----------------------------
    def process_request(self, request, client_address) -> None:
        with self._active_lock:
            full = self._active >= self.max_connections
            if not full:
                self._active += 1
        if full:
            self._refuse_connection(request)
            return
        try:
            super().process_request(request, client_address)
        except BaseException:
            self._release_slot()
            raise

    def process_request_thread(self, request, client_address) -> None:
        try:
            super().process_request_thread(request, client_address)
        finally:
            self._release_slot()

    def _release_slot(self) -> None:
        with self._active_lock:
            self._active -= 1

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


class _Handler(BaseHTTPRequestHandler):
    server: AnnotationServer
    protocol_version = "HTTP/1.1"
    server_version = "bench4d-annotate"
    sys_version = ""
    _body_left = 0
    _linger = False

    # -- plumbing -------------------------------------------------------------------------------
    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - stdlib signature
        if self.server_quiet():
            return
        line = format % args
        sys.stderr.write("%s - %s\n" % (self.address_string(), line.replace(self.server.token, "<token>")))

    def server_quiet(self) -> bool:
        return getattr(self.server, "quiet", True)

    def setup(self) -> None:
        super().setup()
        self.rfile = _DeadlineReader(self.rfile, self.connection)

    def handle_one_request(self) -> None:
        self._body_left = 0
        self.rfile.start(self.server.header_timeout)
        try:
            super().handle_one_request()
        except OSError:  # reset or broken connection: nothing more to say on it
            self.close_connection = True
        if self._body_left:  # not read and not answered: its bytes must not become a request
            self._close_after()

    def finish(self) -> None:
        super().finish()
        if self._linger:
            self._linger_close()

    def _close_after(self) -> None:
        self.close_connection = True
        if self._body_left:
            self._linger = True
        self._body_left = 0

    def _linger_close(self) -> None:
        """Half-close, then drop what the client still sends for a moment, so that closing with
        unread bytes does not reset the connection before the client has read the answer."""
        sock = self.connection
        try:
            sock.shutdown(socket.SHUT_WR)
            end = time.monotonic() + self.server.linger_seconds
            dropped = 0
            while dropped < DRAIN_BYTES:
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

    def parse_request(self) -> bool:
        """The stdlib's parsing, then strict framing: anything ambiguous is refused and the
        connection closed (the classic request-smuggling openings)."""
        if not super().parse_request():
            return False
        if self.headers.get_all("Transfer-Encoding"):
            self.send_error(HTTPStatus.BAD_REQUEST, "Transfer-Encoding is not supported; send Content-Length")
            return False
        lengths = self.headers.get_all("Content-Length") or []
        if len(lengths) > 1:
            self.send_error(HTTPStatus.BAD_REQUEST, "more than one Content-Length")
            return False
        if lengths:
            value = lengths[0].strip(" \t")
            if not _DIGITS.fullmatch(value):
                self.send_error(HTTPStatus.BAD_REQUEST, "Content-Length must be ASCII digits")
                return False
            self._body_left = int(value)
        return True

    def send_error(self, code: int, message: Optional[str] = None, explain: Optional[str] = None) -> None:
        """Errors the stdlib raises (bad request line, unknown method, ...) as this server's JSON,
        always closing the connection (the request's framing is unknown)."""
        if code == HTTPStatus.NOT_IMPLEMENTED:  # an unknown method: not a server fault
            code = HTTPStatus.METHOD_NOT_ALLOWED
        self.close_connection = True
        self._linger = True
        self._body_left = 0
        try:
            self._error(code, message or HTTPStatus(code).phrase)
        except OSError:
            pass

    def _settle_body(self) -> None:
        """Before answering: the unread body of this request is dropped (small) or the connection
        will close after the answer (large); either way it is never parsed as a request."""
        left = self._body_left
        if not left:
            return
        if left > DRAIN_BYTES or self.close_connection:
            self._close_after()
            return
        try:
            self.rfile.start(self.server.body_timeout)
            got = len(self.rfile.read(left))
        except OSError:
            got = -1
        self._body_left = 0 if got == left else left
        if self._body_left:
            self._close_after()

    def _send(self, status: int, body: bytes, content_type: str, cache: str = "no-store",
              extra: Optional[dict] = None) -> None:
        self._settle_body()
        self.connection.settimeout(self.server.write_timeout)
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", cache)
        for k, v in {**_SECURITY_HEADERS, **(extra or {})}.items():
            self.send_header(k, v)
        if self.close_connection:
            self.send_header("Connection", "close")
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, status: int, obj: Any) -> None:
        self._send(status, json.dumps(obj, separators=(",", ":")).encode("utf-8"), "application/json")

    def _error(self, status: int, message: str, **extra: Any) -> None:
        self._json(status, {"error": _one_line(message), **extra})

    def _host_ok(self) -> bool:
        host = (self.headers.get("Host") or "").strip().lower()
        return host in self.server.allowed_hosts

    def _origin_ok(self) -> bool:
        origin = self.headers.get("Origin")
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
        given = self.headers.get(TOKEN_HEADER)
        if given is None and query is not None:
            given = query
        if given is None and cookie:
            for header in self.headers.get_all("Cookie") or []:
                for part in header.split(";"):
                    name, _, value = part.strip().partition("=")
                    if name == self.server.cookie_name:
                        given = value.strip()
        return given is not None and hmac.compare_digest(given.encode("utf-8", "replace"), expected)

    def _read_json(self) -> Any:
        """The body, once the request has passed every check that needs no body."""
        if self.headers.get("Content-Length") is None:
            raise _Refused(HTTPStatus.LENGTH_REQUIRED, "Content-Length required")
        n = self._body_left
        if n > MAX_BODY_BYTES:
            raise _Refused(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"body of {n} bytes; at most {MAX_BODY_BYTES}")
        ctype = (self.headers.get("Content-Type") or "").split(";")[0].strip().lower()
        if ctype != "application/json":
            raise _Refused(HTTPStatus.BAD_REQUEST, "Content-Type: expected application/json")
        self.rfile.start(self.server.body_timeout + n / self.server.body_min_rate)
        raw = self.rfile.read(n)  # TimeoutError past the deadline: answered 408 by the caller
        if len(raw) < n:
            self._close_after()
            raise InputError(None, "body", f"ended after {len(raw)} of the {n} bytes announced")
        self._body_left = 0
        return parse_json_body(raw)

    def _url(self):
        """The parsed request target, or ``None`` (``urlsplit`` refuses e.g. ``http://[x``)."""
        try:
            return urlsplit(self.path)
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
        elif self.server.read_token:
            query = None
            if url is not None and url.path in ("/", "/index.html"):
                query = (parse_qs(url.query).get("token") or [None])[0]
            if not self._token_ok(cookie=True, query=query):
                raise _Refused(HTTPStatus.FORBIDDEN, "this server is reachable from the network: every request "
                                                     "needs the token (open the address the server printed)")

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
        except TimeoutError:  # the body's deadline passed (or the client stopped taking the answer)
            self._close_after()
            try:
                self._error(HTTPStatus.REQUEST_TIMEOUT, "request body not received in time")
            except OSError:
                pass
        except OSError:
            self.close_connection = True
        except Exception as err:  # noqa: BLE001 - report, keep serving
            traceback.print_exc()
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"{type(err).__name__}: {err}")

    # -- methods --------------------------------------------------------------------------------
    def do_OPTIONS(self) -> None:  # noqa: N802 - stdlib naming
        # no CORS: a preflight from another origin gets no Access-Control-* header, so it fails
        self._error(HTTPStatus.METHOD_NOT_ALLOWED, "no CORS here")

    def do_PUT(self) -> None:  # noqa: N802
        self._error(HTTPStatus.METHOD_NOT_ALLOWED, "use POST")

    do_DELETE = do_PUT
    do_PATCH = do_PUT

    def do_HEAD(self) -> None:  # noqa: N802
        self.do_GET()

    def do_GET(self) -> None:  # noqa: N802
        def work() -> None:
            url = self._url()
            self._guard(write=False, url=url)
            if url is None:
                raise InputError(None, "path", "not a valid request target")
            self._route_get(url)

        self._dispatch(work)

    def do_POST(self) -> None:  # noqa: N802
        def work() -> None:
            self._guard(write=True)
            url = self._url()
            if url is None:
                raise _Refused(HTTPStatus.BAD_REQUEST, "path: not a valid request target")
            body = self._read_json()
            if not isinstance(body, dict):
                raise InputError(None, "body", "expected a JSON object")
            self._route_post(url.path, body)

        self._dispatch(work)

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

"""HTTP front of the annotation tool (standard library only: ``http.server``).

Security model (the tool edits files on the annotator's disk):

* binds ``127.0.0.1`` by default;
* every request's ``Host`` header must name this server (``127.0.0.1:PORT``, ``localhost:PORT``,
  ``[::1]:PORT`` or the bound address): a DNS-rebinding page cannot talk to it;
* every write (``POST``) needs the per-launch token in the ``X-Bench4d-Token`` header, a JSON body,
  and, when the browser sends an ``Origin``, this server's own origin;
* no CORS headers are ever sent (``OPTIONS`` is refused), so other origins cannot read responses;
* the page gets the token from the URL fragment the server prints (never sent over the network);
* clients name frames by index and queries by id; the server never opens a path a client sends.
"""

from __future__ import annotations

import hmac
import json
import re
import secrets
import signal
import socket
import sys
import threading
import traceback
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Any, Optional
from urllib.parse import parse_qs, urlsplit

from benchmark.errors import InputError

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
TOKEN_HEADER = "X-Bench4d-Token"


def _static_files() -> dict[str, Path]:
    """The whitelist of files the page may load: every file in ``static/``, by name."""
    return {p.name: p for p in STATIC_DIR.iterdir() if p.is_file() and p.suffix in _CONTENT_TYPES}


class AnnotationServer(ThreadingHTTPServer):
    """A threaded HTTP server bound to one :class:`AnnotationSession`."""

    daemon_threads = True

    def __init__(self, session: AnnotationSession, host: str = "127.0.0.1", port: int = 0,
                 token: Optional[str] = None, extra_hosts: tuple[str, ...] = ()):
        if ":" in host.strip("[]"):
            self.address_family = socket.AF_INET6
        super().__init__((host.strip("[]"), port), _Handler)
        self.session = session
        self.token = token or secrets.token_urlsafe(24)
        self.host = host
        self.port = self.server_address[1]
        names = {"127.0.0.1", "localhost", "[::1]", host if ":" not in host else f"[{host.strip('[]')}]"}
        names.update(extra_hosts)
        self.allowed_hosts = {f"{n}:{self.port}".lower() for n in names}
        self.static = _static_files()

    @property
    def url(self) -> str:
        """Address to open, with the token in the fragment (the browser never sends it anywhere)."""
        shown = self.host if ":" not in self.host else f"[{self.host.strip('[]')}]"
        if shown in ("0.0.0.0", "[::]"):
            shown = "127.0.0.1"
        return f"http://{shown}:{self.port}/#token={self.token}"


class _Handler(BaseHTTPRequestHandler):
    server: AnnotationServer
    protocol_version = "HTTP/1.1"
    server_version = "bench4d-annotate"
    sys_version = ""

    # -- plumbing -------------------------------------------------------------------------------
    def log_message(self, format: str, *args: Any) -> None:  # noqa: A002 - stdlib signature
        if self.server_quiet():
            return
        sys.stderr.write("%s - %s\n" % (self.address_string(), format % args))

    def server_quiet(self) -> bool:
        return getattr(self.server, "quiet", True)

    def _send(self, status: int, body: bytes, content_type: str, cache: str = "no-store") -> None:
        self.send_response(status)
        self.send_header("Content-Type", content_type)
        self.send_header("Content-Length", str(len(body)))
        self.send_header("Cache-Control", cache)
        for k, v in _SECURITY_HEADERS.items():
            self.send_header(k, v)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def _json(self, status: int, obj: Any) -> None:
        self._send(status, json.dumps(obj, separators=(",", ":")).encode("utf-8"), "application/json")

    def _error(self, status: int, message: str, **extra: Any) -> None:
        self._json(status, {"error": message, **extra})

    def _host_ok(self) -> bool:
        host = (self.headers.get("Host") or "").strip().lower()
        return host in self.server.allowed_hosts

    def _origin_ok(self) -> bool:
        origin = self.headers.get("Origin")
        if origin is None:  # not a browser cross-origin request (browsers send Origin on POST)
            return True
        parts = urlsplit(origin)
        return parts.scheme == "http" and parts.netloc.lower() in self.server.allowed_hosts

    def _read_json(self) -> Any:
        length = self.headers.get("Content-Length")
        if length is None or not length.isdigit():
            raise InputError(None, "Content-Length", "required")
        n = int(length)
        if n > MAX_BODY_BYTES:
            raise InputError(None, "body", f"{n} bytes; at most {MAX_BODY_BYTES}")
        ctype = (self.headers.get("Content-Type") or "").split(";")[0].strip().lower()
        if ctype != "application/json":
            raise InputError(None, "Content-Type", "expected application/json")
        raw = self.rfile.read(n)
        try:
            return json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, json.JSONDecodeError):
            raise InputError(None, "body", "not valid JSON") from None

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
        if not self._host_ok():
            self._error(HTTPStatus.FORBIDDEN, "unexpected Host header")
            return
        try:
            self._route_get(urlsplit(self.path))
        except InputError as err:
            self._error(HTTPStatus.BAD_REQUEST, str(err))
        except (BrokenPipeError, ConnectionResetError):
            pass
        except Exception as err:  # noqa: BLE001 - report, keep serving
            traceback.print_exc()
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"{type(err).__name__}: {err}")

    def do_POST(self) -> None:  # noqa: N802
        if not self._host_ok():
            self._error(HTTPStatus.FORBIDDEN, "unexpected Host header")
            return
        if not self._origin_ok():
            self._error(HTTPStatus.FORBIDDEN, "cross-origin write refused")
            return
        given = self.headers.get(TOKEN_HEADER) or ""
        if not hmac.compare_digest(given.encode(), self.server.token.encode()):
            self._error(HTTPStatus.FORBIDDEN, "missing or wrong token (open the address the server printed)")
            return
        try:
            body = self._read_json()
            if not isinstance(body, dict):
                raise InputError(None, "body", "expected a JSON object")
            self._route_post(urlsplit(self.path).path, body)
        except Conflict as err:
            self._error(HTTPStatus.CONFLICT, str(err), revision=err.current)
        except InputError as err:
            self._error(HTTPStatus.BAD_REQUEST, str(err))
        except (BrokenPipeError, ConnectionResetError):
            pass
        except Exception as err:  # noqa: BLE001
            traceback.print_exc()
            self._error(HTTPStatus.INTERNAL_SERVER_ERROR, f"{type(err).__name__}: {err}")

    # -- routes ---------------------------------------------------------------------------------
    def _route_get(self, url) -> None:
        s = self.server.session
        path = url.path
        if path == "/favicon.ico":
            self._send(HTTPStatus.NO_CONTENT, b"", "image/x-icon", cache="max-age=86400")
            return
        if path in ("/", "/index.html"):
            self._static("index.html")
            return
        m = re.fullmatch(r"/static/([A-Za-z0-9_.-]+)", path)
        if m:
            self._static(m.group(1))
            return
        if path == "/api/state":
            self._json(HTTPStatus.OK, s.state())
            return
        m = re.fullmatch(r"/api/frame/(\d+)\.jpg", path)
        if m:
            self._send(HTTPStatus.OK, s.frame_jpeg(int(m.group(1))), "image/jpeg", cache="private, max-age=3600")
            return
        m = re.fullmatch(r"/api/masks/(\d+)", path)
        if m:
            self._json(HTTPStatus.OK, s.masks_of_frame(int(m.group(1))))
            return
        m = re.fullmatch(r"/api/thumb/(\d+)\.jpg", path)
        if m:
            q = parse_qs(url.query).get("query", [None])[0]
            qid = int(q) if q is not None and q.isdigit() else None
            self._send(HTTPStatus.OK, s.thumb_jpeg(int(m.group(1)), qid), "image/jpeg")
            return
        if path == "/api/review":
            self._json(HTTPStatus.OK, {"findings": s.review()})
            return
        self._error(HTTPStatus.NOT_FOUND, "not found")

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


def serve(session: AnnotationSession, host: str = "127.0.0.1", port: int = 0, *, token: Optional[str] = None,
          quiet: bool = True, ready: Optional[threading.Event] = None, announce=print) -> None:
    """Run the server until interrupted; prints the address first. Releases the session's lock."""
    httpd = AnnotationServer(session, host, port, token)
    httpd.quiet = quiet  # type: ignore[attr-defined]
    announce(f"bench4d annotate: {session.scene.name} -> {session.path}")
    announce(f"open {httpd.url}")
    if host not in ("127.0.0.1", "localhost", "::1"):
        announce(f"warning: listening on {host}: anyone who can reach it and has the token can edit")
    sys.stdout.flush()
    if ready is not None:
        ready.set()
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGTERM, _terminate)  # a plain kill still releases the lock file
    try:
        httpd.serve_forever(poll_interval=0.2)
    except KeyboardInterrupt:
        pass
    finally:
        httpd.server_close()
        session.close()

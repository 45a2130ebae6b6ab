"""The annotation server under hostile and faulty input: framing, tokens, slow clients, malformed
numbers and masks, start-up failures, interrupted saves, and a fuzz over every route.

Everything talks to 127.0.0.1 on an ephemeral port; every loop and socket wait is bounded.
"""

from __future__ import annotations

import base64
import http.client
import json
import os
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from urllib.parse import quote

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from annotations.tool.server import AnnotationServer
from annotations.tool.session import AnnotationSession, mask_to_runs, runs_to_mask
from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene
from benchmark.core.errors import InputError
from benchmark.loaders import load_scene

W, H = 96, 64
# conftest flushes denormals to zero (torch), so hypothesis must not draw subnormal floats
ROOT = Path(__file__).resolve().parents[1]
# short limits so that slow-client tests finish quickly
LIMITS = {"header_timeout": 1.0, "body_timeout": 1.5, "body_min_rate": 1 << 20, "max_connections": 8,
          "linger_seconds": 0.3}


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory):
    return write_dnerf_scene(rigid_sequence(4, W, H, seed=1), tmp_path_factory.mktemp("hard") / "scene")


def _start(scene_dir, folder, **kwargs):
    session = AnnotationSession(load_scene(scene_dir), folder / "a.json")
    httpd = AnnotationServer(session, "127.0.0.1", 0, **kwargs)
    httpd.quiet = True
    for k, v in LIMITS.items():
        setattr(httpd, k, v)
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    return httpd


def _stop(httpd):
    httpd.shutdown()
    httpd.server_close()
    httpd.session.close()


@pytest.fixture(scope="module")
def server(scene_dir, tmp_path_factory):
    httpd = _start(scene_dir, tmp_path_factory.mktemp("ann"))
    yield httpd
    _stop(httpd)


@pytest.fixture(scope="module")
def guarded(scene_dir, tmp_path_factory):
    """A server in the off-loopback mode (token on every route), still bound to 127.0.0.1."""
    httpd = _start(scene_dir, tmp_path_factory.mktemp("ann_guarded"), read_token=True)
    yield httpd
    _stop(httpd)


# -- helpers ------------------------------------------------------------------------------------
def host(server) -> str:
    return f"127.0.0.1:{server.port}"


def request(server, method, path, body=None, headers=None):
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    h = {"Host": host(server), **(headers or {})}
    data = None
    if body is not None:
        data = body if isinstance(body, bytes) else json.dumps(body).encode()
        h.setdefault("Content-Type", "application/json")
    try:
        conn.request(method, path, body=data, headers=h)
        res = conn.getresponse()
        return res, res.read()
    finally:
        conn.close()


def write(server, path, body, **headers):
    return request(server, "POST", path, body, {"X-Bench4d-Token": server.token, **headers})


def exchange(server, raw: bytes, *, half_close=True, wait=5.0) -> bytes:
    """Send raw bytes, then read every byte the server sends until it closes (or ``wait`` passes)."""
    with socket.create_connection(("127.0.0.1", server.port), timeout=wait) as s:
        try:
            s.sendall(raw)
            if half_close:
                s.shutdown(socket.SHUT_WR)
        except OSError:  # the server may close early on a request it refuses: read what it sent
            pass
        out = b""
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            try:
                chunk = s.recv(65536)
            except (socket.timeout, ConnectionResetError):
                break
            if not chunk:
                break
            out += chunk
        return out


def statuses(stream: bytes) -> list[int]:
    """Status codes of the responses in a byte stream (a response may follow a body directly)."""
    return [int(m.group(1)) for m in re.finditer(rb"HTTP/1\.[01] ([0-9]{3}) ", stream)]


def raw_request(server, method: str, path: bytes, headers: dict, body: bytes = b"") -> bytes:
    lines = [method.encode() + b" " + path + b" HTTP/1.1", b"Host: " + host(server).encode()]
    for k, v in headers.items():
        lines.append(k.encode() + b": " + (v if isinstance(v, bytes) else str(v).encode()))
    return b"\r\n".join(lines) + b"\r\n\r\n" + body


def assert_alive(server):
    res, body = request(server, "GET", "/api/state", headers={"X-Bench4d-Token": server.token})
    assert res.status == 200, body


def assert_clean_4xx(stream: bytes, *codes: int):
    got = statuses(stream)
    assert got, stream[:300]
    assert got[0] in (codes or range(400, 500)), stream[:300]
    assert b"Traceback" not in stream and b'File "' not in stream
    body = stream.split(b"\r\n\r\n", 1)[1] if b"\r\n\r\n" in stream else b""
    if body:
        assert json.loads(body.split(b"HTTP/1.", 1)[0])["error"]


def add_query(server, text):
    res, payload = write(server, "/api/queries/add", {"revision": server.session.revision, "text": text})
    if res.status == 400 and b"exists already" in payload:
        return next(q.id for q in server.session.aset.queries if q.text == text)
    assert res.status == 200, payload
    return json.loads(payload)["id"]


# -- request smuggling ------------------------------------------------------------------------
def test_a_refused_body_is_never_read_as_the_next_request(server):
    smuggled = f"GET /api/smuggled HTTP/1.1\r\nHost: {host(server)}\r\n\r\n".encode()
    final = f"GET /api/state HTTP/1.1\r\nHost: {host(server)}\r\nConnection: close\r\n\r\n".encode()
    base = {"Content-Type": "application/json", "X-Bench4d-Token": server.token}
    cases = {
        "wrong token": {**base, "X-Bench4d-Token": "wrong"},
        "no token": {k: v for k, v in base.items() if k != "X-Bench4d-Token"},
        "foreign origin": {**base, "Origin": "http://evil.example"},
        "foreign host": {**base, "Host": "evil.example"},
        "not JSON": {**base, "Content-Type": "text/plain"},
    }
    for name, headers in cases.items():
        req = raw_request(server, "POST", b"/api/save", {**headers, "Content-Length": len(smuggled)}, smuggled)
        if name == "foreign host":
            req = req.replace(f"Host: {host(server)}\r\n".encode(), b"", 1)
        codes = statuses(exchange(server, req + final))
        assert codes[:1] in ([400], [403]) and 404 not in codes, (name, codes)
    # a GET with a body, a chunked body, two lengths: never a second request from the body
    for extra in ({"Content-Length": len(smuggled)},
                  {"Transfer-Encoding": "chunked"},
                  {"Content-Length": f"{len(smuggled)}\r\nContent-Length: 0"}):
        req = raw_request(server, "GET", b"/api/state", extra, smuggled)
        codes = statuses(exchange(server, req))
        assert codes and 404 not in codes, (extra, codes)
    # a body too large to accept is not read either: the connection closes
    req = raw_request(server, "POST", b"/api/save", {**base, "Content-Length": 10 ** 12}, smuggled)
    stream = exchange(server, req)
    assert statuses(stream)[:1] == [413] and 404 not in statuses(stream), stream[:300]
    assert_alive(server)


def test_a_refused_small_body_keeps_the_connection_usable(server):
    """The bounded drain: after a refused write, the same connection answers the next request."""
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    try:
        conn.request("POST", "/api/save", body=b'{"revision": 0, "changes": []}',
                     headers={"Host": host(server), "Content-Type": "application/json", "X-Bench4d-Token": "no"})
        res = conn.getresponse()
        res.read()
        assert res.status == 403
        conn.request("GET", "/api/state", headers={"Host": host(server)})
        res = conn.getresponse()
        assert res.status == 200 and json.loads(res.read())["frames"]
    finally:
        conn.close()


# -- token on reads off loopback ----------------------------------------------------------------
READ_ROUTES = ["/", "/index.html", "/static/app.js", "/favicon.ico", "/api/state", "/api/frame/0.jpg",
               "/api/masks/0", "/api/thumb/0.jpg", "/api/review", "/api/nowhere"]


def test_off_loopback_every_route_needs_the_token(guarded):
    for path in READ_ROUTES:
        for headers in ({}, {"X-Bench4d-Token": "wrong"}, {"Cookie": f"bench4d_token_{guarded.port}=wrong"}):
            res, body = request(guarded, "GET", path, headers=headers)
            assert res.status == 403, (path, headers, res.status)
            assert b"<html" not in body.lower() and b"frames" not in body
        res, _ = request(guarded, "GET", path, headers={"X-Bench4d-Token": guarded.token})
        assert res.status in (200, 204, 404), (path, res.status)
    res, _ = request(guarded, "POST", "/api/save", {"revision": 0, "changes": []})
    assert res.status == 403
    # the printed address carries the token once; the server swaps it for a same-site, script-proof cookie
    assert "?token=" in guarded.url
    res, _ = request(guarded, "GET", "/?token=wrong")
    assert res.status == 403 and res.getheader("Set-Cookie") is None
    res, _ = request(guarded, "GET", f"/?token={guarded.token}")
    assert res.status == 303 and res.getheader("Location") == f"/#token={guarded.token}"
    cookie = res.getheader("Set-Cookie")
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie
    jar = {"Cookie": cookie.split(";")[0]}
    for path in READ_ROUTES[:-1]:
        res, _ = request(guarded, "GET", path, headers=jar)
        assert res.status in (200, 204), (path, res.status)
    # the cookie alone never writes (writes need the header a script of this page sends)
    res, _ = request(guarded, "POST", "/api/save", {"revision": 0, "changes": []}, jar)
    assert res.status == 403


def test_on_loopback_reads_stay_open_and_writes_need_the_token(server):
    for path in READ_ROUTES[:-1]:
        res, _ = request(server, "GET", path)
        assert res.status in (200, 204), path
    res, _ = request(server, "POST", "/api/save", {"revision": 0, "changes": []})
    assert res.status == 403


def test_the_mode_follows_the_bound_address_and_is_announced(scene_dir, tmp_path):
    from annotations.tool import server as srv

    assert not srv.needs_read_token("127.0.0.1") and not srv.needs_read_token("::1")
    assert not srv.needs_read_token("127.3.4.5") and not srv.needs_read_token("::ffff:127.0.0.1")
    for addr in ("0.0.0.0", "::", "192.168.1.20", "10.0.0.1", "fe80::1", "not an address"):
        assert srv.needs_read_token(addr), addr
    said: list[str] = []
    session = AnnotationSession(load_scene(scene_dir), tmp_path / "a.json")
    httpd = srv.start_server(session, "127.0.0.1", 0, read_token=True, announce=said.append)
    try:
        assert any("reads included" in line for line in said), said
        assert any(httpd.url in line for line in said)
    finally:
        httpd.server_close()
        session.close()
    said.clear()
    session = AnnotationSession(load_scene(scene_dir), tmp_path / "a.json")
    httpd = srv.start_server(session, "127.0.0.1", 0, announce=said.append)
    httpd.server_close()
    session.close()
    assert not any("reads included" in line for line in said) and not httpd.read_token


# -- slow and half-open connections ----------------------------------------------------------
def test_half_open_connections_are_bounded_in_number_and_time(server):
    before = threading.active_count()
    socks = []
    try:
        for _ in range(24):
            s = socket.create_connection(("127.0.0.1", server.port), timeout=5)
            s.sendall(b"GET /api/state HTTP/1.1\r\nHost: ")  # and never the rest
            socks.append(s)
        time.sleep(0.3)
        assert threading.active_count() - before <= server.max_connections + 1, threading.active_count() - before
        # every one is answered or dropped within the header deadline (plus slack for a busy machine)
        deadline = time.monotonic() + LIMITS["header_timeout"] + 4.0
        for s in socks:
            s.settimeout(max(0.05, deadline - time.monotonic()))
            try:
                while s.recv(4096):
                    pass
            except ConnectionResetError:
                pass
            except socket.timeout:
                pytest.fail("a half-open connection was still held after the header deadline")
    finally:
        for s in socks:
            s.close()
    assert_alive(server)


def test_a_trickled_request_is_cut_at_the_header_deadline(server):
    """One byte at a time, each well inside any per-read timeout: the whole-request deadline still cuts it."""
    with socket.create_connection(("127.0.0.1", server.port), timeout=5) as s:
        t0 = time.monotonic()
        closed = False
        for b in (b"GET /api/state HTTP/1.1\r\nX-Slow: " + b"a" * 200):
            try:
                s.sendall(bytes([b]))
            except OSError:
                closed = True
                break
            s.settimeout(0.05)
            try:
                if s.recv(4096) == b"":
                    closed = True
                    break
            except socket.timeout:
                pass
            except ConnectionResetError:
                closed = True
                break
            if time.monotonic() - t0 > LIMITS["header_timeout"] + 4.0:
                break
        assert closed, "a trickled request held its connection past the header deadline"
    # a body trickled the same way is cut at the body deadline
    req = raw_request(server, "POST", b"/api/save", {"Content-Type": "application/json",
                                                    "X-Bench4d-Token": server.token, "Content-Length": 1000}, b"{")
    with socket.create_connection(("127.0.0.1", server.port), timeout=8) as s:
        s.sendall(req)
        t0 = time.monotonic()
        data = b""
        try:
            while chunk := s.recv(4096):
                data += chunk
        except (socket.timeout, ConnectionResetError):
            pass
        assert time.monotonic() - t0 < LIMITS["body_timeout"] + 4.0
        assert statuses(data)[:1] in ([], [408]), data[:200]
    assert_alive(server)


# -- malformed numbers, deep JSON, big runs ---------------------------------------------------
def test_non_ascii_digits_are_400(server):
    qid = add_query(server, "digits")
    assert qid < 10  # one Arabic-Indic digit below
    base = {"Content-Type": "application/json", "X-Bench4d-Token": server.token}
    body = json.dumps({"revision": server.session.revision, "changes": []}).encode()
    for length in ("\u00b2".encode("latin-1"), "\u0661\u0662".encode(), b"1_2", b"+12", b"0x10", b"1e3", b"-1"):
        stream = exchange(server, raw_request(server, "POST", b"/api/save", {**base, "Content-Length": length},
                                              body))
        assert_clean_4xx(stream, 400)
    for path in (b"/api/frame/\xb2.jpg", b"/api/masks/\xb9", "/api/frame/\u0661.jpg".encode(),
                 b"/api/frame/" + b"9" * 5000 + b".jpg", "/api/thumb/0.jpg?query=%C2%B2".encode(),
                 b"/api/thumb/0.jpg?query=" + quote(chr(0x660 + qid)).encode(), b"/api/thumb/0.jpg?query=" + b"9" * 5000):
        stream = exchange(server, raw_request(server, "GET", path, {}))
        assert statuses(stream)[:1] in ([400], [404]), (path[:60], stream[:300])
        assert_clean_4xx(stream)
    res, _ = request(server, "GET", f"/api/thumb/0.jpg?query={qid}")
    assert res.status == 200
    assert_alive(server)


def test_deep_and_huge_json_is_400(server):
    for body in (b"[" * 100_000 + b"]" * 100_000, b'{"a":' * 100_000 + b"1" + b"}" * 100_000,
                 b'{"revision": ' + b"9" * 5000 + b', "changes": []}',
                 b'{"revision": 0, "changes": [' + b"[" * 200 + b"]" * 200 + b"]}",
                 b'{"revision": NaN, "changes": []}', b'{"revision": 1e999, "changes": []}', b"\xff\xfe{}"):
        res, payload = write(server, "/api/save", body)
        assert res.status == 400, (body[:40], res.status, payload[:300])
        assert b"Traceback" not in payload and len(payload.splitlines()) == 1
    assert_alive(server)


def _mask_change(qid, counts, frame=1):
    return [{"type": "mask", "query": qid, "frame": frame, "mask": {"counts": counts}}]


HUGE_RUNS = {
    "above int64": [2 ** 70],
    "int64 sum wraps to H*W": [H * W, 2 ** 63 - 1, 2 ** 63 - 1, 2],
    "int64 sum wraps, zeros first": [0, 2 ** 62, 2 ** 62, 2 ** 62, 2 ** 62 + H * W],
    "negative run": [H * W + 5, -5],
    "float run": [float(H * W)],
    "bool runs": [True] * (H * W),
    "too many runs": [0] * (H * W + 2) + [H * W],
    "string runs": "abc",
}


def test_malformed_runs_are_400_before_any_decoder(server):
    qid = add_query(server, "runs")
    for name, counts in HUGE_RUNS.items():
        res, payload = write(server, "/api/save", {"revision": server.session.revision,
                                                   "changes": _mask_change(qid, counts)})
        assert res.status == 400, (name, res.status, payload[:300])
        res, payload = write(server, "/api/segment", {"frame": 0, "box": [10, 10, 40, 40], "clicks": [[20, 20, 1]],
                                                      "current": {"counts": counts}})
        assert res.status == 400, (name, res.status, payload[:300])
        assert b"Traceback" not in payload
        with pytest.raises(InputError):
            runs_to_mask(counts, H, W)
    mask = np.zeros((H, W), bool)
    mask[5:9, 7:30] = True
    res, _ = write(server, "/api/save", {"revision": server.session.revision,
                                         "changes": _mask_change(qid, mask_to_runs(mask))})
    assert res.status == 200
    assert_alive(server)


# -- start-up failures, interrupted saves --------------------------------------------------------
def test_port_in_use_or_bad_host_is_one_line_and_releases_the_lock(scene_dir, tmp_path, capsys):
    from annotations.tool import server as srv
    from benchmark.cli import main

    ann = tmp_path / "a.json"
    lock = tmp_path / "a.json.lock"
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen(1)
        port = taken.getsockname()[1]
        rc = main(["annotate", str(scene_dir), "--annotations", str(ann), "--port", str(port)])
        err = capsys.readouterr().err
        assert rc == 2 and "in use" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        assert not lock.exists()
        session = AnnotationSession(load_scene(scene_dir), ann)
        with pytest.raises(InputError, match="in use"):
            srv.start_server(session, "127.0.0.1", port, announce=lambda _: None)
        assert not lock.exists()
    for bad in ("a..b", "::zz", "x" * 300):
        rc = main(["annotate", str(scene_dir), "--annotations", str(ann), "--host", bad])
        err = capsys.readouterr().err
        assert rc == 2 and "cannot resolve" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
        assert not lock.exists()
    AnnotationSession(load_scene(scene_dir), ann).close()  # the lock is free


_KILLED_SAVE = """
import os, signal, sys
from annotations.tool.session import AnnotationSession
from benchmark.loaders import load_scene
session = AnnotationSession(load_scene(sys.argv[1]), sys.argv[2])
os.replace = lambda *a, **k: os.kill(os.getpid(), signal.SIGKILL)  # die between write and rename
session.add_query(session.revision, "killed")
"""


def test_a_save_killed_in_flight_leaves_no_temp_file_behind(scene_dir, tmp_path):
    ann = tmp_path / "a.json"
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([sys.executable, "-c", _KILLED_SAVE, str(scene_dir), str(ann)], env=env, cwd=ROOT,
                          capture_output=True, timeout=120)
    assert proc.returncode == -9, proc.stderr.decode()[-2000:]
    left = [p.name for p in tmp_path.iterdir() if p.name.endswith(".tmp")]
    assert left, "the killed save should have left its temporary file (else this test tests nothing)"
    bystander = tmp_path / ".b.json.abcd1234.tmp"  # another file's temporary file: not ours to remove
    bystander.write_text("x")
    session = AnnotationSession(load_scene(scene_dir), ann)
    try:
        assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".a.json.")]
        assert bystander.exists() and not ann.exists()
    finally:
        session.close()


# -- fuzz over every route ----------------------------------------------------------------------
GET_PATHS = [b"/", b"/index.html", b"/static/app.js", b"/static/../session.py", b"/favicon.ico", b"/api/state",
             b"/api/frame/0.jpg", b"/api/frame/3.jpg", b"/api/frame/4.jpg", b"/api/masks/1", b"/api/thumb/2.jpg",
             b"/api/review", b"/api/frame/\xb2.jpg", b"/api/masks/" + b"9" * 5000, "/api/masks/\u0661".encode(),
             b"http://[bad/x", b"//evil/api/state", b"*", b"/api/frame/-1.jpg"]
POST_PATHS = [b"/api/save", b"/api/queries/add", b"/api/queries/delete", b"/api/queries/reviewed", b"/api/segment",
              b"/api/propagate",
              b"/api/export", b"/api/import", b"/api/none"]
QUERIES = [b"", b"?query=1", b"?query=%C2%B2", b"?query=%D9%A1%D9%A2", b"?query=" + b"9" * 5000, b"?query=-1",
           b"?query=&query=2", b"?token=x", b"?%ff%fe=%00"]

ints = st.one_of(st.integers(-3, 6), st.sampled_from([2 ** 31, 2 ** 63 - 1, 2 ** 63, 2 ** 64 + 5, 2 ** 70, -2 ** 64]))
scalars = st.one_of(st.none(), st.booleans(), ints, st.floats(allow_nan=False, allow_infinity=False, allow_subnormal=False),
                    st.text(max_size=8))
idx = st.one_of(st.integers(0, 3), ints)  # mostly a frame / query that exists
runs = st.one_of(
    st.just([H * W]), st.just([0, H * W]), st.just([10, 20, H * W - 30]),
    st.lists(ints, max_size=6), st.lists(scalars, max_size=4),
    st.sampled_from(list(HUGE_RUNS.values())), scalars)
mask_payload = st.one_of(st.fixed_dictionaries({"counts": runs}), st.fixed_dictionaries({"counts": runs}),
                         st.none(), scalars, st.just({"absent": True}),
                         st.dictionaries(st.text(max_size=5), scalars, max_size=3))


@st.composite
def change(draw, qid):
    kind = draw(st.integers(0, 9))
    if kind < 6:  # a mask for a query that exists: the runs are what is fuzzed
        return {"type": "mask", "query": qid, "frame": draw(idx), "mask": draw(mask_payload)}
    if kind < 8:
        return {"type": draw(st.sampled_from(["mask", "intervals"])), "query": draw(idx), "frame": draw(idx),
                "mask": draw(mask_payload)}
    if kind < 9:
        return {"type": "intervals", "query": draw(idx),
                "intervals": draw(st.one_of(scalars, st.lists(st.lists(ints, max_size=3), max_size=3)))}
    return draw(scalars)


point = st.lists(st.one_of(ints, st.floats(allow_nan=False, allow_infinity=False, width=32, allow_subnormal=False)), min_size=0, max_size=5)
coco = st.fixed_dictionaries({
    "images": st.one_of(scalars, st.lists(st.fixed_dictionaries({"id": scalars, "file_name": st.sampled_from(
        ["r_000.png", "r_001", "../x", 3]), "width": ints, "height": ints}), max_size=2)),
    "categories": st.one_of(scalars, st.lists(st.fixed_dictionaries({"id": ints, "name": scalars}), max_size=2)),
    "annotations": st.one_of(scalars, st.lists(st.fixed_dictionaries(
        {"id": ints, "image_id": scalars, "category_id": ints,
         "segmentation": st.one_of(scalars, st.fixed_dictionaries({"size": st.lists(ints, max_size=3), "counts": runs}),
                                   st.lists(st.lists(scalars, max_size=8), max_size=2))}), max_size=2))})


@st.composite
def post_body(draw, revision_hint, clean, qid):
    rev = draw(st.one_of(st.just(revision_hint), scalars)) if not clean or draw(st.integers(0, 9)) == 9 else revision_hint
    route = draw(st.sampled_from(POST_PATHS))
    shape = "route" if clean else draw(st.sampled_from(["route", "deep", "bytes", "numbers"]))
    if shape == "deep":
        n = draw(st.sampled_from([50, 1500, 100_000]))
        return route, draw(st.sampled_from([b"[" * n + b"]" * n, b'{"a":' * n + b"0" + b"}" * n]))
    if shape == "bytes":
        return route, draw(st.binary(max_size=64))
    if shape == "numbers":
        return route, draw(st.sampled_from([b'{"revision": ' + b"7" * 5000 + b"}", b'{"frame": 1e999}',
                                            b'{"frame": NaN, "box": [Infinity, 0, 1, 2]}', b'{"count": -Infinity}']))
    if route == b"/api/save":
        obj = {"revision": rev, "changes": draw(scalars if draw(st.integers(0, 5)) == 5 else st.lists(change(qid), min_size=1, max_size=3)),
               "timing": draw(st.one_of(st.none(), scalars, st.dictionaries(st.text(max_size=4), scalars, max_size=2)))}
    elif route == b"/api/queries/add":
        obj = {"revision": rev, "text": draw(st.one_of(st.sampled_from(["cat", "dog", " "]), scalars)),
               "kind": draw(st.sampled_from(["agnostic", "sensitive", 1, None])), "base": draw(idx),
               "level": draw(scalars)}
    elif route == b"/api/queries/delete":
        obj = {"revision": rev, "query": draw(st.one_of(st.just(qid), idx))}
    elif route == b"/api/segment":
        obj = {"frame": draw(idx), "box": draw(st.one_of(st.none(), point)),
               "clicks": draw(st.one_of(scalars, st.lists(st.one_of(point, scalars), max_size=3))),
               "current": draw(st.one_of(st.none(), scalars, st.fixed_dictionaries({"counts": runs})))}
    elif route == b"/api/propagate":
        obj = {"query": draw(st.one_of(st.just(qid), idx)), "frame": draw(idx), "direction": draw(st.one_of(st.sampled_from([1, -1, 1.0]), ints)),
               "count": draw(st.one_of(ints, st.floats(allow_nan=False, allow_infinity=False, allow_subnormal=False)))}
    elif route == b"/api/export":
        obj = {"format": draw(st.sampled_from(["project", "coco-rle", "nope", 3, None]))}
    else:
        data = draw(st.one_of(st.binary(max_size=48), coco.map(lambda d: json.dumps(d).encode()),
                              st.just(b"PK\x03\x04garbage")))
        obj = {"revision": rev, "format": draw(st.sampled_from(["project", "coco-rle", "release", "video-annotations",
                                                                "x"])),
               "filename": draw(st.sampled_from(["a.json", "../../etc/passwd", "r.zip", 5])),
               "data": draw(st.one_of(st.just(base64.b64encode(data).decode()), scalars))}
    if draw(st.integers(0, 4)) == 4:
        obj = {k: v for k, v in obj.items() if draw(st.booleans())}
    return route, json.dumps(obj).encode()


@st.composite
def any_request(draw, server):
    """Most requests are well framed and authorised (so that the routes themselves are exercised,
    with hostile bodies); the rest break framing, headers or authorisation as well."""
    clean = draw(st.integers(0, 9)) < 6
    headers: dict = {}
    token = "good" if clean else draw(st.sampled_from(["good", "missing", "wrong", "unicode"]))
    if token != "missing":
        headers["X-Bench4d-Token"] = {"good": server.token, "wrong": "x" * 32,
                                      "unicode": "\u00e9\u00b2".encode("latin-1")}[token]
    if not clean and draw(st.booleans()):
        headers["Origin"] = draw(st.sampled_from(["http://evil.example", f"http://{host(server)}", "null", "\xff"]))
    if not clean and draw(st.booleans()):
        headers["Cookie"] = draw(st.sampled_from([b"bench4d_token_1=x", b"\xff=\xfe;;=", b"a" * 3000]))
    if draw(st.integers(0, 2)) == 2:
        method = draw(st.sampled_from(["GET", "GET", "HEAD"] + ([] if clean else ["OPTIONS", "PUT", "BREW", "get"])))
        path = draw(st.sampled_from(GET_PATHS)) + draw(st.sampled_from(QUERIES))
        body = b"" if clean else draw(st.sampled_from([b"", b"GET /api/smuggled HTTP/1.1\r\n\r\n"]))
    else:
        method = "POST"
        qid = min((q.id for q in server.session.aset.agnostic_queries), default=1)
        path, body = draw(post_body(server.session.revision, clean, qid))
        headers["Content-Type"] = "application/json" if clean else draw(st.sampled_from(
            ["application/json", "text/plain", "application/json; charset=\xff", ""]))
    length = "right" if clean else draw(st.sampled_from(
        ["right", "none", "huge", "big", "unicode", "negative", "short", "double", "chunked"]))
    if length == "right" and (body or method == "POST"):
        headers["Content-Length"] = len(body)
    elif length == "huge":
        headers["Content-Length"] = "9" * 40
    elif length == "big":
        headers["Content-Length"] = 399 * 1024 * 1024  # allowed size, never sent: the read must end at EOF
    elif length == "unicode":
        headers["Content-Length"] = draw(st.sampled_from(["\u00b2".encode("latin-1"), "\u0661\u0662".encode()]))
    elif length == "negative":
        headers["Content-Length"] = -len(body)
    elif length == "short":
        headers["Content-Length"] = max(0, len(body) - 3)
    elif length == "double":
        headers["Content-Length"] = f"{len(body)}\r\nContent-Length: {len(body) + 1}"
    elif length == "chunked":
        headers["Transfer-Encoding"] = "chunked"
    raw = raw_request(server, method, path, headers, body)
    if not clean and draw(st.integers(0, 4)) == 4:
        raw = raw.replace(f"Host: {host(server)}".encode(), b"Host: evil.example", 1)
    return raw


@pytest.fixture(scope="module")
def fuzz_server(scene_dir, tmp_path_factory):
    httpd = _start(scene_dir, tmp_path_factory.mktemp("ann_fuzz"))
    add_query(httpd, "thing")
    yield httpd
    _stop(httpd)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture,
                                                                   HealthCheck.too_slow, HealthCheck.data_too_large])
@given(data=st.data())
def test_fuzz_every_route_never_5xx_never_a_traceback(fuzz_server, data):
    if not fuzz_server.session.aset.agnostic_queries:  # the fuzz may delete it: masks need one
        add_query(fuzz_server, "thing")
    raw = data.draw(any_request(fuzz_server))
    stream = exchange(fuzz_server, raw, wait=10.0)
    codes = statuses(stream)
    assert all(c < 500 for c in codes), (raw[:300], stream[:500])
    assert b"Traceback" not in stream and b'File "' not in stream, stream[:500]
    assert_alive(fuzz_server)

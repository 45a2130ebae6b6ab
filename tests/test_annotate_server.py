"""The annotation server's HTTP surface: Host check, token, Origin, no CORS, 409, static whitelist."""

from __future__ import annotations

import argparse
import http.client
import json
import threading

import cv2
import numpy as np
import pytest

from annotations.tool.server import AnnotationServer
from annotations.tool.session import AnnotationSession, mask_to_runs
from annotations.tool.synthetic import rigid_sequence, write_dnerf_scene
from benchmark.loaders import load_scene

W, H = 96, 64


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    seq = rigid_sequence(4, W, H, seed=1)
    root = tmp_path_factory.mktemp("srv")
    scene = load_scene(write_dnerf_scene(seq, root / "scene"))
    session = AnnotationSession(scene, root / "ann" / "a.json")
    httpd = AnnotationServer(session, "127.0.0.1", 0)
    httpd.quiet = True
    thread = threading.Thread(target=httpd.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
    thread.start()
    yield httpd
    httpd.shutdown()
    httpd.server_close()
    session.close()


def request(server, method, path, body=None, headers=None, host=None):
    conn = http.client.HTTPConnection("127.0.0.1", server.port, timeout=10)
    h = {"Host": host or f"127.0.0.1:{server.port}"}
    h.update(headers or {})
    data = None
    if body is not None:
        data = json.dumps(body).encode()
        h.setdefault("Content-Type", "application/json")
    conn.request(method, path, body=data, headers=h)
    res = conn.getresponse()
    payload = res.read()
    conn.close()
    return res, payload


def write(server, path, body, **headers):
    return request(server, "POST", path, body, {"X-Bench4d-Token": server.token, **headers})


def test_binds_loopback_by_default(server):
    assert server.server_address[0] == "127.0.0.1"
    from benchmark.commands import annotate

    p = argparse.ArgumentParser()
    annotate.add_arguments(p)
    args = p.parse_args(["scene", "--annotations", "a.json"])
    assert args.host == "127.0.0.1" and args.port == 0 and args.segmenter == "grabcut"
    assert "#token=" in server.url and server.url.startswith("http://127.0.0.1:")


def test_page_and_static_files_with_security_headers(server):
    res, body = request(server, "GET", "/")
    assert res.status == 200 and b'type="module"' in body
    csp = res.getheader("Content-Security-Policy")
    assert "default-src 'none'" in csp and "script-src 'self'" in csp and "connect-src 'self'" in csp
    assert res.getheader("Access-Control-Allow-Origin") is None
    res, body = request(server, "GET", "/static/app.js")
    assert res.status == 200 and res.getheader("Content-Type").startswith("text/javascript")
    # nothing is fetched from elsewhere: no absolute URLs in the page's files
    for name in server.static:
        text = (server.static[name]).read_text()
        assert "http://" not in text and "https://" not in text and "//cdn" not in text, name
    for bad in ("/static/../session.py", "/static/%2e%2e/session.py", "/static/session.py", "/../../etc/passwd"):
        res, _ = request(server, "GET", bad)
        assert res.status == 404, bad


def test_host_header_is_checked(server):
    for host in (f"127.0.0.1:{server.port}", f"localhost:{server.port}"):
        res, _ = request(server, "GET", "/api/state", host=host)
        assert res.status == 200
    for host in (f"evil.example:{server.port}", "127.0.0.1:1", f"127.0.0.1.evil.example:{server.port}"):
        res, _ = request(server, "GET", "/api/state", host=host)
        assert res.status == 403, host
        res, _ = request(server, "POST", "/api/save", {"revision": 0, "changes": []},
                         {"X-Bench4d-Token": server.token}, host=host)
        assert res.status == 403, host


def test_writes_need_the_token_json_and_own_origin(server):
    body = {"revision": server.session.revision, "changes": []}
    res, _ = request(server, "POST", "/api/save", body)
    assert res.status == 403
    res, _ = request(server, "POST", "/api/save", body, {"X-Bench4d-Token": "wrong"})
    assert res.status == 403
    res, _ = write(server, "/api/save", body, Origin="http://evil.example")
    assert res.status == 403
    res, _ = write(server, "/api/save", body, **{"Content-Type": "text/plain"})
    assert res.status == 400
    res, payload = write(server, "/api/save", body, Origin=f"http://127.0.0.1:{server.port}")
    assert res.status == 200 and json.loads(payload)["revision"] == body["revision"] + 1


def test_no_cors_preflight(server):
    res, _ = request(server, "OPTIONS", "/api/save", headers={"Origin": "http://evil.example",
                                                             "Access-Control-Request-Method": "POST"})
    assert res.status == 405
    assert res.getheader("Access-Control-Allow-Origin") is None
    assert res.getheader("Access-Control-Allow-Headers") is None


def test_stale_save_is_409_and_frames_are_served_by_index(server):
    res, payload = write(server, "/api/queries/add", {"revision": server.session.revision, "text": "blob"})
    assert res.status == 200
    qid, rev = json.loads(payload)["id"], json.loads(payload)["revision"]
    mask = np.zeros((H, W), bool)
    mask[10:20, 30:50] = True
    change = [{"type": "mask", "query": qid, "frame": 2, "mask": {"counts": mask_to_runs(mask)}}]
    res, payload = write(server, "/api/save", {"revision": rev, "changes": change})
    assert res.status == 200
    res, payload = write(server, "/api/save", {"revision": rev, "changes": change})
    assert res.status == 409 and json.loads(payload)["revision"] == rev + 1
    res, payload = request(server, "GET", "/api/masks/2")
    got = json.loads(payload)["masks"][str(qid)]
    assert got["state"] == "mask" and got["counts"] == mask_to_runs(mask)
    res, payload = request(server, "GET", "/api/frame/2.jpg")
    img = cv2.imdecode(np.frombuffer(payload, np.uint8), cv2.IMREAD_COLOR)
    assert res.status == 200 and img.shape == (H, W, 3)
    res, _ = request(server, "GET", "/api/frame/99.jpg")
    assert res.status == 400
    res, payload = write(server, "/api/save", {"revision": rev + 1, "changes": [{"type": "mask", "query": qid,
                                                                                  "frame": "../../x", "mask": None}]})
    assert res.status == 400 and b"frame index" in payload

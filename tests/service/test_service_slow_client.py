"""Slow clients cannot hold the door: a real server, a client trickling its upload over raw sockets.

Before, the upload guard let one submission in at a time and a slow uploader kept its turn while it
trickled: every other submission waited the guard's whole 2 s (median 2.2 s against 0.1 s alone,
bench/bench_slow_uploader.py), and a client that stopped sending held a turn forever.
"""

from __future__ import annotations

import socket
import threading
import time

import pytest
from servers import BOUNDARY, Server, add_user, multipart, slow_upload, submit

FAST = {"method": "tri", "skeleton": "points", "fps": 120.0}


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("slow_data")
    token = add_user(data, "una")
    env = {"ACINOSET_WARM_START": "0", "ACINOSET_UPLOAD_IDLE_TIMEOUT_SECONDS": "1.5",
           "ACINOSET_MAX_RECEIVING_UPLOADS": "2"}
    srv = Server(data, data.parent / "slow_server.log", workers=1, env=env).start(ready=(200,))
    srv.token = token
    yield srv
    srv.stop()


def _open_upload(port: int, token: str, length: int) -> socket.socket:
    s = socket.create_connection(("127.0.0.1", port), timeout=30)
    s.sendall((f"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
               f"Content-Type: multipart/form-data; boundary={BOUNDARY}\r\n"
               f"Content-Length: {length}\r\n\r\n").encode())
    return s


def test_other_submissions_do_not_wait_for_a_slow_uploader(server, small_run):
    with server.client(server.token) as c:
        assert submit(c, small_run, FAST).status_code == 202  # the readers started
        slow: dict = {}
        body = multipart(small_run, FAST)
        th = threading.Thread(target=slow_upload, args=(server.port, server.token, body, 6.0, slow))
        th.start()
        time.sleep(0.5)
        took = []
        while th.is_alive():
            t = time.perf_counter()
            r = submit(c, small_run, FAST)
            took.append(time.perf_counter() - t)
            assert r.status_code == 202, r.text
        th.join()
    assert slow["status"] == "HTTP/1.1 202 Accepted", slow  # the slow one is served too, in the end
    assert len(took) >= 3 and sorted(took)[len(took) // 2] < 1.0, took


def test_an_upload_that_stalls_is_answered_408_and_frees_its_place(server, small_run):
    body = multipart(small_run, FAST)
    s = _open_upload(server.port, server.token, len(body))
    s.sendall(body[:1000])  # then nothing
    t = time.perf_counter()
    answer = s.recv(4096).decode(errors="replace")
    waited = time.perf_counter() - t
    s.settimeout(5)
    while "ACINOSET_UPLOAD_IDLE_TIMEOUT_SECONDS" not in answer:  # the body may come in a segment of its own
        more = s.recv(4096)
        if not more:
            break
        answer += more.decode(errors="replace")
    s.close()
    assert answer.startswith("HTTP/1.1 408"), answer
    assert 1.0 < waited < 10
    assert "ACINOSET_UPLOAD_IDLE_TIMEOUT_SECONDS" in answer


def test_more_uploads_arriving_at_once_than_allowed_get_503(server, small_run):
    body = multipart(small_run, FAST)
    held = [_open_upload(server.port, server.token, len(body)) for _ in range(2)]
    try:
        for s in held:
            s.sendall(body[:100])
        time.sleep(0.3)
        with server.client(server.token) as c:
            r = submit(c, small_run, FAST)
            assert r.status_code == 503 and r.headers["retry-after"] == "5", r.text
            assert "ACINOSET_MAX_RECEIVING_UPLOADS" in r.json()["detail"]
    finally:
        for s in held:
            s.close()
    time.sleep(0.5)
    with server.client(server.token) as c:
        assert submit(c, small_run, FAST).status_code == 202


def test_connections_beyond_the_cap_are_answered_503(tmp_path):
    """ACINOSET_MAX_CONNECTIONS caps the open connections (uvicorn's limit_concurrency): idle clients
    that hold sockets open cannot take every slot of the server's event loop."""
    import httpx

    data = tmp_path / "data"
    srv = Server(data, tmp_path / "server.log", workers=1,
                 env={"ACINOSET_WARM_START": "0", "ACINOSET_MAX_CONNECTIONS": "4"}).start(ready=(200,))
    held = []
    try:
        for _ in range(4):
            s = socket.create_connection(("127.0.0.1", srv.port), timeout=10)
            s.sendall(b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n")  # answered, then kept alive
            s.recv(4096)
            held.append(s)
        assert httpx.get(srv.url + "/healthz", timeout=10).status_code == 503
        for s in held:
            s.close()
        held.clear()
        time.sleep(0.5)
        assert httpx.get(srv.url + "/healthz", timeout=10).status_code == 200
    finally:
        for s in held:
            s.close()
        srv.stop()

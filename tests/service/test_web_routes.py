"""The pages' routes on a real server: what they serve, and what they refuse (no browser needed)."""

from __future__ import annotations

import re

import httpx
import pytest
from servers import Server


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    data = tmp_path_factory.mktemp("pages_data")
    srv = Server(data, data.parent / "pages_server.log", workers=1).start()
    yield srv
    srv.stop()


@pytest.fixture
def client(server) -> httpx.Client:
    with server.client() as c:
        yield c


def test_pages_are_html_and_load_only_local_scripts(client):
    c = client
    for path in ("/", "/login", "/jobs/new", "/jobs/0123456789abcdef0123456789abcdef", "/docs",
                 "/calibrations/0123456789abcdef0123456789abcdef"):
        r = c.get(path)
        assert r.status_code == 200, path
        assert r.headers["content-type"].startswith("text/html")
        assert r.headers["cache-control"] == "no-cache"
        for src in re.findall(r'(?:src|href)="([^"]+)"', r.text):
            assert src.startswith("/") or src.startswith("#"), f"{path} refers outside the server: {src}"
            if src.startswith("/static/"):
                assert c.get(src).status_code == 200, f"{path}: {src} is missing"


def test_every_page_has_one_h1_a_title_and_a_language(client):
    c = client
    for path in ("/", "/login", "/jobs/new", "/jobs/abc", "/docs", "/calibrations/abc"):
        text = c.get(path).text
        assert '<html lang="en">' in text and "<title>" in text
        assert text.count("<h1") == 1, path
        assert 'href="#main"' in text and 'id="main"' in text, f"{path}: no skip link"


def test_plotly_comes_from_the_installed_package(client):
    r = client.get("/static/plotly.min.js")
    assert r.status_code == 200
    assert r.headers["content-type"].startswith("text/javascript")
    assert "max-age" in r.headers["cache-control"]
    assert len(r.content) > 1_000_000 and b"plotly" in r.content[:2000].lower()


def test_static_files_are_confined_to_the_folder(client):
    c = client
    assert c.get("/static/app.css").headers["content-type"].startswith("text/css")
    for bad in ("/static/..%2Fweb.py", "/static/web.py", "/static/.hidden.js", "/static/nope.js",
                "/static/%2e%2e%2f%2e%2e%2fpyproject.toml"):
        assert c.get(bad).status_code == 404, bad
    assert c.get("/jobs/..%2F..%2Fetc").status_code == 404
    assert c.get("/calibrations/..%2F..%2Fetc").status_code == 404


def test_every_answer_carries_a_content_security_policy_and_docs_load_nothing_from_elsewhere(client):
    """Issue item 11: /docs loaded swagger-ui from a CDN without SRI on the origin where the token
    lives, and no answer had a Content-Security-Policy."""
    for path in ("/", "/login", "/docs", "/healthz", "/openapi.json", "/v1/jobs", "/static/app.css", "/nope"):
        r = client.get(path)
        csp = r.headers.get("content-security-policy", "")
        assert "default-src 'self'" in csp and "script-src 'self';" in csp and "frame-ancestors 'none'" in csp, path
        assert r.headers["x-content-type-options"] == "nosniff", path
    docs = client.get("/docs").text
    assert "<script" not in docs and "cdn" not in docs.lower() and "http" not in docs.replace("/openapi.json", "")
    assert "/v1/jobs/{job_id}/result" in docs and "Submit a job" in docs
    assert client.get("/redoc").status_code == 404

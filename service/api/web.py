"""The web pages: sign in, the job list, the submit form, the job page and the calibration page.

Plain HTML and JavaScript (``service/templates``, ``service/static``) that call the REST API v1 with
the user's token, which the browser keeps in localStorage. Nothing is fetched from outside the
server: plotly.js comes from the plotly wheel (:func:`graph.viewer.playback.plotly_js_path`), the result view
and its stylesheet from the library (:mod:`graph.viewer`), both under ``/static/``. The app includes
:data:`router` with ``include_in_schema=False``: pages are not part of the REST contract.

Every page is ``templates/_page.html`` (the head, the skip link and the top bar, once) around its own
template (its ``<main>`` and its scripts), with its title. A template's ``{{viewer_styles}}`` and
``{{viewer_scripts}}`` become the tags loading
:data:`graph.viewer.STYLES` and :data:`graph.viewer.SCRIPTS`; ``{{job_statuses}}`` becomes the job
statuses of :mod:`service.store` as JSON (``<script type="application/json" id="job-statuses">``),
which the page scripts read instead of naming them again.
"""

from __future__ import annotations

import html
import json
import re
from pathlib import Path
from urllib.parse import urlencode, urlsplit

from fastapi import APIRouter, HTTPException, Request, Response
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse

from graph import viewer
from graph.viewer.playback import plotly_js_path
from service.store import ACTIVE, STATUSES

HERE = Path(__file__).resolve().parents[1]  # service/
TEMPLATES = HERE / "templates"
STATIC = HERE / "static"
# The result view's files, served beside service/static (a name there never shadows one of these).
VIEWER_FILES = frozenset(viewer.SCRIPTS + viewer.STYLES)

router = APIRouter(include_in_schema=False)

_STATIC_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*\.(js|css)$")
_JOB_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
_MEDIA = {"js": "text/javascript; charset=utf-8", "css": "text/css; charset=utf-8"}
# Pages and our scripts are revalidated on every load (small, and an upgrade shows at once);
# plotly.js is large and changes only with the installed plotly.
_PAGE_HEADERS = {"Cache-Control": "no-cache", "X-Content-Type-Options": "nosniff", "Referrer-Policy": "no-referrer",
                 "X-Frame-Options": "DENY"}
_PLOTLY_HEADERS = {"Cache-Control": "public, max-age=86400", "X-Content-Type-Options": "nosniff"}


def _json_script(element_id: str, value) -> str:
    """Value as JSON in a ``<script type="application/json">``; no ``<`` can end it early."""
    text = json.dumps(value, separators=(",", ":")).replace("<", "\\u003c")
    return f'<script type="application/json" id="{element_id}">{text}</script>'


# What the {{name}} marks of the templates stand for.
_FILLS = {
    "viewer_styles": "\n".join(f'<link rel="stylesheet" href="/static/{html.escape(n)}">' for n in viewer.STYLES),
    "viewer_scripts": "\n".join(f'<script src="/static/{html.escape(n)}"></script>' for n in viewer.SCRIPTS),
    "job_statuses": _json_script("job-statuses", {"all": list(STATUSES), "active": list(ACTIVE)}),
}
_MARK = re.compile(r"\{\{(\w+)\}\}")


def _filled(name: str, fills: dict[str, str]) -> str:
    """A template with its marks filled; a mark nobody fills is an error, not left in the page."""
    return _MARK.sub(lambda m: fills[m.group(1)], (TEMPLATES / name).read_text(encoding="utf-8"))


def render_template(name: str, title: str) -> str:
    """The page of template ``name`` (its ``<main>`` and scripts) in ``_page.html``, titled ``title``."""
    main = _filled(name, _FILLS).rstrip("\n")
    return _filled("_page.html", {**_FILLS, "title": html.escape(title), "main": main})


def _page(name: str, title: str, status_code: int = 200) -> HTMLResponse:
    return HTMLResponse(render_template(name, title), status_code=status_code, headers=_PAGE_HEADERS)


@router.get("/", response_class=HTMLResponse)
def jobs_page() -> HTMLResponse:
    """The caller's jobs with live status and progress."""
    return _page("jobs.html", "Jobs")


_DOT_SEGMENTS = {".", "..", "%2e", ".%2e", "%2e.", "%2e%2e"}  # what a browser's URL parser resolves away


def same_origin_path(target: str) -> bool:
    """Whether ``target`` (a decoded ``next`` parameter) is a path on this server and nothing else:
    it starts with one ``/``, has no backslash or control character (browsers read ``/\\host``
    and ``/\t/host`` as another host), no scheme or host of its own, and no empty or dot segment in
    its path (a browser resolves ``/.//host`` and ``/..//host`` to ``//host``, another host)."""
    if not target.startswith("/") or target.startswith("//"):
        return False
    if "\\" in target or any(ord(c) < 0x20 or ord(c) == 0x7F for c in target):
        return False
    parts = urlsplit(target)
    if parts.scheme or parts.netloc:
        return False
    segments = parts.path.split("/")[1:]
    return not any(s.lower() in _DOT_SEGMENTS for s in segments) and "" not in segments[:-1]


@router.get("/login", response_class=HTMLResponse)
def login_page(next: str | None = None, reason: str | None = None) -> Response:
    """The sign-in page. A ``next`` that is not a path of this server is dropped (the page's script
    checks it again before it goes there)."""
    if next is not None and not same_origin_path(next):
        query = urlencode({"reason": reason} if reason else {})
        return RedirectResponse("/login" + (f"?{query}" if query else ""), status_code=303, headers=_PAGE_HEADERS)
    return _page("login.html", "Sign in")


@router.get("/jobs/new", response_class=HTMLResponse)
def submit_page() -> HTMLResponse:
    return _page("submit.html", "New job")


@router.get("/jobs/{job_id}", response_class=HTMLResponse)
def job_page(job_id: str) -> HTMLResponse:
    """One job. The page itself holds no job data: its script asks the API, with the user's token."""
    if not _JOB_ID.match(job_id):
        raise HTTPException(404, "no such page")
    return _page("job.html", "Job")


@router.get("/calibrations", response_class=HTMLResponse)
def calibrations_page() -> HTMLResponse:
    """The caller's calibrations, newest first (its script asks the API)."""
    return _page("calibrations.html", "Calibrations")


@router.get("/calibrations/new", response_class=HTMLResponse)
def calibrate_page() -> HTMLResponse:
    """The form that calibrates a rig from board detections or videos."""
    return _page("calibrate.html", "New calibration")


@router.get("/calibrations/{calibration_id}", response_class=HTMLResponse)
def calibration_page(calibration_id: str) -> HTMLResponse:
    """One calibration: status, quality per camera, downloads and figures (its script asks the API)."""
    if not _JOB_ID.match(calibration_id):
        raise HTTPException(404, "no such page")
    return _page("calibration.html", "Calibration")


@router.get("/docs", response_class=HTMLResponse)
def api_docs(request: Request) -> HTMLResponse:
    """The REST contract as a page of this server: every operation, its parameters and answers, from
    the app's OpenAPI spec (the whole spec is ``/openapi.json``). No script, nothing from elsewhere."""
    spec = request.app.openapi()
    e = html.escape
    rows = []
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            params = ", ".join(f"{p['name']} ({p['in']})" for p in op.get("parameters", []))
            answers = ", ".join(sorted(op.get("responses", {})))
            rows.append(f"<tr><td><code>{e(method.upper())}</code></td><td><code>{e(path)}</code></td>"
                        f"<td>{e(op.get('summary', ''))}</td><td>{e(params)}</td><td>{e(answers)}</td></tr>")
    body = (f'<!doctype html>\n<html lang="en">\n<head>\n<meta charset="utf-8">\n<title>API · acinoset</title>\n'
            f'<link rel="stylesheet" href="/static/app.css">\n</head>\n<body>\n<a class="skip" href="#main">Skip to '
            f'content</a>\n<main id="main">\n'
            f'<h1>{e(spec["info"]["title"])} REST API {e(spec["info"]["version"])}</h1>\n'
            + "".join(f"<p>{e(par)}</p>\n" for par in spec["info"].get("description", "").split("\n\n"))
            + '<p>The whole contract: <a href="/openapi.json">/openapi.json</a> (OpenAPI 3).</p>\n'
            '<table>\n<thead><tr><th>method</th><th>path</th><th>what</th><th>parameters</th><th>answers</th></tr>'
            '</thead>\n<tbody>\n' + "\n".join(rows) + "\n</tbody>\n</table>\n</main>\n</body>\n</html>\n")
    return HTMLResponse(body, headers=_PAGE_HEADERS)


@router.get("/static/plotly.min.js")
def plotly_js() -> FileResponse:
    return FileResponse(plotly_js_path(), media_type=_MEDIA["js"], headers=_PLOTLY_HEADERS)


@router.get("/static/{name}")
def static_file(name: str) -> FileResponse:
    """A script or stylesheet of the pages: one of the result view's files, or one in
    ``service/static``; nothing else."""
    m = _STATIC_NAME.match(name)
    path = (viewer.viewer_dir() if name in VIEWER_FILES else STATIC) / name
    if not m or not path.is_file():
        raise HTTPException(404, f"no static file {name!r}")
    return FileResponse(path, media_type=_MEDIA[m.group(1)], headers=_PAGE_HEADERS)

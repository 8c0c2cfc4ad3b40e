"""The HTML playback file: plotly.js, the result view and the payload (:mod:`graph.viewer.payload`)
inlined in one page, so that it opens offline from a laptop, a shared drive or an e-mail attachment.
"""

from __future__ import annotations

import html
import importlib.util
from collections.abc import Sequence
from pathlib import Path

from graph.types import Result
from graph.viewer import SCRIPTS, STYLES, viewer_dir
from graph.viewer.payload import group_payload, payload_json, result_payload

HTML_NAME = "playback.html"



def plotly_js_path() -> Path:
    """plotly.min.js as shipped inside the plotly wheel (no network needed)."""
    spec = importlib.util.find_spec("plotly")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError("the plotly package is not installed")
    p = Path(list(spec.submodule_search_locations)[0]) / "package_data" / "plotly.min.js"
    if not p.is_file():
        raise FileNotFoundError(f"{p} is missing from the plotly package")
    return p


def _script_text(text: str) -> str:
    """Make text safe inside ``<script>``: no ``</script`` or ``<!--`` can end it early."""
    return text.replace("</", "<\\/").replace("<!--", "<\\!--")


def playback_html(result: Result | Sequence[tuple[str, Result]], calibration=None, title: str | None = None) -> str:
    """One self-contained HTML page: plotly.js, the result view and the payload inlined; of several
    individuals solved together (``(name, result)`` pairs), them all in one view
    (:func:`graph.viewer.payload.group_payload`)."""
    d = viewer_dir()
    if isinstance(result, Result):
        data = result_payload(result, calibration)
    else:
        data = group_payload(result, calibration)
        names = ", ".join(name for name, _ in result)
        result = result[0][1]
        title = title or f"acinoset: {result.method} / {result.skeleton}, {names}, {result.positions.shape[0]} frames"
    payload = payload_json(data).decode("utf-8")
    css = "\n".join((d / name).read_text(encoding="utf-8") for name in STYLES)
    view = "\n".join((d / name).read_text(encoding="utf-8") for name in SCRIPTS)
    plotly = plotly_js_path().read_text(encoding="utf-8")
    title = title or f"acinoset: {result.method} / {result.skeleton}, {result.positions.shape[0]} frames"
    return f"""<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{html.escape(title)}</title>
<style>{css}</style>
<script>{_script_text(plotly)}</script>
<script>{_script_text(view)}</script>
</head>
<body>
<header class="top"><span class="brand">acinoset</span></header>
<main id="main">
<h1>{html.escape(title)}</h1>
<div id="result"><p>Loading the result view&hellip;</p></div>
</main>
<script type="application/json" id="payload">{_script_text(payload)}</script>
<script>
AcinoResultView.render(document.getElementById("result"),
  JSON.parse(document.getElementById("payload").textContent), {{}});
</script>
</body>
</html>
"""


def write_playback_html(result: Result | Sequence[tuple[str, Result]], path: str | Path, calibration=None) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(playback_html(result, calibration), encoding="utf-8")
    return path

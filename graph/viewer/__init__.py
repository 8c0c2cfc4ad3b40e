"""The 3D result view, shipped as package data of the library: the HTML playback file of
:mod:`graph.viewer.playback` inlines it, and the service's pages load it from here.

``dom.js`` is the DOM helper (``window.AcinoDom.el``) the view and the service's page scripts share,
``result-view.js`` the view (``window.AcinoResultView.render``), ``result-view.css`` its look and the
base of the service's pages. Plotly is not part of it: the page supplies ``window.Plotly``.
"""

from importlib import resources
from pathlib import Path


def viewer_dir() -> Path:
    """The folder holding the files of :data:`SCRIPTS` and :data:`STYLES`."""
    return Path(str(resources.files(__name__)))

# What a page needs of the view, in load order: the HTML playback of graph.viewer.playback inlines them, the
# service serves them under /static/.
SCRIPTS: tuple[str, ...] = ("dom.js", "result-view.js")
STYLES: tuple[str, ...] = ("result-view.css",)

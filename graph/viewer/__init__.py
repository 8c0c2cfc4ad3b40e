"""The 3D result view (``result-view.js``), shipped as package data of the library: the HTML playback
file of :mod:`graph.plot` inlines it, and the service's job page loads it from here."""

from importlib import resources
from pathlib import Path


def viewer_dir() -> Path:
    """The folder holding ``result-view.js`` and its stylesheet."""
    return Path(str(resources.files(__name__)))

# What a page needs of the view, in load order: the HTML playback of graph.plot inlines them.
SCRIPTS: tuple[str, ...] = ("result-view.js",)
STYLES: tuple[str, ...] = ()

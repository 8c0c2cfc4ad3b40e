"""Importing this module compiles the solver once, so the processes forked afterwards start warm.

The embedded backend's forkserver and ``acinoset worker`` import it before forking solves
(:func:`graph.app.warmup.warm_up`: numba compiles the kernels the first time, then loads them from its
cache in well under a second), and each forked solve inherits them instead of loading them again.
It never raises: a failed warm-up only means the first solve of each process compiles for itself.
"""

from __future__ import annotations

from graph.app.warmup import warm_up

_seconds = warm_up()

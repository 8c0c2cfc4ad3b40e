"""Progress on a terminal: one line redrawn in place, for the commands' long work; and the note
that the kernels are being compiled (:func:`compile_notice`).

:class:`ProgressBar` draws ``[#####-----]  50% text`` and is called with a
:class:`graph.types.Progress` (a solve's stage, iteration and cost); :class:`FrameProgress` is called
with ``(done, total)`` frames and adds the rate. Both draw at most every ``min_interval`` seconds
(the end always); the commands make one only when stderr is a terminal.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import contextmanager
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from graph.types import Progress


class ProgressLine:
    """A plain one-line progress bar on a terminal, ``[#####-----]  50% text``: :meth:`show` draws
    any fraction and text."""

    def __init__(self, stream, width: int = 30, min_interval: float = 0.1):
        self.stream = stream
        self.width = width
        self.min_interval = min_interval
        self._last = 0.0
        self._shown = False

    def show(self, fraction: float, text: str) -> None:
        """``[###---] NN% text``, at most every ``min_interval`` seconds (the end always)."""
        now = time.monotonic()
        if now - self._last < self.min_interval and fraction < 1.0:
            return
        self._last = now
        frac = min(max(float(fraction), 0.0), 1.0)
        filled = int(round(frac * self.width))
        line = f"\r[{'#' * filled}{'-' * (self.width - filled)}] {frac * 100:3.0f}% {text}"
        self.stream.write(line.ljust(self.width + 40))
        self.stream.flush()
        self._shown = True

    def close(self) -> None:
        if self._shown:
            self.stream.write("\n")
            self.stream.flush()


class ProgressBar(ProgressLine):
    """``[#####-----]  50% solve it 12 cost 3.1e+03``, called with a :class:`graph.types.Progress`."""

    def __call__(self, p: Progress) -> None:
        text: str = p.stage
        if p.iteration:
            text += f" it {p.iteration}"
        if p.cost == p.cost:  # not NaN
            text += f" cost {p.cost:.3g}"
        if p.detail:
            text += f", {p.detail}"
        self.show(p.fraction, text)


class FrameProgress(ProgressLine):
    """``[#####-----]  50% 450/900 camera-frames, 52/s`` on one terminal line, called with
    ``(done, total)``."""

    def __init__(self, stream, label: str = "camera-frames", width: int = 30, min_interval: float = 0.2):
        super().__init__(stream, width, min_interval)
        self.label = label
        self._t0 = time.monotonic()

    def __call__(self, done: int, total: int) -> None:
        rate = done / max(time.monotonic() - self._t0, 1e-9)
        self.show(done / max(total, 1), f"{done}/{total} {self.label}, {rate:.0f}/s")


@contextmanager
def compile_notice(say: Callable[[str], None]):
    """Within this context, ``say`` is called with one line when numba starts compiling a kernel,
    and with one more when the context ends, giving the time the compiles took; loading a kernel
    from its on-disk cache (``cache=True``) says nothing. A new install (or a new version of the
    kernels) compiles for one to two minutes on two cores (an ``fte`` solve: 120-132 s measured),
    which would otherwise look like a hang."""
    from numba.core import event

    started: list[bool] = []
    compiling = [0.0, 0]  # seconds in outermost compiles; how deep the compile under way is

    class _Notice(event.Listener):
        def on_start(self, ev):
            if not started:
                started.append(True)
                say("compiling the solver's kernels for this machine (once after an install, about half a minute; "
                    "later runs load them from the cache)")
            if compiling[1] == 0:
                compiling[0] -= time.perf_counter()
            compiling[1] += 1

        def on_end(self, ev):
            compiling[1] -= 1
            if compiling[1] == 0:
                compiling[0] += time.perf_counter()

    try:
        with event.install_listener("numba:compile", _Notice()):
            yield
    finally:
        if started:
            say(f"kernels compiled in {compiling[0]:.0f} s (cached for later runs)")

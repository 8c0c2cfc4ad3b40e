"""Progress on a terminal: one line redrawn in place, for the commands' long work.

:class:`ProgressBar` draws ``[#####-----]  50% text`` and is called with a
:class:`graph.types.Progress` (a solve's stage, iteration and cost); :class:`FrameProgress` is called
with ``(done, total)`` frames and adds the rate. Both draw at most every ``min_interval`` seconds
(the end always); the commands make one only when stderr is a terminal.
"""

from __future__ import annotations

import time


class ProgressBar:
    """A plain one-line progress bar on a terminal: ``[#####-----]  50% solve it 12 cost 3.1e+03``.
    Called with a :class:`graph.types.Progress`; :meth:`show` draws any fraction and text."""

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

    def __call__(self, p) -> None:
        text = p.stage
        if p.iteration:
            text += f" it {p.iteration}"
        if p.cost == p.cost:  # not NaN
            text += f" cost {p.cost:.3g}"
        self.show(p.fraction, text)

    def close(self) -> None:
        if self._shown:
            self.stream.write("\n")
            self.stream.flush()


class FrameProgress(ProgressBar):
    """``[#####-----]  50% 450/900 camera-frames, 52/s`` on one terminal line, called with
    ``(done, total)``."""

    def __init__(self, stream, label: str = "camera-frames", width: int = 30, min_interval: float = 0.2):
        super().__init__(stream, width, min_interval)
        self.label = label
        self._t0 = time.monotonic()

    def __call__(self, done: int, total: int) -> None:
        rate = done / max(time.monotonic() - self._t0, 1e-9)
        self.show(done / max(total, 1), f"{done}/{total} {self.label}, {rate:.0f}/s")

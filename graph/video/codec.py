"""Video files in and out, streamed through the ffmpeg binary that the ``imageio-ffmpeg`` wheel ships.

Nothing here uses a system ffmpeg or the network: :func:`ffmpeg_exe` is the bundled binary (the
``video`` extra installs it). Frames travel as raw planar YUV 4:2:0 (``yuv420p``, the layout H.264
stores) through pipes, one frame at a time, so memory does not grow with the length of a video:

* :class:`FrameReader` runs ``ffmpeg -i VIDEO -f rawvideo -pix_fmt yuv420p -`` and hands out one
  :class:`YuvFrame` per ``read`` (a buffer it reuses: copy it to keep it);
* :class:`FrameWriter` runs ``ffmpeg -f rawvideo -pix_fmt yuv420p -i - -c:v libx264 ... OUT.mp4``:
  H.264 in MP4, ``yuv420p``, ``+faststart`` (the index first, so a browser starts playing at once),
  at the input's frame rate, one output frame per frame written.

A ``yuv420p`` frame of width W and height H (both even) is ``W*H`` bytes of luma (Y) followed by
two ``W/2 x H/2`` chroma planes (U = Cb, V = Cr): 1.5 bytes a pixel, half of BGR's 3, and no colour
conversion on either side of the pipe. Odd sizes are padded by one pixel (H.264 in 4:2:0 needs even
ones). :func:`probe` reads a video's size, rate and frame count from its container.
"""

from __future__ import annotations

import io
import os
import subprocess
import tempfile
from dataclasses import dataclass
from fractions import Fraction
from pathlib import Path

import numpy as np

from graph.errors import InputError

EXTRA = "video"  # pip install 'acinoset[video]'
CRF = 23  # x264 constant quality: 23 is its default, visually clean for overlays on footage
PRESET = "ultrafast"  # x264 speed: the overlays change little of a frame; see bench/RESULTS.md


def ffmpeg_exe() -> str:
    """The ffmpeg binary bundled with the ``imageio-ffmpeg`` wheel (never one from the system)."""
    try:
        import imageio_ffmpeg
    except ModuleNotFoundError:
        raise InputError(f"videos need the '{EXTRA}' extra: pip install 'acinoset[{EXTRA}]'") from None
    return imageio_ffmpeg.get_ffmpeg_exe()


@dataclass(frozen=True)
class VideoInfo:
    """What the container says about a video: size (pixels), rate and number of frames."""

    path: str
    width: int
    height: int
    fps: float
    frames: int
    codec: str = ""

    @property
    def even_size(self) -> tuple[int, int]:
        """(width, height) rounded up to even numbers: the size frames are decoded at."""
        return self.width + self.width % 2, self.height + self.height % 2


def probe(path: str | Path) -> VideoInfo:
    """Size, frame rate, frame count and codec of ``path`` from its container (OpenCV's reader);
    one-line :class:`InputError` when it is missing or holds no video."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise InputError("no such video file", path)
    cap = cv2.VideoCapture(str(path))
    try:
        if not cap.isOpened():
            raise InputError("cannot be read as a video", path)
        w = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        h = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        fps = float(cap.get(cv2.CAP_PROP_FPS))
        n = int(round(cap.get(cv2.CAP_PROP_FRAME_COUNT)))
        fourcc = int(cap.get(cv2.CAP_PROP_FOURCC))
    finally:
        cap.release()
    if w <= 0 or h <= 0 or n <= 0:
        raise InputError("holds no video frames", path)
    if not fps > 0:
        raise InputError("has no frame rate in its container", path)
    codec = "".join(chr((fourcc >> (8 * i)) & 0xFF) for i in range(4)).strip("\x00 ")
    return VideoInfo(path=str(path), width=w, height=h, fps=fps, frames=n, codec=codec)


class YuvFrame:
    """One ``yuv420p`` frame: ``y`` (H, W), ``u`` and ``v`` (H/2, W/2), views of one buffer ``data``
    laid out as ffmpeg and OpenCV's ``COLOR_YUV2BGR_I420`` expect (``data.reshape(H*3//2, W)``)."""

    __slots__ = ("width", "height", "data", "y", "u", "v")

    def __init__(self, width: int, height: int, data: np.ndarray | None = None):
        if width % 2 or height % 2:
            raise ValueError(f"yuv420p frames have even sizes, not {width}x{height}")
        self.width, self.height = width, height
        n = width * height
        self.data = np.empty(n * 3 // 2, dtype=np.uint8) if data is None else data
        self.y = self.data[:n].reshape(height, width)
        self.u = self.data[n:n + n // 4].reshape(height // 2, width // 2)
        self.v = self.data[n + n // 4:].reshape(height // 2, width // 2)

    def copy(self) -> "YuvFrame":
        return YuvFrame(self.width, self.height, self.data.copy())

    def to_bgr(self) -> np.ndarray:
        """The frame as an OpenCV BGR image (BT.601, video range: what ffmpeg assumes untagged)."""
        import cv2

        return cv2.cvtColor(self.data.reshape(self.height * 3 // 2, self.width), cv2.COLOR_YUV2BGR_I420)

    @classmethod
    def from_bgr(cls, image: np.ndarray) -> "YuvFrame":
        """A BGR image (even sizes) as a yuv420p frame (OpenCV's BT.601 video-range conversion)."""
        import cv2

        h, w = image.shape[:2]
        return cls(w, h, cv2.cvtColor(image, cv2.COLOR_BGR2YUV_I420).reshape(-1))


PIPE_BYTES = 1 << 20  # Linux's default limit for an unprivileged pipe: 16x fewer system calls than 64 KiB


def _widen(pipe) -> None:
    """Make a pipe's buffer ``PIPE_BYTES`` where the system allows (Linux ``F_SETPIPE_SZ``)."""
    try:
        import fcntl

        fcntl.fcntl(pipe.fileno(), getattr(fcntl, "F_SETPIPE_SZ", 1031), PIPE_BYTES)
    except (ImportError, OSError):
        pass


class _Ffmpeg:
    """An ffmpeg child process whose messages go to a temporary file (a pipe could fill and block
    it); :meth:`close` waits for it and turns a failure into one line."""

    def __init__(self, args: list[str], what: str, path: str | Path, **popen):
        self.what, self.path = what, path
        self._log = tempfile.TemporaryFile()
        self.proc = subprocess.Popen([ffmpeg_exe(), "-hide_banner", "-nostdin", "-loglevel", "error", *args],
                                     stderr=self._log, **popen)

    def finish(self, kill: bool = False) -> str | None:
        """Wait for the process (after killing it, if asked); its last message if it failed."""
        if kill and self.proc.poll() is None:
            self.proc.kill()
        rc = self.proc.wait()
        if self._log.closed:
            return None
        self._log.seek(0)
        lines = [ln for ln in self._log.read().decode("utf-8", "replace").splitlines() if ln.strip()]
        self._log.close()
        if rc == 0 or kill:
            return None
        return lines[-1].strip() if lines else f"ffmpeg exited with status {rc}"

    @property
    def stdout(self) -> io.FileIO:
        """The child's output: a reader's process has one, unbuffered (``bufsize=0``: a raw file)."""
        assert isinstance(self.proc.stdout, io.FileIO)
        return self.proc.stdout

    @property
    def stdin(self) -> io.FileIO:
        """The child's input: a writer's process has one, unbuffered (``bufsize=0``: a raw file)."""
        assert isinstance(self.proc.stdin, io.FileIO)
        return self.proc.stdin


class FrameReader:
    """Stream the frames ``start .. start+count-1`` of a video as :class:`YuvFrame` s.

    Seeking is ffmpeg's accurate seek to half a frame before ``start`` (it decodes from the key
    frame before and drops what comes earlier), so a constant-rate video starts exactly at ``start``.
    ``read()`` returns the next frame (the same buffer each time) or None at the end.
    """

    def __init__(self, info: VideoInfo, start: int = 0, count: int | None = None, threads: int = 1):
        self.info = info
        self.width, self.height = info.even_size
        self.start = int(start)
        self.count = info.frames - self.start if count is None else int(count)
        args = []
        if self.start > 0:
            args += ["-ss", f"{(self.start - 0.5) / info.fps:.6f}"]
        args += ["-threads", str(threads), "-i", str(info.path), "-map", "0:v:0", "-frames:v", str(self.count)]
        if (self.width, self.height) != (info.width, info.height):
            args += ["-vf", f"pad={self.width}:{self.height}"]
        args += ["-f", "rawvideo", "-pix_fmt", "yuv420p", "-"]
        self._ff = _Ffmpeg(args, "decode", info.path, stdout=subprocess.PIPE, bufsize=0)
        _widen(self._ff.stdout)
        self._frame = YuvFrame(self.width, self.height)
        self._view = self._frame.data.data  # the buffer's memoryview
        self.frames_read = 0

    def read(self) -> YuvFrame | None:
        """The next frame, or None after the last (the buffer is overwritten by the next read)."""
        if self.frames_read >= self.count:
            return None
        got, size, out = 0, len(self._view), self._ff.stdout
        while got < size:
            n = out.readinto(self._view[got:])
            if not n:
                return None
            got += n
        self.frames_read += 1
        return self._frame

    def __iter__(self):
        while (frame := self.read()) is not None:
            yield frame

    def close(self) -> None:
        self._ff.stdout.close()
        self._ff.finish(kill=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class FrameWriter:
    """Encode :class:`YuvFrame` s (or BGR images) to an H.264 MP4 (``yuv420p``) at ``fps``."""

    def __init__(self, path: str | Path, width: int, height: int, fps: float, crf: int = CRF,
                 preset: str = PRESET, threads: int = 1, bitrate: float | None = None):
        """``crf`` sets a constant quality; a ``bitrate`` (bits per second) instead sets the average
        rate, as a camera does."""
        if width % 2 or height % 2:
            raise ValueError(f"H.264 in yuv420p needs even sizes, not {width}x{height}")
        self.path, self.width, self.height = Path(path), width, height
        rate = Fraction(fps).limit_denominator(1001)
        args = ["-y", "-f", "rawvideo", "-pix_fmt", "yuv420p", "-s", f"{width}x{height}", "-r", f"{rate}",
                "-i", "-", "-an", "-c:v", "libx264", "-preset", preset,
                *(["-crf", str(crf)] if bitrate is None else ["-b:v", f"{int(bitrate)}"]),
                "-pix_fmt", "yuv420p", "-threads", str(threads), "-movflags", "+faststart", str(self.path)]
        self._ff = _Ffmpeg(args, "encode", path, stdin=subprocess.PIPE, bufsize=0)
        _widen(self._ff.stdin)
        self.frames_written = 0

    def write(self, frame: YuvFrame | np.ndarray) -> None:
        """Append one frame: a :class:`YuvFrame` of the writer's size, or a BGR image of it."""
        if not isinstance(frame, YuvFrame):
            frame = YuvFrame.from_bgr(frame)
        if (frame.width, frame.height) != (self.width, self.height):
            raise ValueError(f"frame of {frame.width}x{frame.height} for a {self.width}x{self.height} video")
        try:
            self._ff.stdin.write(frame.data.data)
        except BrokenPipeError:
            raise InputError(f"the encoder stopped: {self._ff.finish()}", self.path) from None
        self.frames_written += 1

    def close(self) -> None:
        """Finish the file; a failed encode raises :class:`InputError` naming the output."""
        try:
            self._ff.stdin.close()
        except BrokenPipeError:
            pass
        failure = self._ff.finish()
        if failure:
            raise InputError(f"could not be written: {failure}", self.path)

    def abort(self) -> None:
        """Stop the encoder and remove the partial file."""
        try:
            self._ff.stdin.close()
        except BrokenPipeError:
            pass
        self._ff.finish(kill=True)
        try:
            os.remove(self.path)
        except OSError:
            pass

    def __enter__(self):
        return self

    def __exit__(self, exc_type, *exc):
        if exc_type is None:
            self.close()
        else:
            self.abort()


def read_frame(info: VideoInfo, index: int) -> YuvFrame:
    """One frame of a video (a copy), for a single picture."""
    if not 0 <= index < info.frames:
        raise InputError(f"has frames 0 to {info.frames - 1}, not frame {index}", info.path)
    with FrameReader(info, start=index, count=1) as reader:
        frame = reader.read()
        if frame is None:
            raise InputError(f"frame {index} could not be decoded", info.path)
        return frame.copy()

"""Labelled videos: the estimate drawn over each camera's footage, a 3D view, and a grid of both.

The front door:

* :func:`render_videos` (``acinoset video``): every camera's labelled video, the 3D view and
  optionally the combined grid, streamed in one pass (:class:`RenderedVideos` says what was written);
* :func:`camera_frame_png` (``acinoset plot --frame``): one camera's frame with the estimate on it;
* :func:`probe`, :class:`FrameReader`, :class:`FrameWriter`: video files in and out as H.264 MP4
  (``yuv420p``) through the ffmpeg binary of the ``imageio-ffmpeg`` wheel (the ``video`` extra);
* :func:`write_simulated_videos` (``acinoset simulate --videos``): footage of a simulated run.

Modules: :mod:`~graph.video.codec` (files), :mod:`~graph.video.draw` (drawing on a camera's
frame), :mod:`~graph.video.scene` (the 3D view), :mod:`~graph.video.render` (matching frames and
clocks, the pass over the videos), :mod:`~graph.video.synthetic` (rendering a simulated run).
"""

from graph.video.codec import FrameReader, FrameWriter, VideoInfo, YuvFrame, ffmpeg_exe, probe
from graph.video.render import RenderedVideos, camera_frame_png, render_videos
from graph.video.synthetic import scaled_rig, write_simulated_videos

__all__ = ["FrameReader", "FrameWriter", "RenderedVideos", "VideoInfo", "YuvFrame", "camera_frame_png",
           "ffmpeg_exe", "probe", "render_videos", "scaled_rig", "write_simulated_videos"]

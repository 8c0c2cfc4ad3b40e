/* The job page's videos: the labelled videos (each camera's footage with the estimate drawn on it,
 * the 3D view, the grid of all) played in step with the result view's frame slider, and the frame
 * picker (one camera's frame with the reprojection drawn on it, a PNG from the server).
 *
 *   const sync = AcinoJobVideos.panel(job, payload, () => view);   // a card, before the view exists
 *   AcinoResultView.render(box, payload, { onFrame: sync.onFrame, onPlaying: sync.onPlaying });
 *
 * Clocks: the 3D view's frame n is the reference clock (camera 1's). The 3D and grid videos are on
 * it; camera c's video is on its own clock, where frame m was taken at reference time m + tau_c, so
 * it shows frame n - round(tau_c) (the report's time_offsets_frames), as the grid does. A frame's
 * time in a video is taken at its middle, (m + 0.5) / fps, so a seek never lands on a boundary. */
(function () {
  "use strict";
  const A = window.Acino;
  const { el } = A;

  function panel(job, P, getView) {
    const id = job.id;
    const N = P.frames;
    const fps = P.fps || 1;
    const tau = ((P.report || {}).time_offsets_frames || []).map((t) => (t == null ? 0 : Math.round(t)));
    const section = el("section", { class: "card", "data-testid": "job-videos" });
    const select = el("select", { id: "video-view", "aria-label": "Which video" });
    const video = el("video", { controls: "", muted: "", playsinline: "", preload: "auto", "data-testid": "job-video",
      "aria-label": "Labelled video, following the frame slider", style: "width:100%;max-height:70vh;background:#111" });
    video.muted = true;
    const note = el("p", { class: "muted", text: "The video follows the 3D playback: move the frame slider or press " +
      "play there. Seeking the video moves the slider." });
    const error = el("p", { class: "alert", role: "alert", hidden: "" });
    section.append(el("h2", { text: "Videos" }), note,
      el("p", {}, el("label", { for: "video-view", text: "Video " }), select), video, error);

    let links = {};
    let offset = 0;        // frames this video's clock is behind the reference clock
    let target = null;     // the time the page last asked the video to be at
    let driving = false;   // the video is moving the view (do not seek it back)

    const frameOf = (t) => Math.max(0, Math.min(N - 1, Math.floor(t * fps) + offset));
    const timeOf = (n) => (Math.max(0, Math.min(N - 1, n - offset)) + 0.5) / fps;

    function seek(n) {
      target = timeOf(n);
      video.currentTime = target;
    }

    function choose(view) {
      if (!links[view]) return;
      const state = getView() ? getView().state : null;
      offset = /^[0-9]+$/.test(view) ? (tau[Number(view) - 1] || 0) : 0;
      video.src = links[view];
      video.dataset.view = view;
      seek(state ? state.frame : 0);
    }

    video.addEventListener("seeked", () => {
      if (target !== null && Math.abs(video.currentTime - target) < 0.5 / fps) return;  // our own seek
      const view = getView();
      if (!view || view.state.playing) return;
      driving = true;
      try { view.setFrame(frameOf(video.currentTime)); } finally { driving = false; }
    });
    video.addEventListener("timeupdate", () => {  // the video's own play button
      const view = getView();
      if (!view || video.paused || view.state.playing) return;
      driving = true;
      try { view.setFrame(frameOf(video.currentTime)); target = video.currentTime; } finally { driving = false; }
    });
    video.addEventListener("error", () => {
      error.textContent = "The video could not be played (its link may have expired: reload the page).";
      error.hidden = false;
    });
    select.addEventListener("change", () => choose(select.value));

    const ready = A.api(job.links.videos).then((list) => {
      for (const v of list.videos) {
        links[v.view] = v.href;
        const name = /^[0-9]+$/.test(v.view) ? `Camera ${v.view}${P.cameras[Number(v.view) - 1] ? ` (${P.cameras[Number(v.view) - 1]})` : ""}`
          : v.view === "3d" ? "3D view" : "All views (grid)";
        select.append(el("option", { value: v.view, text: name }));
      }
      const first = list.videos.length ? list.videos[0].view : null;
      if (first) choose(first);
    }).catch((e) => { error.textContent = `The videos could not be listed: ${e.message}`; error.hidden = false; });

    return {
      section,
      ready,
      video,
      onFrame(n, fromPlayback) {
        if (driving || !video.src) return;
        if (!fromPlayback) { if (!video.paused) video.pause(); seek(n); return; }
        if (Math.abs(video.currentTime - timeOf(n)) > 3 / fps) seek(n);  // drifted, or the 3D view looped
        if (video.paused) video.play().catch(() => {});  // (a video that reached its end stops by itself)
      },
      onPlaying(on, speed) {
        if (!video.src) return;
        if (on) { video.playbackRate = speed || 1; video.play().catch(() => {}); } else video.pause();
      },
    };
  }

  /** The frame picker: camera, the camera's frame (the slider's, on its clock, at a click) and the
   * PNG the server draws. */
  function framePicker(job, P, getView) {
    const tau = ((P.report || {}).time_offsets_frames || []).map((t) => (t == null ? 0 : Math.round(t)));
    const section = el("section", { class: "card", "data-testid": "frame-picker" });
    const camera = el("select", { id: "picker-camera" },
      P.cameras.map((name, c) => el("option", { value: String(c + 1), text: `Camera ${c + 1} (${name})` })));
    const frame = el("input", { id: "picker-frame", type: "number", min: 0, max: P.frames - 1, step: 1, value: 0 });
    const useSlider = el("button", { type: "button", text: "Slider's frame" });
    const show = el("button", { type: "button", text: "Draw this frame", "data-testid": "picker-show" });
    const img = el("img", { alt: "", "data-testid": "picker-image", style: "max-width:100%;display:block", hidden: "" });
    const error = el("p", { class: "alert", role: "alert", hidden: "" });
    section.append(el("h2", { text: "One camera's frame" }),
      el("p", { class: "muted", text: "The camera's own frame with the detections and the reprojected skeleton drawn on it." }),
      el("div", { class: "controls" }, el("label", { for: "picker-camera", text: "Camera " }), camera,
        el("label", { for: "picker-frame", text: "Frame to draw " }), frame, useSlider, show), img, error);
    useSlider.addEventListener("click", () => {  // the camera's own frame nearest the slider's time
      const v = getView();
      if (v) frame.value = String(Math.max(0, Math.min(P.frames - 1, v.state.frame - (tau[Number(camera.value) - 1] || 0))));
    });
    show.addEventListener("click", async () => {
      error.hidden = true;
      show.disabled = true;
      try {
        const res = await A.api(`/v1/jobs/${encodeURIComponent(job.id)}/frame?camera=${camera.value}&n=${Number(frame.value) || 0}`,
          { raw: true, headers: { Accept: "image/png" } });
        const url = URL.createObjectURL(await res.blob());
        if (img.src.startsWith("blob:")) URL.revokeObjectURL(img.src);
        img.src = url;
        img.alt = `Camera ${camera.value}, frame ${frame.value}, with the estimate drawn on it`;
        img.hidden = false;
      } catch (e) {
        error.textContent = `The frame could not be drawn: ${e.message}`;
        error.hidden = false;
      } finally { show.disabled = false; }
    });
    return section;
  }

  window.AcinoJobVideos = { panel, framePicker };
})();

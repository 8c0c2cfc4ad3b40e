/* One job: live status and progress, the error in plain words when it failed, downloads of every
 * result format, and the result view (3D playback, reprojection error, over time, flags). */
(function () {
  "use strict";
  const A = window.Acino;
  if (!A.requireToken()) return;
  A.header("job");
  const { el } = A;
  const id = decodeURIComponent(location.pathname.split("/").filter(Boolean)[1] || "");
  const short = id.slice(0, 8);
  const title = document.getElementById("job-title");
  const statusLine = document.getElementById("job-status");
  const alertBox = document.getElementById("job-alert");
  const progressBox = document.getElementById("job-progress");
  const bar = document.getElementById("progress-bar");
  const progressText = document.getElementById("progress-text");
  const facts = document.getElementById("job-facts");
  const actions = document.getElementById("job-actions");
  const downloads = document.getElementById("downloads");
  const downloadButtons = document.getElementById("download-buttons");
  const downloadError = document.getElementById("download-error");
  const resultBox = document.getElementById("result");
  // Each download format's label, what its file holds and its extension, as the server lists them
  // (GET /v1/formats); if the list cannot be had, a button names its format by the format's name.
  let formatInfo = {};
  const formatsLoaded = A.api("/v1/formats").then(
    (list) => { formatInfo = Object.fromEntries(list.map((f) => [f.name, f])); },
    () => {});
  let lastStatus = null;
  let timer = null;
  let resultShown = false;

  title.textContent = `Job ${short}`;

  function fact(k, v) { if (v !== null && v !== undefined && v !== "") facts.append(el("dt", { text: k }), el("dd", {}, v)); }

  function drawFacts(job) {
    facts.replaceChildren();
    const t = job.timings || {};
    const o = job.options || {};
    const i = job.inputs || {};
    fact("Job id", el("code", { text: job.id }));
    fact("Label", job.label);
    fact("Owner", job.owner);
    fact("Method", `${o.method} with the ${o.skeleton} skeleton at ${o.fps} fps, likelihood threshold ${o.likelihood_threshold}`);
    fact("Input", `${i.cameras} cameras, ${i.frames} frames, ${(i.bodyparts || []).length} bodyparts`);
    if (i.keypoints) fact("Keypoint files", el("ul", { class: "plain" },
      i.keypoints.map((f, k) => el("li", { text: `camera ${k + 1}: ${f.name}` + (f.frames != null ? ` (${f.frames} frames)` : "") }))));
    if (i.calibration_id) {
      fact("Calibration", el("span", {}, "made on this server: ",
        el("a", { href: `/calibrations/${encodeURIComponent(i.calibration_id)}`, text: `calibration ${i.calibration_id.slice(0, 8)}` })));
    } else if (i.calibration) fact("Calibration", i.calibration.name);
    fact("Submitted", A.fmtDate(t.created_at));
    fact("Started", t.started_at ? A.fmtDate(t.started_at) : null);
    fact("Finished", t.finished_at ? A.fmtDate(t.finished_at) : null);
    fact("Waited", t.queued_seconds != null ? A.fmtSeconds(t.queued_seconds) : null);
    fact("Ran", t.run_seconds != null ? A.fmtSeconds(t.run_seconds) : null);
    if (job.attempts > 1) fact("Attempts", `${job.attempts} of ${job.max_attempts}`);
    const r = job.result;
    if (r && r.identity) {
      const who = r.identity;
      fact("Individuals", `${(who.individuals || []).join(", ")} (${who.count === "given" ? "as many as asked for" : "found in the files"})`);
      const sw = who.switches_corrected || {};
      fact("2D identity switches corrected", Object.keys(sw).map((c) => `${c} ${sw[c]}`).join(", "));
    }
    if (r) {
      fact(r.identity ? "Reprojection RMSE (first individual)" : "Reprojection RMSE",
        r.reprojection_rmse_px != null ? `${r.reprojection_rmse_px.toFixed(2)} px` : null);
      fact("Rejected detections", r.outliers != null ? `${r.outliers} of ${r.observations}` : null);

    }
  }

  function drawAlert(job) {
    alertBox.replaceChildren();
    if (job.status === "succeeded" && job.has_warnings) {
      const r = job.result || {};
      alertBox.append(el("section", { class: "notice", role: "status", "data-testid": "job-warnings" },
        el("h2", { text: "Succeeded with warnings" }),
        el("p", { text: "The solve finished, but it found something about the input to check before you trust the result:" }),
        el("ul", {}, (r.warnings || []).map((w) => el("li", { text: w })))));
    }
    if (job.status === "failed") {
      const err = (job.error || "").trim();
      // The server says what failed (error_kind): the input, a limit of the server, runs that kept
      // dying, or the software itself. Only the last is put down to the software.
      const kind = job.error_kind || "internal";
      const box = el("section", { class: "alert", role: "alert", "data-testid": "job-error", "data-kind": kind },
        el("h2", { text: "This job failed" }));
      const detail = err ? el("p", { class: "error-text", text: err }) : null;
      if (kind === "input") {
        box.append(detail, el("p", { text: "The solver could not use the input: fix what the message names " +
          "(one of the uploaded files or an option) and submit the job again." }));
      } else if (kind === "limit") {
        box.append(detail, el("p", { text: "The run hit a limit of this server (its time or memory). A shorter " +
          "run, fewer frames or cameras, or a faster method fits; or ask whoever runs this server." }));
      } else if (kind === "interrupted") {
        box.append(detail, el("p", { text: "Every run of this job was interrupted (the solve process died or the " +
          "server restarted). A very large input can cause that; otherwise send the job id " + job.id +
          " to whoever runs this server." }));
      } else {
        box.append(
          el("p", { text: "The solver stopped on an error it did not expect. Send the job id " + job.id +
            " to whoever runs this server, with the detail below; it may also come from something unusual in the files." }),
          err ? el("details", {}, el("summary", { text: "Technical detail" }), detail) : null);
      }
      box.append(el("p", {}, el("a", { class: "button", href: "/jobs/new", text: "Submit a new job" })));
      alertBox.append(box);
    } else if (job.status === "cancelled") {
      alertBox.append(el("p", { class: "notice", text: "This job was cancelled; it has no result." }));
    } else if (job.interruption && A.isActive(job.status)) {
      alertBox.append(el("p", { class: "notice", text: `An earlier run of this job was interrupted (${job.interruption}); it is being run again.` }));
    }
  }

  function drawProgress(job) {
    const active = A.isActive(job.status);
    progressBox.hidden = !active;
    if (!active) return;
    const f = job.progress && job.progress.fraction != null ? job.progress.fraction : null;
    if (f === null) bar.removeAttribute("value");
    else { bar.value = f; bar.setAttribute("aria-valuetext", `${Math.round(100 * f)} percent`); }
    progressText.textContent = job.status === "queued" ? A.queuedText(job) : (A.progressText(job) || "Starting.");
  }

  function drawActions(job) {
    const active = A.isActive(job.status);
    const fitted = job.status === "succeeded" && job.result && job.result.motion_scales;
    actions.replaceChildren(fitted ? el("a", { class: "button", href: `/jobs/new?smoothing=${encodeURIComponent(id)}`,
      text: "Use its smoothing in a new job" }) : "", el("button", { type: "button", class: active ? "" : "danger",
      text: active ? "Cancel this job" : "Delete this job", onclick: async () => {
        if (!confirm(active ? `Cancel job ${short}?` : `Delete job ${short} and its result files?`)) return;
        try {
          await A.api(`/v1/jobs/${encodeURIComponent(id)}`, { method: "DELETE" });
          if (active) refresh(); else location.assign("/");
        } catch (e) {
          alertBox.replaceChildren(el("p", { class: "alert", role: "alert", text: `Could not do that: ${e.message}` }));
        }
      } }));
  }

  function downloadButton(href, f, whose) {
    const { label, description: what, extension } = formatInfo[f] ||
      { label: f.toUpperCase(), description: "", extension: `.${f}` };
    return el("button", { type: "button", "data-format": f, "data-individual": whose || null, onclick: async (ev) => {
      downloadError.hidden = true;
      ev.target.disabled = true;
      try { await A.download(href, `${id}${extension}`); }
      catch (e) { downloadError.textContent = `The ${label} file could not be downloaded: ${e.message}`; downloadError.hidden = false; }
      finally { ev.target.disabled = false; }
    } }, el("strong", { text: `Download ${label}` }), what ? el("span", { class: "muted", text: ` — ${what}` }) : null);
  }

  function drawDownloads(job) {
    const links = (job.links && job.links.result) || {};
    const each = (job.links && job.links.individuals) || {};
    const formats = Object.keys(links);
    downloads.hidden = !formats.length;
    downloadButtons.replaceChildren(...formats.map((f) => downloadButton(links[f], f, null)),
      ...Object.keys(each).map((name) => el("div", { class: "individual-downloads", "data-individual": name },
        el("h3", { text: name }), ...Object.keys(each[name]).map((f) => downloadButton(each[name][f], f, name)))));
  }

  /** The result drawn: the job's, or with several individuals them all (at first) or the one picked. */
  function individualPicker(job, draw) {
    const each = job.links.individuals;
    if (!each) return null;
    const names = Object.keys(each);
    const all = job.links.result && job.links.result.json;
    const select = el("select", { id: "individual-picker", "aria-label": "Individual to draw",
      onchange: () => draw(select.value === "" ? all : each[select.value].json) },
    ...(all ? [el("option", { value: "", text: "every individual" })] : []),
    ...names.map((n) => el("option", { value: n, text: n })));
    return el("p", { class: "picker" }, el("label", { for: "individual-picker", text: "Individual: " }), select);
  }

  async function showResult(job, chosen) {
    resultShown = true;
    if (job.links.individuals && !document.getElementById("individual-picker")) {
      resultBox.before(individualPicker(job, (href) => showResult(job, href)));
    }
    resultBox.replaceChildren(el("p", { class: "muted", role: "status", text: "Loading the result for drawing…" }));
    try {
      const first = job.links.individuals ? Object.values(job.links.individuals)[0].json : null;
      const href = chosen || (job.links.result && job.links.result.json) || first ||
        `/v1/jobs/${encodeURIComponent(id)}/result?format=json`;
      const payload = await A.api(href);
      if (typeof window.Plotly === "undefined" || !window.AcinoResultView) throw new Error("the plotting scripts did not load");
      let view = null;
      const videos = job.links.videos ? window.AcinoJobVideos.panel(job, payload, () => view) : null;
      view = window.AcinoResultView.render(resultBox, payload, videos ? { onFrame: videos.onFrame, onPlaying: videos.onPlaying } : {});
      if (videos && view) {  // under the 3D playback, so both are in sight together
        view.playbackSection.after(videos.section, window.AcinoJobVideos.framePicker(job, payload, () => view));
      }
    } catch (e) {
      resultShown = false;
      resultBox.replaceChildren(el("p", { class: "alert", role: "alert", text: `The result could not be drawn: ${e.message}` }));
    }
  }

  async function refresh() {
    clearTimeout(timer);
    let job;
    try {
      job = await A.api(`/v1/jobs/${encodeURIComponent(id)}`);
    } catch (e) {
      if (e.status === 404) {
        title.textContent = `Job ${short}: not found`;
        statusLine.textContent = "There is no such job, or it belongs to another user.";
        return;
      }
      statusLine.textContent = `Could not load the job: ${e.message}. Trying again…`;
      timer = setTimeout(refresh, 5000);
      return;
    }
    document.title = `Job ${short} · ${job.status} · acinoset`;
    if (job.status !== lastStatus) {
      statusLine.replaceChildren(A.statusBadge(job.status, job), " ",
        job.status === "succeeded" && job.has_warnings ? "Done, with warnings to check." : A.statusSentence(job.status));
      drawAlert(job);
      drawActions(job);
      lastStatus = job.status;
    }
    drawProgress(job);
    drawFacts(job);
    await formatsLoaded;
    drawDownloads(job);
    if (job.status === "succeeded" && !resultShown) showResult(job);
    if (A.isActive(job.status)) timer = setTimeout(refresh, 1000);
  }

  refresh();
})();

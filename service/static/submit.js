/* Submit a job: keypoint files in camera order, the calibration (a file, or one made on this
 * server) and the solve options, sent as POST /v1/jobs (multipart); on 202 go to the job's page. */
(function () {
  "use strict";
  const A = window.Acino;
  if (!A.requireToken()) return;
  A.header("new");
  const { el } = A;
  const form = document.getElementById("submit-form");
  const kpInput = document.getElementById("keypoints");
  const list = document.getElementById("keypoint-list");
  const calib = document.getElementById("calibration");
  const skeleton = document.getElementById("skeleton");
  const skeletonHint = document.getElementById("skeleton-hint");
  const errorBox = document.getElementById("submit-error");
  const status = document.getElementById("submit-status");
  const calibId = document.getElementById("calibration-id");
  const calibIdHint = document.getElementById("calibration-id-hint");
  let skeletons = [];

  function showError(text, focus) {
    errorBox.textContent = text;
    errorBox.hidden = !text;
    if (text && focus) focus.focus();
  }

  const keypoints = A.fileOrder(kpInput, list, (files) => {
    status.textContent = files.length ? `${files.length} keypoint file${files.length === 1 ? "" : "s"} selected.` : "";
  });

  /** ``?smoothing=JOB``: the smoothing that job fitted (its result's motion_scales, with the orders
   * they are for) offered, and chosen, as the new job's smoothing and motion model. */
  let earlier = null;
  async function loadEarlierSmoothing() {
    const from = new URLSearchParams(location.search).get("smoothing");
    if (!from) return;
    try {
      const job = await A.api(`/v1/jobs/${encodeURIComponent(from)}`);
      const r = job.result || {};
      if (!r.motion_scales) throw new Error("that job did not fit its smoothing");
      earlier = { scales: r.motion_scales, orders: r.motion_orders };
      const what = `fitted by job ${from.slice(0, 8)}` + (job.label ? ` (${job.label})` : "");
      const n = Object.keys(r.motion_scales).length;
      document.getElementById("motion-scale").append(el("option", { value: "job", text: `${what}, ${n} group${n > 1 ? "s" : ""}` }));
      document.getElementById("motion-scale").value = "job";
      if (r.motion_orders) {
        document.getElementById("motion-order").append(el("option", { value: "job", text: `the orders ${what}` }));
        document.getElementById("motion-order").value = "job";
      }
      document.querySelector("details").open = true;
    } catch (e) {
      showError(`The smoothing of job ${from.slice(0, 8)} could not be used: ${e.message}`);
    }
  }

  /** The caller's succeeded calibrations as choices: a job may name one instead of uploading a file. */
  async function loadCalibrations() {
    try {
      const data = await A.api("/v1/calibrations?status=succeeded&limit=100");
      const rows = data.calibrations || [];
      calibId.append(...rows.map((c) => {
        const r = c.report || {};
        const bits = [`${c.inputs.cameras} cameras`];
        if (r.rms_px != null) bits.push(`RMS ${Number(r.rms_px).toFixed(2)} px`);
        bits.push(A.fmtDate(c.timings && c.timings.created_at));
        return el("option", { value: c.id, text: `${c.label || c.id.slice(0, 8)} (${bits.join(", ")})` });
      }));
      const wanted = new URLSearchParams(location.search).get("calibration");
      if (wanted && rows.some((c) => c.id === wanted)) calibId.value = wanted;
      calibIdHint.textContent = rows.length ? "" : "None yet: calibrate a rig on the Calibrations page.";
    } catch (e) {
      calibIdHint.textContent = `The calibrations could not be loaded: ${e.message}`;
    }
  }

  async function loadSkeletons() {
    try {
      skeletons = await A.api("/v1/skeletons");
      skeleton.replaceChildren(...skeletons.map((s) => el("option", { value: s.name, text: s.name })));
      skeleton.value = skeletons.some((s) => s.name === "cheetah") ? "cheetah" : (skeletons[0] || {}).name;
      describeSkeleton();
    } catch (e) {
      skeletonHint.textContent = `The list of skeletons could not be loaded: ${e.message}`;
    }
  }

  function describeSkeleton() {
    const s = skeletons.find((x) => x.name === skeleton.value);
    if (!s) { skeletonHint.textContent = ""; return; }
    let text = s.description || "";
    if (s.markers) text += ` Markers: ${s.markers.join(", ")}.`;
    skeletonHint.textContent = text.trim();
  }
  skeleton.addEventListener("change", describeSkeleton);
  const autoBox = document.getElementById("measurement-auto");
  autoBox.addEventListener("change", () => { document.getElementById("measurement-std").disabled = autoBox.checked; });

  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    showError("");
    const files = keypoints.files();
    if (!files.length) return showError("Choose at least one keypoint file (one per camera).", kpInput);
    if (!calib.files.length && !calibId.value) {
      return showError("Choose the calibration file, or a calibration made on this server.", calib);
    }
    if (calib.files.length && calibId.value) {
      return showError("Give one calibration: a file or one made on this server, not both.", calibId);
    }
    const fps = Number(document.getElementById("fps").value);
    if (!(fps > 0)) return showError("The frame rate must be a positive number.", document.getElementById("fps"));
    const thr = Number(document.getElementById("threshold").value);
    if (!(thr >= 0 && thr <= 1)) return showError("The likelihood threshold must be between 0 and 1.", document.getElementById("threshold"));
    const autoNoise = document.getElementById("measurement-auto").checked;
    const stdPx = autoNoise ? "auto" : Number(document.getElementById("measurement-std").value);
    if (!autoNoise && !(stdPx > 0)) return showError("The detection noise must be a positive number of pixels.", document.getElementById("measurement-std"));
    const options = {
      method: form.querySelector("input[name=method]:checked").value,
      fps, skeleton: skeleton.value, likelihood_threshold: thr,
      measurement_std_px: stdPx, robust: document.getElementById("robust").checked,
      body: document.getElementById("body-estimate").checked ? "estimate" : "model",
      sync: document.getElementById("sync-estimate").checked ? "estimate" : "given",
    };
    const smoothing = document.getElementById("motion-scale").value;  // "": the skeleton's default
    if (smoothing === "job") options.motion_scale = earlier.scales;
    else if (smoothing) options.motion_scale = smoothing === "auto" ? "auto" : Number(smoothing);
    const order = document.getElementById("motion-order").value;
    if (order === "job") options.motion_order = earlier.orders;
    else options.motion_order = order === "auto" ? "auto" : Number(order);
    const label = document.getElementById("label").value.trim();
    if (label) options.label = label;
    const data = new FormData();
    for (const f of files) data.append("keypoints", f, f.name);
    if (calibId.value) data.append("calibration_id", calibId.value);
    else data.append("calibration", calib.files[0], calib.files[0].name);
    const spec = document.getElementById("skeleton-file");
    if (spec.files.length) data.append("skeleton", spec.files[0], spec.files[0].name);
    const videos = Array.from(document.getElementById("videos").files)
      .sort((a, b) => a.name.localeCompare(b.name, undefined, { numeric: true }));
    if (videos.length && videos.length !== files.length) {
      return showError(`Choose one video per camera: ${videos.length} videos for ${files.length} keypoint files.`,
        document.getElementById("videos"));
    }
    for (const v of videos) data.append("videos", v, v.name);
    data.append("options", JSON.stringify(options));
    await A.submitForm("/v1/jobs", data, { noun: "job", button: form.querySelector("button[type=submit]"), status,
      errorBox, pageOf: (job) => `/jobs/${encodeURIComponent(job.id)}` });
  });

  loadSkeletons();
  loadCalibrations();
  loadEarlierSmoothing();
})();

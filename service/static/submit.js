/* Submit a job: keypoint files in camera order, the calibration and the solve options, sent as
 * POST /v1/jobs (multipart); on 202 go to the job's page. */
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
  let files = [];
  let skeletons = [];

  function showError(text, focus) {
    errorBox.textContent = text;
    errorBox.hidden = !text;
    if (text && focus) focus.focus();
  }

  function drawList() {
    list.replaceChildren(...files.map((f, i) => {
      const up = el("button", { type: "button", text: "Up", "aria-label": `Move ${f.name} up`, disabled: i === 0,
        onclick: () => { [files[i - 1], files[i]] = [files[i], files[i - 1]]; drawList(); focusRow(i - 1, "Up"); } });
      const down = el("button", { type: "button", text: "Down", "aria-label": `Move ${f.name} down`,
        disabled: i === files.length - 1,
        onclick: () => { [files[i + 1], files[i]] = [files[i], files[i + 1]]; drawList(); focusRow(i + 1, "Down"); } });
      const rm = el("button", { type: "button", text: "Remove", class: "danger", "aria-label": `Remove ${f.name}`,
        onclick: () => { files.splice(i, 1); drawList(); kpInput.focus(); } });
      return el("li", {}, el("span", { class: "cam", text: `camera ${i + 1}` }),
        el("span", { class: "name", text: `${f.name} (${(f.size / 1024).toFixed(0)} KiB)` }), up, down, rm);
    }));
    status.textContent = files.length ? `${files.length} keypoint file${files.length === 1 ? "" : "s"} selected.` : "";
  }

  function focusRow(i, label) {
    const b = list.children[i] && [...list.children[i].querySelectorAll("button")].find((x) => x.textContent === label);
    if (b && !b.disabled) b.focus();
  }

  kpInput.addEventListener("change", () => {
    const known = new Set(files.map((f) => `${f.name}/${f.size}`));
    const added = [...kpInput.files].filter((f) => !known.has(`${f.name}/${f.size}`));
    added.sort((a, b) => a.name.localeCompare(b.name, undefined, { numeric: true }));
    files = files.concat(added);
    kpInput.value = "";
    drawList();
  });

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
    if (!files.length) return showError("Choose at least one keypoint file (one per camera).", kpInput);
    if (!calib.files.length) return showError("Choose the calibration file.", calib);
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
    const label = document.getElementById("label").value.trim();
    if (label) options.label = label;
    const data = new FormData();
    for (const f of files) data.append("keypoints", f, f.name);
    data.append("calibration", calib.files[0], calib.files[0].name);
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
    const button = form.querySelector("button[type=submit]");
    button.disabled = true;
    status.textContent = "Uploading and checking the files…";
    try {
      const job = await A.api("/v1/jobs", { method: "POST", body: data });
      status.textContent = "Submitted.";
      location.assign(`/jobs/${encodeURIComponent(job.id)}`);
    } catch (e) {
      status.textContent = "";
      showError(`The job was not submitted: ${e.message}`);
      errorBox.focus && errorBox.setAttribute("tabindex", "-1");
      errorBox.focus();
    } finally {
      button.disabled = false;
    }
  });

  loadSkeletons();
})();

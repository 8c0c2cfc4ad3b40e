/* One calibration: live status, the quality report per camera, downloads of its files, and its
 * figures. The figures are fetched with the token and shown from blob: URLs (the API needs the
 * token; an <img src> to it could not send one). */
(function () {
  "use strict";
  const A = window.Acino;
  if (!A.requireToken()) return;
  A.header("calibrations");
  const { el } = A;
  const id = decodeURIComponent(location.pathname.split("/").filter(Boolean)[1] || "");
  const short = id.slice(0, 8);
  const $ = (x) => document.getElementById(x);
  const FILES = {
    "calibration.toml": "Anipose calibration (TOML): what a solve job takes",
    "scene.json": "AcinoSet scene (JSON)",
    "report.json": "the quality report (JSON)",
  };
  const FIGURES = {
    "rig.png": "The cameras (centre and viewing direction) and the board of every view used, in the world frame",
    "residuals.png": "Reprojection error of every corner, per camera",
    "coverage.png": "Every corner used, in each camera's image, coloured by its reprojection error",
  };
  const REFINE_RIG = "The cameras before (grey) and after the refinement (blue when kept, orange when the old rig was kept)";
  let timer = null;
  let figuresShown = false;
  $("cal-title").textContent = `Calibration ${short}`;

  function fact(k, v) {
    if (v !== null && v !== undefined && v !== "") $("cal-facts").append(el("dt", { text: k }), el("dd", {}, v));
  }
  const num = (x, digits) => (x === null || x === undefined ? "–" : Number(x).toFixed(digits));
  const worst = (xs) => (Array.isArray(xs) && xs.length ? Math.max(...xs) : null);

  function drawRefineFacts(cal) {
    const o = cal.options || {}, i = cal.inputs || {}, r = cal.report;
    fact("Refined from job", el("a", { href: `/jobs/${encodeURIComponent(i.refined_from || "")}`, text: String(i.refined_from || "").slice(0, 8) }));
    fact("Keypoints", el("ul", { class: "plain" }, (i.keypoints || []).map((d, k) => el("li", { text: `camera ${k + 1}: ${d.name}` }))));
    fact("Keypoints used", `likelihood at least ${o.likelihood}`);
    fact("Pose prior", o.pose_sd ? `sd ${o.pose_sd}°: a camera the keypoints would move beyond 3 sd is held where it was` : "none");
    fact("Intrinsics refined", (o.refine_intrinsics || []).length ? `${o.refine_intrinsics.join(", ")} (prior sd: focal ${o.focal_sd}, k1 ${o.k1_sd})` : "none (held)");
    if (r) {
      const loo = r.leave_one_out_px || {};
      fact("Verdict", r.accepted ? "refined: the new rig predicts each camera from the others better" : "kept the old rig");
      fact("Leave one camera out", `${num(loo.old_mean, 2)} px before, ${num(loo.new_mean, 2)} px after, on ${loo.held_out_frames || "the"} ${loo.frames} frames`);
    }
  }

  function drawFacts(cal) {
    $("cal-facts").replaceChildren();
    const o = cal.options || {}, i = cal.inputs || {}, t = cal.timings || {}, r = cal.report;
    fact("Calibration id", el("code", { text: cal.id }));
    fact("Label", cal.label);
    if (o.refine) {
      drawRefineFacts(cal);
      fact("Submitted", A.fmtDate(t.created_at));
      fact("Ran", t.run_seconds != null ? A.fmtSeconds(t.run_seconds) : null);
      return;
    }
    fact("Board", o.board);
    fact("Camera model", o.model);
    fact("Lens fitted", o.lens || "full");
    fact("World frame", o.origin === "camera1" ? "camera 1 at the origin" : `the board of view ${String(o.origin).slice(6)}`);
    const sources = (i.videos || []).length ? i.videos : (i.detections || []);
    fact((i.videos || []).length ? "Videos" : "Detections", el("ul", { class: "plain" }, sources.map((d, k) =>
      el("li", { text: `camera ${k + 1}: ${d.name}` + (d.views != null ? ` (${d.views} views)` : d.frames != null ? ` (${d.frames} frames)` : "") }))));
    if ((i.intrinsics || []).length) fact("Intrinsics", (i.intrinsics || []).map((d) => d.name).join(", "));
    fact("Submitted", A.fmtDate(t.created_at));
    fact("Ran", t.run_seconds != null ? A.fmtSeconds(t.run_seconds) : null);
    if (r) {
      fact("Reprojection RMS", `${num(r.rms_px, 3)} px over ${r.frames_used} shared views`);
      fact("Baselines", Object.entries(r.baselines_m || {}).map(([k, v]) => `${k}: ${num(v, 4)} m`).join("; "));
    }
  }

  function drawRefineQuality(r) {
    const cols = ["camera", "before: leave one out (px)", "after (px)", "moved (mm)", "turned (deg)", "focal change (%)", "posed again", "held"];
    $("cal-head").replaceChildren(el("tr", {}, cols.map((c) => el("th", { scope: "col", text: c }))));
    $("cal-cameras").replaceChildren(...(r.cameras || []).map((c) => el("tr", {},
      el("th", { scope: "row", text: c.name }), el("td", { text: num(c.leave_one_out_old_px, 2) }),
      el("td", { text: num(c.leave_one_out_new_px, 2) }), el("td", { text: num(c.position_change_mm, 1) }),
      el("td", { text: num(c.rotation_change_deg, 3) }), el("td", { text: num(c.focal_change_percent, 2) }),
      el("td", { text: c.re_posed ? "yes" : "no" }), el("td", { text: c.held ? "yes" : "no" }))));
  }

  function drawQuality(cal) {
    const r = cal.report;
    $("cal-quality").hidden = !r;
    if (!r) return;
    if ((cal.options || {}).refine) return drawRefineQuality(r);
    $("cal-cameras").replaceChildren(...(r.cameras || []).map((c) => el("tr", {},
      el("th", { scope: "row", text: c.name }), el("td", { text: num(c.rms_px, 3) }),
      el("td", { text: String(c.views_used) }),
      el("td", { text: String(Object.keys(c.views_dropped || {}).length || (c.views_dropped || []).length || 0) }),
      el("td", { text: num(worst(c.position_std_mm), 2) }), el("td", { text: num(worst(c.rotation_std_deg), 3) }))));
  }

  function drawAlert(cal) {
    const box = $("cal-alert");
    box.replaceChildren();
    if (cal.status === "failed") {
      box.append(el("section", { class: "alert", role: "alert", "data-testid": "cal-error" },
        el("h2", { text: "This calibration failed" }), el("p", { class: "error-text", text: cal.error || "" })));
    } else if (cal.status === "succeeded" && cal.report && (cal.report.warnings || cal.report.notes || []).length) {
      const said = cal.report.warnings || cal.report.notes;
      box.append(el("section", { class: "notice", role: "status" }, el("h2", { text: cal.report.warnings ? "Warnings" : "Notes" }),
        el("ul", {}, said.map((w) => el("li", { text: w })))));
    }
  }

  function drawDownloads(cal) {
    const names = Object.keys(FILES).filter((n) => cal.links && cal.links[n]);
    $("downloads").hidden = !names.length;
    $("use-in-job").href = `/jobs/new?calibration=${encodeURIComponent(cal.id)}`;
    $("download-buttons").replaceChildren(...names.map((n) => el("button", { type: "button", onclick: async (ev) => {
      $("download-error").hidden = true;
      ev.target.disabled = true;
      try { await A.download(cal.links[n], `${id}.${n}`); }
      catch (e) { $("download-error").textContent = `${n} could not be downloaded: ${e.message}`; $("download-error").hidden = false; }
      finally { ev.target.disabled = false; }
    } }, el("strong", { text: `Download ${n}` }), el("span", { class: "muted", text: ` — ${FILES[n]}` }))));
  }

  async function showFigures(cal) {
    figuresShown = true;
    const names = Object.keys(FIGURES).filter((n) => cal.links && cal.links[n]);
    $("figures").hidden = !names.length;
    const list = $("figure-list");
    list.replaceChildren();
    for (const n of names) {
      const caption = (cal.options || {}).refine && n === "rig.png" ? REFINE_RIG : FIGURES[n];
      const fig = el("figure", { "data-figure": n }, el("figcaption", { text: caption }));
      list.append(fig);
      try {
        const res = await A.api(cal.links[n], { raw: true, headers: { Accept: "image/png" } });
        const img = el("img", { alt: caption, src: URL.createObjectURL(await res.blob()) });
        img.style.maxWidth = "100%";
        fig.prepend(img);
      } catch (e) {
        fig.append(el("p", { class: "alert", role: "alert", text: `${n} could not be loaded: ${e.message}` }));
      }
    }
  }

  async function refresh() {
    clearTimeout(timer);
    let cal;
    try {
      cal = await A.api(`/v1/calibrations/${encodeURIComponent(id)}`);
    } catch (e) {
      if (e.status === 404) {
        $("cal-title").textContent = `Calibration ${short}: not found`;
        $("cal-status").textContent = "There is no such calibration, or it belongs to another user.";
        return;
      }
      $("cal-status").textContent = `Could not load the calibration: ${e.message}. Trying again…`;
      timer = setTimeout(refresh, 5000);
      return;
    }
    document.title = `Calibration ${short} · ${cal.status} · acinoset`;
    $("cal-status").replaceChildren(A.statusBadge(cal.status, null), " ", A.statusSentence(cal.status));
    const active = A.isActive(cal.status);
    $("cal-progress").hidden = !active;
    if (active) {
      $("progress-text").textContent = cal.status === "queued" ? A.queuedText(cal) : (A.progressText(cal) || "Starting.");
      const f = cal.progress && cal.progress.fraction != null ? cal.progress.fraction : null;
      if (f === null) $("progress-bar").removeAttribute("value"); else $("progress-bar").value = f;
    }
    drawAlert(cal);
    drawFacts(cal);
    drawQuality(cal);
    drawDownloads(cal);
    if (cal.status === "succeeded" && !figuresShown) await showFigures(cal);
    if (active) timer = setTimeout(refresh, 1000);
    else document.body.dataset.ready = "true";
  }

  refresh();
})();

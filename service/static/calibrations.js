/* The calibration list: the caller's calibrations, newest first, refreshed while any is queued or
 * running; each links to its page, and a succeeded one to a new job that uses it. */
(function () {
  "use strict";
  const A = window.Acino;
  if (!A.requireToken()) return;
  A.header("calibrations");
  const { el } = A;
  const body = document.getElementById("calibrations-body");
  const more = document.getElementById("more");
  const counts = document.getElementById("counts");
  const updated = document.getElementById("updated");
  const errorBox = document.getElementById("list-error");
  let limit = 50;
  let timer = null;

  function showError(text) {
    errorBox.textContent = text;
    errorBox.hidden = !text;
  }

  function resultCell(cal) {
    if (cal.status === "queued") return el("td", { class: "small", text: A.queuedText(cal) });
    if (cal.status === "running") {
      const f = cal.progress && cal.progress.fraction != null ? cal.progress.fraction : null;
      const bar = el("progress", { max: "1", "aria-label": `Progress of calibration ${cal.id.slice(0, 8)}` });
      if (f !== null) bar.value = f;
      return el("td", { class: "progress-cell" }, bar, el("div", { class: "small", text: A.progressText(cal) }));
    }
    if (cal.status === "failed") return el("td", { class: "small", text: (cal.error || "").slice(0, 120) });
    const r = cal.report;
    if (cal.status !== "succeeded" || !r) return el("td");
    const bits = [`RMS ${Number(r.rms_px).toFixed(2)} px`];
    if ((r.warnings || []).length) bits.push(`${r.warnings.length} warning${r.warnings.length > 1 ? "s" : ""}`);
    return el("td", { class: "small" }, bits.join(" · "), " · ",
      el("a", { href: `/jobs/new?calibration=${encodeURIComponent(cal.id)}`, text: "use in a new job",
        "aria-label": `Use calibration ${cal.id.slice(0, 8)} in a new job` }));
  }

  async function act(cal) {
    const failed = await A.cancelOrDelete("calibration", cal, `/v1/calibrations/${encodeURIComponent(cal.id)}`,
      "Its files are removed.");
    if (failed) showError(failed);
    refresh();
  }

  function row(cal) {
    const short = cal.id.slice(0, 8);
    const active = A.isActive(cal.status);
    const inputs = cal.inputs || {};
    const source = (inputs.videos || []).length ? "videos" : "detections";
    return el("tr", { "data-calibration": cal.id, "data-status": cal.status },
      el("td", {}, el("a", { href: cal.links.page, "aria-label": `Calibration ${short}, open`, text: short })),
      el("td", { text: cal.label || "" }),
      el("td", {}, el("time", { datetime: cal.timings && cal.timings.created_at, text: A.fmtDate(cal.timings && cal.timings.created_at) })),
      el("td", { text: `${(cal.options || {}).board || "?"} · ${(cal.options || {}).model || "?"}` }),
      el("td", { text: `${inputs.cameras ?? "?"} (${source})` }),
      el("td", {}, A.statusBadge(cal.status, null)),
      resultCell(cal),
      el("td", {}, el("button", { type: "button", class: active ? "" : "danger",
        "aria-label": `${active ? "Cancel" : "Delete"} calibration ${short}`, text: active ? "Cancel" : "Delete",
        onclick: () => act(cal) })));
  }

  async function refresh() {
    clearTimeout(timer);
    let next = 10000;
    try {
      const data = await A.api(`/v1/calibrations?limit=${limit}`);
      const rows = data.calibrations || [];
      if (!rows.length) {
        body.replaceChildren(el("tr", {}, el("td", { colspan: "8" }, "No calibrations yet. ",
          el("a", { href: "/calibrations/new", text: "Calibrate a rig" }), ".")));
      } else body.replaceChildren(...rows.map(row));
      const active = rows.filter((c) => A.isActive(c.status)).length;
      counts.textContent = `${rows.length} of ${data.total} shown` + (active ? `, ${active} in progress` : "");
      more.hidden = !(data.total > rows.length && limit < 500);
      updated.textContent = `Updated ${new Date().toLocaleTimeString()}`;
      showError("");
      next = active ? 2000 : 10000;
    } catch (e) {
      showError(`Could not load the calibrations: ${e.message}`);
    }
    if (document.visibilityState === "visible") timer = setTimeout(refresh, next);
  }

  more.addEventListener("click", () => { limit = Math.min(500, limit + 50); refresh(); });
  document.addEventListener("visibilitychange", () => { if (document.visibilityState === "visible") refresh(); });
  refresh();
})();

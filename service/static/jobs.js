/* The job list: the caller's jobs, newest first, refreshed while any is queued or running. */
(function () {
  "use strict";
  const A = window.Acino;
  if (!A.requireToken()) return;
  A.header("jobs");
  const { el } = A;
  const body = document.getElementById("jobs-body");
  const filter = document.getElementById("status-filter");
  const more = document.getElementById("more");
  const counts = document.getElementById("counts");
  const updated = document.getElementById("updated");
  const errorBox = document.getElementById("list-error");
  const params = new URLSearchParams(location.search);
  // The filter: all jobs, the active ones together, then each other status the server knows.
  const { active, all } = A.STATUSES;
  if (active.length) {
    filter.append(el("option", { value: "active",
      text: new Intl.ListFormat("en", { type: "conjunction" }).format(active.map(A.statusWord)) }));
  }
  filter.append(...all.filter((s) => !active.includes(s)).map((s) => el("option", { value: s, text: A.statusWord(s) })));
  filter.value = params.get("status") || "";
  // The other filters, each kept in the page's address as the API's own parameter.
  const others = { warnings: document.getElementById("warnings-filter"), method: document.getElementById("method-filter"),
    label: document.getElementById("label-filter") };
  for (const [name, input] of Object.entries(others)) input.value = params.get(name) || "";
  let limit = 50;
  let timer = null;

  function query() {
    const q = new URLSearchParams({ limit: String(limit) });
    if (filter.value === "active") for (const s of A.STATUSES.active) q.append("status", s);
    else if (filter.value) q.append("status", filter.value);
    for (const [name, input] of Object.entries(others)) if (input.value.trim()) q.set(name, input.value.trim());
    return q.toString();
  }

  function inputText(job) {
    const i = job.inputs || {};
    const files = (i.keypoints || []).map((f) => f.name);
    const first = files.length ? files[0] + (files.length > 1 ? ` +${files.length - 1}` : "") : "";
    return `${i.cameras ?? "?"} cameras × ${i.frames ?? "?"} frames` + (first ? ` (${first})` : "");
  }

  function progressCell(job) {
    if (job.status === "queued") return el("td", { class: "progress-cell" }, el("span", { class: "small", text: A.queuedText(job) }));
    if (job.status !== "running") {
      if (job.status === "failed") return el("td", { class: "progress-cell small", text: (job.error || "").slice(0, 120) });
      const r = job.result;
      if (job.status === "succeeded" && r) {
        const bits = [];
        if (r.reprojection_rmse_px != null) bits.push(`RMSE ${r.reprojection_rmse_px.toFixed(1)} px`);
        if (r.outliers != null) bits.push(`${r.outliers} of ${r.observations} rejected`);
        if (r.warnings && r.warnings.length) bits.push(`${r.warnings.length} warning${r.warnings.length > 1 ? "s" : ""}`);
        return el("td", { class: "progress-cell small", text: bits.join(" · ") });
      }
      return el("td", { class: "progress-cell" });
    }
    const f = job.progress && job.progress.fraction != null ? job.progress.fraction : null;
    const bar = el("progress", { max: "1", "aria-label": `Progress of job ${job.id.slice(0, 8)}` });
    if (f !== null) { bar.value = f; bar.setAttribute("aria-valuetext", `${Math.round(100 * f)} percent`); }
    return el("td", { class: "progress-cell" }, bar, el("div", { class: "small", text: A.progressText(job) }));
  }

  async function act(job) {
    const failed = await A.cancelOrDelete("job", job, `/v1/jobs/${encodeURIComponent(job.id)}`,
      "Its result files are removed.");
    if (failed) showError(failed);
    refresh();
  }

  function row(job) {
    const opts = job.options || {};
    const short = job.id.slice(0, 8);
    const active = A.isActive(job.status);
    return el("tr", { "data-job": job.id, "data-status": job.status },
      el("td", {}, el("a", { href: `/jobs/${encodeURIComponent(job.id)}`, "aria-label": `Job ${short}, open`, text: short })),
      el("td", { text: job.label || "" }),
      el("td", {}, el("time", { datetime: job.timings && job.timings.created_at, text: A.fmtDate(job.timings && job.timings.created_at) })),
      el("td", { text: `${opts.method || "?"} · ${opts.skeleton || "?"} · ${opts.fps ?? "?"} fps` }),
      el("td", { text: inputText(job) }),
      el("td", {}, A.statusBadge(job.status, job)),
      progressCell(job),
      el("td", { text: A.fmtSeconds(job.timings && job.timings.run_seconds) }),
      el("td", {}, el("button", { type: "button", class: active ? "" : "danger",
        "aria-label": `${active ? "Cancel" : "Delete"} job ${short}`, text: active ? "Cancel" : "Delete",
        onclick: () => act(job) })));
  }

  function showError(text) {
    errorBox.textContent = text;
    errorBox.hidden = !text;
  }

  async function refresh() {
    clearTimeout(timer);
    let next = 10000;
    try {
      const data = await A.api(`/v1/jobs?${query()}`);
      const jobs = data.jobs || [];
      // Keep keyboard focus on the same control across the redraw.
      const focused = document.activeElement && document.activeElement.closest("tr[data-job]");
      const focusJob = focused ? focused.dataset.job : null;
      const focusLabel = focusJob ? document.activeElement.getAttribute("aria-label") : null;
      if (!jobs.length) {
        body.replaceChildren(el("tr", {}, el("td", { colspan: "9" },
          filter.value || Object.values(others).some((i) => i.value.trim()) ? "No jobs match this filter. " : "No jobs yet. ",
          el("a", { href: "/jobs/new", text: "Submit one" }), ".")));
      } else body.replaceChildren(...jobs.map(row));
      if (focusJob && focusLabel) {
        const again = body.querySelector(`tr[data-job="${CSS.escape(focusJob)}"] [aria-label="${CSS.escape(focusLabel)}"]`);
        if (again) again.focus();
      }
      const active = jobs.filter((j) => A.isActive(j.status)).length;
      counts.textContent = `${jobs.length} of ${data.total} shown` + (active ? `, ${active} in progress` : "");
      more.hidden = !(data.total > jobs.length && limit < 500);
      updated.textContent = `Updated ${new Date().toLocaleTimeString()}`;
      showError("");
      next = active ? 2000 : 10000;
    } catch (e) {
      showError(`Could not load the jobs: ${e.message}`);
    }
    if (document.visibilityState === "visible") timer = setTimeout(refresh, next);
  }

  function filtered() {
    const q = new URLSearchParams(location.search);
    if (filter.value) q.set("status", filter.value); else q.delete("status");
    for (const [name, input] of Object.entries(others)) {
      if (input.value.trim()) q.set(name, input.value.trim()); else q.delete(name);
    }
    history.replaceState(null, "", `${location.pathname}${q.toString() ? "?" + q : ""}`);
    refresh();
  }
  filter.addEventListener("change", filtered);
  others.warnings.addEventListener("change", filtered);
  others.method.addEventListener("change", filtered);
  let typing = null;
  others.label.addEventListener("input", () => { clearTimeout(typing); typing = setTimeout(filtered, 300); });
  more.addEventListener("click", () => { limit = Math.min(500, limit + 50); refresh(); });
  document.addEventListener("visibilitychange", () => { if (document.visibilityState === "visible") refresh(); });
  refresh();
})();

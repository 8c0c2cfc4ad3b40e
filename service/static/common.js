/* Shared by every page: the API token (kept in this browser's localStorage), calls to the REST API
 * v1 with it, the page header, the job statuses, the camera-ordered file list of the forms, and
 * small formatting helpers. Needs dom.js. */
(function () {
  "use strict";

  const TOKEN_KEY = "acinoset.token";

  class ApiError extends Error {
    constructor(status, detail) {
      super(detail);
      this.status = status;
    }
  }

  const { el } = window.AcinoDom;

  function token() {
    try { return localStorage.getItem(TOKEN_KEY); } catch (e) { return null; }
  }

  function here() { return location.pathname + location.search; }

  function toLogin(reason) {
    const q = new URLSearchParams({ next: here() });
    if (reason) q.set("reason", reason);
    location.replace("/login?" + q.toString());
  }

  /** Send the user to the sign-in page when this browser holds no token. */
  function requireToken() {
    if (!token()) { toLogin(); return false; }
    return true;
  }

  function detailText(body, fallback) {
    if (!body) return fallback;
    const d = body.detail;
    if (typeof d === "string") return d;
    if (Array.isArray(d)) return d.map((e) => (e && e.msg ? e.msg : JSON.stringify(e))).join("; ");
    return fallback;
  }

  /** Call the REST API with the token. Resolves to parsed JSON (or the Response when raw);
   * rejects with an ApiError whose message is the server's one-line detail. A 401 clears the token
   * and goes to the sign-in page. */
  async function api(path, opts) {
    opts = opts || {};
    const headers = Object.assign({ Accept: "application/json" }, opts.headers || {});
    const t = opts.token !== undefined ? opts.token : token();
    if (t) headers.Authorization = "Bearer " + t;
    let res;
    try {
      res = await fetch(path, { method: opts.method || "GET", headers, body: opts.body, cache: "no-store" });
    } catch (e) {
      throw new ApiError(0, "The server cannot be reached. Check that it is running and try again.");
    }
    if (res.status === 401 && !opts.noRedirect) {
      try { localStorage.removeItem(TOKEN_KEY); } catch (e) { /* ignore */ }
      toLogin("expired");
      throw new ApiError(401, "Your token was not accepted; sign in again.");
    }
    if (!res.ok) {
      let body = null;
      try { body = await res.json(); } catch (e) { /* not JSON */ }
      throw new ApiError(res.status, detailText(body, `${res.status} ${res.statusText}`));
    }
    if (opts.raw) return res;
    if (res.status === 204) return null;
    return res.json();
  }

  /** Fetch a file with the token and hand it to the browser as a download, under the name the
   * server gives it (its Content-Disposition), else ``filename``. */
  async function download(path, filename) {
    const res = await api(path, { raw: true, headers: { Accept: "*/*" } });
    const named = /filename="([^"]+)"/.exec(res.headers.get("content-disposition") || "");
    if (named) filename = named[1];
    const blob = await res.blob();
    const url = URL.createObjectURL(blob);
    const a = el("a", { href: url, download: filename });
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(url), 60000);
  }

  /** The job statuses the server knows, from the page (the server writes them in as JSON):
   * {all: [...], active: [...]}. Empty lists when the page has none. */
  function readStatuses() {
    const node = document.getElementById("job-statuses");
    let s = null;
    try { s = node ? JSON.parse(node.textContent) : null; } catch (e) { /* left empty */ }
    return { all: (s && Array.isArray(s.all)) ? s.all : [], active: (s && Array.isArray(s.active)) ? s.active : [] };
  }
  const STATUSES = readStatuses();

  /** Whether a job in this status may still change (queued or running, as the server says). */
  function isActive(status) { return STATUSES.active.includes(status); }

  // How each status looks: an icon beside the word (never colour alone), and a sentence for the
  // job page. A status not listed here still shows, as "?" and its name.
  const LOOK = {
    queued: ["◷", "Waiting in the queue."],
    running: ["⟳", "Solving."],
    succeeded: ["✓", "Done."],
    failed: ["✕", "Stopped with an error."],
    cancelled: ["⊘", "Cancelled."],
  };
  const statusWord = (status) => String(status).replace(/_/g, " ");

  /** A status as icon and word (never colour alone); a job that succeeded with warnings in its
   * report says so ("succeeded with warnings", its own icon and data-warnings). */
  function statusBadge(status, job) {
    const warned = status === "succeeded" && job && job.has_warnings;
    const [icon] = warned ? ["⚠"] : LOOK[status] || ["?"];
    return el("span", { class: `status status-${status}${warned ? " status-warnings" : ""}`, "data-status": status,
      "data-warnings": warned ? "true" : null },
      el("span", { "aria-hidden": "true", text: icon }), statusWord(status) + (warned ? " with warnings" : ""));
  }

  /** A status in a sentence, for the job page ("" for a status without one). */
  function statusSentence(status) { return (LOOK[status] || [null, ""])[1]; }

  /** A moment as its date and time of day in this browser's zone, "2026-12-02 14:05:09" (a night's
   * runs span two dates: the date is always shown). */
  function fmtDate(iso) {
    if (!iso) return "–";
    const d = new Date(iso);
    if (isNaN(d)) return String(iso);
    const two = (n) => String(n).padStart(2, "0");
    return `${d.getFullYear()}-${two(d.getMonth() + 1)}-${two(d.getDate())} ` +
      `${two(d.getHours())}:${two(d.getMinutes())}:${two(d.getSeconds())}`;
  }

  function fmtSeconds(s) {
    if (s === null || s === undefined || !isFinite(s)) return "–";
    if (s < 1) return `${Math.round(s * 1000)} ms`;
    if (s < 60) return `${s.toFixed(1)} s`;
    const m = Math.floor(s / 60), r = Math.round(s % 60);
    if (m < 60) return `${m} min ${r} s`;
    return `${Math.floor(m / 60)} h ${m % 60} min`;
  }

  /** Why a queued job waits. */
  function queuedText(job) {
    return job.progress && job.progress.stage === "compiling"
      ? "Waiting: the server is compiling its solver (once after an install or upgrade, about half a minute)."
      : "Waiting for a free worker.";
  }

  function progressText(job) {
    const p = job.progress || {};
    const bits = [];
    if (p.stage) bits.push(p.stage);
    if (p.detail) bits.push(p.detail);
    else if (p.iteration) bits.push(`iteration ${p.iteration}`);
    if (p.fraction !== null && p.fraction !== undefined) bits.push(`${Math.round(100 * p.fraction)}%`);
    return bits.join(", ");
  }

  /** Files chosen in a multiple file ``input`` (in several goes if need be) as an ordered list in
   * ``list`` (an <ol>): row i is camera i + 1, with Up, Down and Remove buttons. A new batch is
   * sorted by name (numbers in names as numbers) and added at the end. ``changed(files)`` is called
   * after every change. Returns ``{ files() }``, the files in their order. */
  function fileOrder(input, list, changed) {
    let files = [];
    function focusRow(i, label) {
      const b = list.children[i] && [...list.children[i].querySelectorAll("button")].find((x) => x.textContent === label);
      if (b && !b.disabled) b.focus();
    }
    function draw() {
      list.replaceChildren(...files.map((f, i) => {
        const up = el("button", { type: "button", text: "Up", "aria-label": `Move ${f.name} up`, disabled: i === 0,
          onclick: () => { [files[i - 1], files[i]] = [files[i], files[i - 1]]; draw(); focusRow(i - 1, "Up"); } });
        const down = el("button", { type: "button", text: "Down", "aria-label": `Move ${f.name} down`,
          disabled: i === files.length - 1,
          onclick: () => { [files[i + 1], files[i]] = [files[i], files[i + 1]]; draw(); focusRow(i + 1, "Down"); } });
        const rm = el("button", { type: "button", text: "Remove", class: "danger", "aria-label": `Remove ${f.name}`,
          onclick: () => { files.splice(i, 1); draw(); input.focus(); } });
        return el("li", {}, el("span", { class: "cam", text: `camera ${i + 1}` }),
          el("span", { class: "name", text: `${f.name} (${(f.size / 1024).toFixed(0)} KiB)` }), up, down, rm);
      }));
      if (changed) changed(files);
    }
    input.addEventListener("change", () => {
      const known = new Set(files.map((f) => `${f.name}/${f.size}`));
      const added = [...input.files].filter((f) => !known.has(`${f.name}/${f.size}`));
      added.sort((a, b) => a.name.localeCompare(b.name, undefined, { numeric: true }));
      files = files.concat(added);
      input.value = "";
      draw();
    });
    return { files: () => files.slice() };
  }

  /** The Cancel/Delete button of a list row: asks first, then DELETEs ``path`` (a queued or running
   * item is cancelled, a finished one deleted with ``gone``, its files). Resolves to "" when done or
   * not confirmed, else the sentence to show. */
  async function cancelOrDelete(noun, item, path, gone) {
    const active = isActive(item.status);
    const what = active ? "Cancel" : "Delete";
    if (!confirm(`${what} ${noun} ${item.id.slice(0, 8)}?` + (active ? "" : ` ${gone}`))) return "";
    try {
      await api(path, { method: "DELETE" });
      return "";
    } catch (e) {
      return `Could not ${what.toLowerCase()} the ${noun}: ${e.message}`;
    }
  }

  /** Send a form's multipart ``data`` to ``path`` (POST); on 202 go to ``pageOf(answer)``. While it
   * uploads the ``button`` is disabled and ``status`` says so; a refusal is shown in ``errorBox``
   * (focused, so a screen reader reads it) as "The NOUN was not submitted: detail". */
  async function submitForm(path, data, { noun, button, status, errorBox, pageOf }) {
    button.disabled = true;
    status.textContent = "Uploading and checking the files…";
    try {
      const made = await api(path, { method: "POST", body: data });
      status.textContent = "Submitted.";
      location.assign(pageOf(made));
    } catch (e) {
      status.textContent = "";
      errorBox.textContent = `The ${noun} was not submitted: ${e.message}`;
      errorBox.hidden = false;
      errorBox.setAttribute("tabindex", "-1");
      errorBox.focus();
    } finally {
      button.disabled = false;
    }
  }

  /** The page header: brand, navigation with the current page marked, who is signed in, sign out. */
  function header(active) {
    const top = document.getElementById("top");
    if (!top) return;
    const link = (href, text, key) => el("a", { href, text, "aria-current": key === active ? "page" : null });
    const who = el("span", { class: "who", "aria-live": "polite" });
    const out = el("button", { type: "button", text: "Sign out", onclick: () => {
      try { localStorage.removeItem(TOKEN_KEY); } catch (e) { /* ignore */ }
      location.assign("/login");
    } });
    top.replaceChildren(
      el("a", { class: "brand", href: "/", text: "acinoset" }),
      el("nav", { "aria-label": "Main" }, link("/", "Jobs", "jobs"), link("/jobs/new", "New job", "new"),
        link("/calibrations", "Calibrations", "calibrations"),
        el("span", { class: "spacer" }), token() ? who : null, token() ? out : null));
    if (token()) {
      api("/v1/me").then((me) => { who.textContent = `Signed in as ${me.name}${me.admin ? " (admin)" : ""}`; })
        .catch(() => { /* the call redirects on 401; other errors leave the name out */ });
    }
  }

  window.Acino = { TOKEN_KEY, ApiError, el, token, requireToken, api, download, STATUSES, isActive, statusBadge,
    statusWord, statusSentence, fmtDate, fmtSeconds, progressText, queuedText, header, toLogin, fileOrder,
    cancelOrDelete, submitForm,
    setToken(t) { localStorage.setItem(TOKEN_KEY, t); } };
})();

/* Sign in: check the API token against GET /v1/me and keep it in this browser. */
(function () {
  "use strict";
  const { api, header } = window.Acino;
  header("login");
  const form = document.getElementById("login-form");
  const input = document.getElementById("token");
  const error = document.getElementById("login-error");
  const show = document.getElementById("show-token");
  const params = new URLSearchParams(location.search);
  if (params.get("reason") === "expired") {
    document.getElementById("login-note").textContent =
      "Your token was not accepted (it may have been revoked). Sign in again.";
  }

  // Where to go after signing in: a path of this server only. The browser's own URL parser decides
  // (it reads "/\\evil.example", "/\tevil" and "/%0a/evil" as other hosts, which a prefix check misses).
  function safeNext() {
    const next = params.get("next") || "/";
    if (!next.startsWith("/") || /[\\\u0000-\u001f\u007f]/.test(next)) return "/";
    let url;
    try {
      url = new URL(next, location.origin);
    } catch (e) {
      return "/";
    }
    // the parser resolves dot segments: "/.//evil.example" becomes the path "//evil.example", which
    // location.assign would read as another host
    if (url.origin !== location.origin || url.pathname.startsWith("//") || url.pathname.startsWith("/login")) {
      return "/";
    }
    return url.pathname + url.search + url.hash;
  }

  show.addEventListener("change", () => { input.type = show.checked ? "text" : "password"; });

  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    error.hidden = true;
    const t = input.value.trim();
    if (!t) {
      error.textContent = "Paste your API token first.";
      error.hidden = false;
      input.focus();
      return;
    }
    const button = form.querySelector("button[type=submit]");
    button.disabled = true;
    try {
      await api("/v1/me", { token: t, noRedirect: true });
      window.Acino.setToken(t);
      location.assign(safeNext());
    } catch (e) {
      error.textContent = e.status === 401
        ? "That token was not accepted. Check that you copied all of it, or ask your admin for a new one."
        : `Could not sign in: ${e.message}`;
      error.hidden = false;
      input.setAttribute("aria-invalid", "true");
      input.focus();
    } finally {
      button.disabled = false;
    }
  });
})();

/* Calibrate a rig: the board, each camera's detections or video (in camera order), optional
 * intrinsics and options, sent as POST /v1/calibrations (multipart); on 202 go to its page. */
(function () {
  "use strict";
  const A = window.Acino;
  if (!A.requireToken()) return;
  A.header("calibrations");
  const $ = (x) => document.getElementById(x);
  const form = $("calibrate-form");
  const errorBox = $("submit-error");
  const status = $("submit-status");
  const views = A.fileOrder($("views"), $("view-list"), (files) => {
    status.textContent = files.length ? `${files.length} file${files.length === 1 ? "" : "s"} selected.` : "";
  });
  const kind = () => form.querySelector("input[name=board-kind]:checked").value;
  const source = () => form.querySelector("input[name=source]:checked").value;
  const mm = (id) => Number($(id).value) / 1000;

  /** The board spec the API takes, from the fields (lengths in metres). */
  function spec() {
    const grid = `${$("board-cols").value}x${$("board-rows").value}`;
    return kind() === "charuco"
      ? `charuco:${grid}:${mm("board-square")}:${mm("board-marker")}:${$("board-dictionary").value}`
      : `checkerboard:${grid}:${mm("board-square")}`;
  }

  function drawBoard() {
    const charuco = kind() === "charuco";
    for (const f of form.querySelectorAll(".charuco-only")) f.hidden = !charuco;
    $("board-cols-label").textContent = charuco ? "Squares across" : "Inner corners across";
    $("board-rows-label").textContent = charuco ? "Squares down" : "Inner corners down";
    $("board-spec").textContent = spec();
  }

  function drawSource() {
    const videos = source() === "videos";
    for (const f of form.querySelectorAll(".videos-only")) f.hidden = !videos;
    $("views-label").textContent = videos ? "Videos, one per camera" : "Detection files, one per camera";
    $("views").accept = videos ? "video/*,.mp4,.avi,.mov,.mkv" : ".json";
  }

  form.addEventListener("input", drawBoard);
  for (const r of form.querySelectorAll("input[name=board-kind]")) r.addEventListener("change", drawBoard);
  for (const r of form.querySelectorAll("input[name=source]")) r.addEventListener("change", drawSource);
  drawBoard();
  drawSource();

  function showError(text, focus) {
    errorBox.textContent = text;
    errorBox.hidden = !text;
    if (text && focus) focus.focus();
  }

  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    showError("");
    const files = views.files();
    if (files.length < 2) return showError("Choose one file per camera, at least two cameras.", $("views"));
    for (const id of ["board-cols", "board-rows", "board-square"].concat(kind() === "charuco" ? ["board-marker"] : [])) {
      if (!(Number($(id).value) > 0)) return showError("The board's sizes must be positive numbers.", $(id));
    }
    const intrinsics = Array.from($("intrinsics").files)
      .sort((a, b) => a.name.localeCompare(b.name, undefined, { numeric: true }));
    if (intrinsics.length && intrinsics.length !== files.length) {
      return showError(`Give intrinsics for every camera or none: ${intrinsics.length} files for ${files.length} cameras.`,
        $("intrinsics"));
    }
    const options = { model: $("model").value, lens: $("lens").value,
                      origin: $("origin").value.trim() || "camera1" };
    if (source() === "videos") options.every = Math.max(1, Math.round(Number($("every").value) || 1));
    const label = $("label").value.trim();
    if (label) options.label = label;
    const data = new FormData();
    data.append("board", spec());
    for (const f of files) data.append(source(), f, f.name);
    for (const f of intrinsics) data.append("intrinsics", f, f.name);
    data.append("options", JSON.stringify(options));
    await A.submitForm("/v1/calibrations", data, { noun: "calibration", button: form.querySelector("button[type=submit]"),
      status, errorBox, pageOf: (cal) => cal.links.page });
  });
})();

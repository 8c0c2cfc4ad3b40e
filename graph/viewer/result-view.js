/* The result view: 3D skeleton playback, reprojection error per marker and camera, coordinates
 * and pose parameters over time with their uncertainty, and what the solver flagged.
 *
 * Draws from the payload of graph.viewer.payload.result_payload (the service's result?format=json). Used by
 * the job page and inlined into the HTML file `acinoset plot` writes; needs Plotly and dom.js.
 *
 *   const view = AcinoResultView.render(containerElement, payload, { onFrame(n, fromPlayback) {}, onPlaying(on, speed) {} });
 *   view.setFrame(42);
 *
 * render() builds one panel after another (summary, 3D playback, error heat map, over time,
 * flags), each by its own function below, then wires the frame control that they all follow.
 */
(function () {
  "use strict";

  const { el } = window.AcinoDom;

  // Okabe-Ito colours (safe for colour-blind readers); sides also differ by line style.
  const COLOR = { left: "#0072B2", right: "#D55E00", mid: "#333333", flag: "#CC0000",
                  camera: "#009E73", path: "#999999", band: "rgba(0,114,178,0.22)" };
  // several individuals' bones: the rest of the Okabe-Ito palette, then more
  const INDIVIDUAL_COLORS = ["#E69F00", "#56B4E9", "#009E73", "#CC79A7", "#0072B2", "#D55E00", "#F0E442", "#000000"];
  const PLOT_CONFIG = { displaylogo: false, responsive: true };
  // Light (small error) to dark (large error), the light half of magma: numbers stay readable.
  const ERROR_SCALE = [[0, "#fcfdbf"], [0.25, "#feb078"], [0.5, "#f1605d"], [0.75, "#b73779"], [1, "#51127c"]];

  let uid = 0;
  const newId = (stem) => `${stem}-${++uid}`;
  const fmt = (v, d) => (v === null || v === undefined || !isFinite(v) ? "–" : Number(v).toFixed(d));
  const side = (name) => (/^(l_|left)/i.test(name) ? "left" : /^(r_|right)/i.test(name) ? "right" : "mid");
  const seen = (p) => p && p[0] !== null;

  function ranges(frames) {
    const fs = Array.from(new Set(frames)).sort((a, b) => a - b);
    const out = [];
    for (const f of fs) {
      if (out.length && f === out[out.length - 1][1] + 1) out[out.length - 1][1] = f;
      else out.push([f, f]);
    }
    return out;
  }

  function plural(n, one, many) { return `${n} ${n === 1 ? one : (many || one + "s")}`; }

  /** A card section headed by its title, labelled by that heading. */
  function card(title) {
    const section = el("section", { class: "card", "aria-labelledby": newId("h") });
    section.append(el("h2", { id: section.getAttribute("aria-labelledby"), text: title }));
    return section;
  }

  /** Call fn with the first clicked point of a Plotly plot; hooked once however often it is redrawn. */
  function onPlotClick(plot, fn) {
    if (plot._acinoClick) return;
    plot._acinoClick = true;
    plot.on("plotly_click", (ev) => { if (ev.points && ev.points.length) fn(ev.points[0]); });
  }

  function bbox(pts) {
    const lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (const p of pts) for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], p[k]); hi[k] = Math.max(hi[k], p[k]); }
    if (!pts.length) return { lo: [-1, -1, -1], hi: [1, 1, 1] };
    return { lo, hi };
  }

  function cube(lo, hi, minExtent) {
    const mid = [0, 1, 2].map((k) => (lo[k] + hi[k]) / 2);
    let ext = [0, 1, 2].map((k) => Math.max(hi[k] - lo[k], minExtent) * 1.1);
    const big = Math.max(...ext);
    ext = ext.map((e) => Math.max(e, 0.2 * big));
    return {
      ranges: [0, 1, 2].map((k) => [mid[k] - ext[k] / 2, mid[k] + ext[k] / 2]),
      aspect: { x: ext[0] / big, y: ext[1] / big, z: ext[2] / big },
    };
  }

  // ------------------------------------------------------------------ the payload and its facts

  /** Older or partial payloads: fill what the view needs with "unknown". */
  function fillGaps(P) {
    const blank = (v) => P.positions.map((f) => f.map(() => v));
    P.cameras = P.cameras || P.camera_names || [];
    P.std = P.std || blank([null, null, null]);
    P.ncams = P.ncams || blank(0);
    P.outliers = P.outliers || [];
    P.residuals = P.residuals || P.cameras.map(() => blank(null));
    P.error_table = P.error_table || { median: P.cameras.map(() => P.markers.map(() => null)),
      observations: P.cameras.map(() => P.markers.map(() => 0)), outliers: P.cameras.map(() => P.markers.map(() => 0)) };
    P.param_names = P.param_names || [];
    P.param_units = P.param_units || P.param_names.map((p) => (/^[xyz]_/.test(p) ? "m" : "rad"));
  }

  /** The run's frame number of the view's frame n, "of" the run's last. */
  function frameName(ctx, n) {
    return `${n * ctx.step} of ${(ctx.report.frames || ctx.N) - 1}`;
  }

  /** What every panel reads: sizes, lookups, the flags per frame and the shared playback state. */
  function context(P) {
    const N = P.frames, M = P.markers.length, C = P.cameras.length;
    const markerIndex = new Map(P.markers.map((m, i) => [m, i]));
    const boneIdx = (P.bones || []).map(([a, b]) => [markerIndex.get(a), markerIndex.get(b)])
      .filter(([a, b]) => a !== undefined && b !== undefined);
    const report = P.report || {};
    const outByFrame = Array.from({ length: N }, () => []);
    for (const [c, n, m] of P.outliers) outByFrame[n].push([c, m]);
    // The best-observed marker: its path orients the 3D view and it is plotted over time first.
    let track = 0, best = -1;
    for (let m = 0; m < M; m++) {
      let k = 0;
      for (let n = 0; n < N; n++) if (seen(P.positions[n][m])) k++;
      if (k > best) { best = k; track = m; }
    }
    return {
      P, N, M, C, markerIndex, boneIdx, report, outByFrame, track,
      fps: P.fps || 1,
      // a long run's view holds every step-th frame (frame_step); "frame" below is the run's frame number
      step: P.frame_step || 1,
      frames: Array.from({ length: N }, (_, i) => i),
      unconstrainedFrames: new Set(report.unconstrained_frames || []),
      unconstrainedMarkers: new Set(report.unconstrained_markers || []),
      state: { frame: 0, playing: false, speed: 1, view: "run", last: 0, acc: 0, lastSync: 0 },
    };
  }

  /** Per marker in frame n: {missing, weak (cameras < 2), cams, rejected: [camera names]}. */
  function markerFlags(ctx, n) {
    const { P, M } = ctx;
    const flags = P.markers.map(() => ({ missing: false, weak: false, cams: 0, rejected: [] }));
    for (let m = 0; m < M; m++) {
      flags[m].missing = !seen(P.positions[n][m]);
      flags[m].cams = P.ncams[n][m];
      flags[m].weak = flags[m].cams < 2;
    }
    for (const [c, m] of ctx.outByFrame[n]) flags[m].rejected.push(P.cameras[c]);
    return flags;
  }

  /** Frame n in words: one sentence, and a note per flagged marker. */
  function frameSummary(ctx, n) {
    const { P, N, M, fps } = ctx;
    const flags = markerFlags(ctx, n);
    const have = flags.filter((f) => !f.missing).length;
    const blind = ctx.unconstrainedFrames.has(n);  // then every marker is weak: said once, below
    const notes = [];
    flags.forEach((f, m) => {
      const bits = [];
      if (f.missing) bits.push("no estimate");
      else if (f.weak && !blind) bits.push(`seen by ${plural(f.cams, "camera")}`);
      if (f.rejected.length) bits.push(`rejected in ${f.rejected.join(", ")}`);
      if (bits.length) notes.push(`${P.markers[m]}: ${bits.join("; ")}`);
    });
    let text = `Frame ${frameName(ctx, n)} (${(n / fps).toFixed(3)} s). ${have} of ${M} markers estimated.`;
    if (P.frame_error && P.frame_error[n] !== null) text += ` Reprojection error ${fmt(P.frame_error[n], 1)} px.`;
    if (blind) text += " No marker was seen by two cameras in this frame.";
    return { text, notes };
  }

  /** Grey bands over the frames where no marker was seen by two cameras. */
  function hatchShapes(ctx, yref) {
    return ranges([...ctx.unconstrainedFrames]).map(([a, b]) => ({ type: "rect", xref: "x", yref, x0: a - 0.5, x1: b + 0.5,
      y0: 0, y1: 1, fillcolor: "rgba(120,120,120,0.25)", line: { width: 0 }, layer: "below" }));
  }

  /** The dotted line at the current frame. */
  function cursorShape(ctx) {
    const f = ctx.state.frame;
    return { type: "line", xref: "x", yref: "paper", x0: f, x1: f, y0: 0, y1: 1,
      line: { color: "#000", width: 1.5, dash: "dot" }, name: "cursor" };
  }

  // ------------------------------------------------------------------ summary

  const ORDER_WORDS = { 1: "a random walk of positions", 2: "constant velocity", 3: "constant acceleration" };

  /** Scales as "x1.4", or many as their median and range. */
  function scalesText(values) {
    const fmt = (v) => (isFinite(v) ? Number(v).toPrecision(2) : "–");  // scales span 1e-6 to 1e3
    if (values.length === 1) return `×${fmt(values[0])} the model's process noise`;
    const sorted = values.slice().sort((a, b) => a - b);
    return `×${fmt(sorted[Math.floor(sorted.length / 2)])} (median; ${fmt(sorted[0])}–` +
      `${fmt(sorted[sorted.length - 1])} over ${sorted.length} markers)`;
  }

  /** The process noise's scale: fitted, or given (one, or one per group from an earlier run). */
  function smoothingText(report, options) {
    const fitted = report.motion_scales ? Object.values(report.motion_scales) : [];
    if (fitted.length) return `fitted to the data${fitted.length > 1 ? " per marker" : ""}: ${scalesText(fitted)}`;
    const given = options.motion_scale;
    if (typeof given === "number") return `${scalesText([given])} (given)`;
    if (given && typeof given === "object") return `given per group: ${scalesText(Object.values(given))}`;
    return null;
  }

  /** The motion prior's order: chosen from the data (how many groups took each) or given. */
  function motionModelText(report, options) {
    const per = (orders) => {
      const counts = {};
      for (const k of orders) counts[k] = (counts[k] || 0) + 1;
      return Object.keys(counts).sort().map((k) => `order ${k} (${ORDER_WORDS[k] || "?"}) for ${counts[k]}`).join(", ");
    };
    if (options.motion_order === "auto" && report.motion_orders) {
      return "chosen from the data: " + per(Object.values(report.motion_orders));
    }
    const k = options.motion_order || 3;
    if (typeof k === "object") return "given per group: " + per(Object.values(k));
    return `order ${k} (${ORDER_WORDS[k] || "?"})`;
  }

  function summaryPanel(ctx) {
    const { P, N, M, fps, report } = ctx;
    const section = card("Summary");
    const dl = el("dl", { class: "facts" });
    const fact = (k, v) => dl.append(el("dt", { text: k }), el("dd", { text: v }));
    fact("Method", `${P.method} (${P.skeleton} skeleton)`);
    const all = report.frames || N, rate = Number((fps * ctx.step).toPrecision(12));
    fact("Frames", `${all} at ${rate} fps (${(all / rate).toFixed(2)} s)` +
      (ctx.step > 1 ? `; one frame in ${ctx.step} shown (${N})` : ""));
    fact("Markers", String(M));
    fact("Cameras", P.cameras.join(", "));
    fact("Reprojection RMSE", `${fmt(report.reprojection_rmse_px, 2)} px`);
    fact("Rejected detections", `${report.outliers ?? P.outliers.length} of ${report.observations ?? "–"}`);
    if (report.sigma_px > 0) {
      const measuredNoise = P.options && P.options.measurement_std_px === "auto";
      let noise = `${fmt(report.sigma_px, 2)} px ${measuredNoise ? "(measured from the data)" : "(given)"}`;
      if (!measuredNoise && report.noise_px > 0) noise += `; the residuals scatter ${fmt(report.noise_px, 2)} px`;
      fact("Detection noise", noise);
    }
    const smoothing = smoothingText(report, P.options || {});
    if (smoothing) fact("Smoothing", smoothing);
    if (P.method !== "tri") fact("Motion model", motionModelText(report, P.options || {}));
    const { unconstrainedMarkers, unconstrainedFrames } = ctx;
    fact("Never seen by two cameras", unconstrainedMarkers.size ? [...unconstrainedMarkers].join(", ") : "none");
    fact("Frames with no marker seen twice", unconstrainedFrames.size
      ? ranges([...unconstrainedFrames]).map(([a, b]) => (a === b ? `${a}` : `${a}–${b}`)).join(", ") : "none");
    if (report.iterations) fact("Iterations", String(report.iterations));
    if (report.seconds && report.seconds.total) fact("Solve time", `${fmt(report.seconds.total, 2)} s`);
    section.append(dl);
    if (report.warnings && report.warnings.length) {
      section.append(el("h3", { text: "Warnings" }), el("ul", {}, report.warnings.map((w) => el("li", { text: w }))));
    }
    return section;
  }

  /** The body and the clocks the solve estimated or was given: a table of lengths against the
   *  model's, and each camera's time offset, with their sd; null when the solve had neither. */
  function bodyAndClocksPanel(ctx) {
    const { P, report } = ctx;
    const lengths = report.body_lengths || null;
    const offsets = report.time_offsets_frames || null;
    if (!lengths && !offsets) return null;
    const section = card("Body and clocks");
    section.dataset.testid = "body-and-clocks";
    const cm = (v) => (v == null ? "–" : `${fmt(v * 100, 1)} cm`);
    if (lengths) {
      const rows = Object.entries(lengths).map(([name, v]) => el("tr", {},
        el("th", { scope: "row", text: name }), el("td", { text: cm(v.length_m) }),
        el("td", { text: v.std_m ? `± ${cm(v.std_m)}` : "given" }), el("td", { text: cm(v.model_m) }),
        el("td", { text: v.model_m ? `${fmt((v.length_m / v.model_m - 1) * 100, 1)} %` : "–" })));
      section.append(el("table", { class: "data" },
        el("caption", { text: "The body: each length (metres in the calibration's frame) against the model's" }),
        el("thead", {}, el("tr", {}, ...["length", "estimated", "sd", "model", "difference"].map((t) => el("th", { scope: "col", text: t })))),
        el("tbody", {}, ...rows)));
    }
    if (offsets) {
      const sd = report.time_offsets_std_frames || [];
      const lost = new Set(report.offsets_not_identified || []);
      const rows = offsets.map((t, c) => el("tr", {},
        el("th", { scope: "row", text: P.cameras[c] }), el("td", { text: `${fmt(t, 3)} frames` }),
        el("td", { text: c === 0 ? "reference" : sd[c] ? `± ${fmt(sd[c], 3)}` : "given" }),
        el("td", { text: `${fmt((t / (P.fps || 1)) * 1000, 2)} ms` }),
        el("td", { text: lost.has(P.cameras[c]) ? "not identified by the motion" : "" })));
      section.append(el("table", { class: "data" },
        el("caption", { text: "The clocks: each camera's time offset (its frame n is at n + offset)" }),
        el("thead", {}, el("tr", {}, ...["camera", "offset", "sd", "in time", ""].map((t) => el("th", { scope: "col", text: t })))),
        el("tbody", {}, ...rows)));
    }
    return section;
  }

  // ------------------------------------------------------------------ 3D playback

  /** The 3D playback card: the plot's box, the playback controls and the frame's description. */
  function playbackPanel(ctx) {
    const { P, N, M, C, state } = ctx;
    const section = card("3D playback");
    section.append(el("p", { class: "hint", text:
      "Drag to rotate, scroll to zoom. Bones: left side solid blue, right side dashed orange, midline grey. " +
      "Markers drawn as an open diamond are flagged in this frame (seen by fewer than two cameras, or a detection " +
      "was rejected); they are named beside it and listed below." }));
    const plot3d = el("div", { class: "plot plot3d", role: "img", "data-testid": "plot3d",
      "aria-label": `3D skeleton of ${P.skeleton}, ${M} markers` + (P.camera_centers ? ` and ${C} cameras` : "") });
    const sliderId = newId("frame");
    const numberId = newId("frame-number");
    const speedId = newId("speed");
    const viewId = newId("view");
    const playBtn = el("button", { type: "button", class: "primary", "aria-pressed": "false", text: "▶ Play" });
    const prevBtn = el("button", { type: "button", "aria-label": "Previous frame", text: "◀ Prev" });
    const nextBtn = el("button", { type: "button", "aria-label": "Next frame", text: "Next ▶" });
    const slider = el("input", { type: "range", id: sliderId, min: 0, max: Math.max(0, N - 1), step: 1, value: 0,
      "data-testid": "frame-slider" });
    const number = el("input", { type: "number", id: numberId, min: 0, max: Math.max(0, N - 1), step: 1, value: 0,
      class: "narrow" });
    const speed = el("select", { id: speedId },
      [["0.1", "0.1× (slow motion)"], ["0.25", "0.25×"], ["0.5", "0.5×"], ["1", "1× (real time)"]].map(
        ([v, t]) => el("option", { value: v, selected: v === "0.25", text: t })));
    state.speed = 0.25;
    const view = el("select", { id: viewId },
      el("option", { value: "run", text: "Whole run" }),
      el("option", { value: "follow", text: "Follow the animal" }),
      el("option", { value: "scene", text: "Scene with cameras", disabled: !P.camera_centers }));
    const status = el("p", { class: "frame-status", "aria-live": "polite", "data-testid": "frame-status" });
    const notes = el("ul", { class: "frame-notes" });
    const controls = el("div", { class: "controls", role: "group", "aria-label": "Playback controls" },
      playBtn, prevBtn, nextBtn,
      el("label", { for: sliderId, class: "grow" }, "Frame ", slider),
      el("label", { for: numberId }, "Frame number ", number),
      el("label", { for: speedId }, "Speed ", speed),
      el("label", { for: viewId }, "View ", view));
    const timeLabel = el("span", { class: "time" });
    section.append(plot3d, controls, timeLabel, status, notes);

    /** The frame in words under the plot, and on the slider for screen readers. */
    function describe(n) {
      const s = frameSummary(ctx, n);
      status.textContent = s.text + (s.notes.length ? ` ${plural(s.notes.length, "marker")} flagged:` : " No marker flagged.");
      notes.replaceChildren(...s.notes.slice(0, 30).map((t) => el("li", { text: t })));
      if (s.notes.length > 30) notes.append(el("li", { text: `and ${s.notes.length - 30} more` }));
      showTime(n);
      slider.setAttribute("aria-valuetext", `Frame ${frameName(ctx, n)}, ${(n / ctx.fps).toFixed(3)} seconds`);
    }

    function showTime(n) { timeLabel.textContent = `${(n / ctx.fps).toFixed(3)} s`; }

    return { section, plot3d, playBtn, prevBtn, nextBtn, slider, number, speed, view, status, describe, showTime };
  }

  /** The skeleton, the cameras and the tracked marker's path drawn into plot3d; draw(n) moves to frame n. */
  function skeletonScene(ctx, plot3d) {
    const { P, N, M, boneIdx, track, state } = ctx;
    const all = [];
    for (const fr of P.positions) for (const p of fr) if (seen(p)) all.push(p);
    const runBox = bbox(all);
    // the animal's size (m), from the data: a fly's is a fraction of a millimetre, a cheetah's a metre
    const animalSize = (() => {
      let s = 0;
      for (let n = 0; n < N; n += Math.max(1, Math.floor(N / 20))) {
        const b = bbox(P.positions[n].filter(seen));
        if (isFinite(b.lo[0])) s = Math.max(s, ...[0, 1, 2].map((k) => b.hi[k] - b.lo[k]));
      }
      return s > 0 ? s : 1;
    })();
    const sceneBox = P.camera_centers ? bbox(all.concat(P.camera_centers)) : runBox;

    // The bones' traces: by side (left, right dashed, midline), or with several individuals one each,
    // in a colour of its own (P.individuals: name, markers [first, count]).
    const boneGroups = [];
    if (P.individuals && P.individuals.length) {
      P.individuals.forEach((ind, k) => {
        const [lo, count] = ind.markers;
        boneGroups.push({ name: `bones, ${ind.name}`, line: { color: INDIVIDUAL_COLORS[k % INDIVIDUAL_COLORS.length], width: 6 },
          list: boneIdx.filter(([a]) => a >= lo && a < lo + count) });
      });
    } else {
      const bySide = { left: [], right: [], mid: [] };
      for (const [a, b] of boneIdx) bySide[side(P.markers[b]) !== "mid" ? side(P.markers[b]) : side(P.markers[a])].push([a, b]);
      boneGroups.push({ name: "bones, left side", line: { color: COLOR.left, width: 6 }, list: bySide.left },
        { name: "bones, right side (dashed)", line: { color: COLOR.right, width: 6, dash: "dash" }, list: bySide.right },
        { name: "bones, midline", line: { color: COLOR.mid, width: 6 }, list: bySide.mid });
    }

    function boneXYZ(n, list) {
      const x = [], y = [], z = [];
      for (const [a, b] of list) {
        const pa = P.positions[n][a], pb = P.positions[n][b];
        if (!seen(pa) || !seen(pb)) continue;
        x.push(pa[0], pb[0], null); y.push(pa[1], pb[1], null); z.push(pa[2], pb[2], null);
      }
      return { x, y, z };
    }

    function markerXYZ(n, flagged) {
      const x = [], y = [], z = [], text = [], hover = [];
      markerFlags(ctx, n).forEach((f, m) => {
        const isFlag = f.weak || f.rejected.length > 0;
        if (f.missing || isFlag !== flagged) return;
        const p = P.positions[n][m], s = P.std[n][m];
        x.push(p[0]); y.push(p[1]); z.push(p[2]);
        text.push(P.markers[m]);
        const sd = s && s[0] !== null ? Math.max(s[0], s[1], s[2]) * 2000 : null;
        let h = `${P.markers[m]}<br>x ${fmt(p[0], 3)}, y ${fmt(p[1], 3)}, z ${fmt(p[2], 3)} m` +
          `<br>±2 std ${fmt(sd, 0)} mm<br>seen by ${plural(f.cams, "camera")}`;
        if (f.rejected.length) h += `<br>rejected in ${f.rejected.join(", ")}`;
        hover.push(h);
      });
      return { x, y, z, text, hover };
    }

    const traces = [];
    const idx = {};
    if (P.camera_centers) {
      idx.cameras = traces.length;
      const cc = P.camera_centers;
      traces.push({ type: "scatter3d", mode: "markers+text", name: "cameras",
        x: cc.map((c) => c[0]), y: cc.map((c) => c[1]), z: cc.map((c) => c[2]), text: P.cameras,
        textposition: "top center", marker: { symbol: "square", size: 5, color: COLOR.camera },
        hovertemplate: "%{text}<br>x %{x:.2f}, y %{y:.2f}, z %{z:.2f} m<extra></extra>" });
      if (P.camera_directions) {
        const span = Math.max(...[0, 1, 2].map((k) => sceneBox.hi[k] - sceneBox.lo[k]));
        const L = 0.08 * span, x = [], y = [], z = [];
        cc.forEach((c, i) => {
          const d = P.camera_directions[i];
          x.push(c[0], c[0] + L * d[0], null); y.push(c[1], c[1] + L * d[1], null); z.push(c[2], c[2] + L * d[2], null);
        });
        traces.push({ type: "scatter3d", mode: "lines", name: "camera view direction", x, y, z,
          line: { color: COLOR.camera, width: 3 }, hoverinfo: "skip" });
      }
    }
    idx.path = traces.length;
    traces.push({ type: "scatter3d", mode: "lines", name: `path of ${P.markers[track]}`,
      x: P.positions.map((f) => (f[track] ? f[track][0] : null)),
      y: P.positions.map((f) => (f[track] ? f[track][1] : null)),
      z: P.positions.map((f) => (f[track] ? f[track][2] : null)),
      line: { color: COLOR.path, width: 2 }, hoverinfo: "skip" });
    idx.bones = boneGroups.map((g) => {
      traces.push({ type: "scatter3d", mode: "lines", name: g.name, ...boneXYZ(0, g.list), line: g.line, hoverinfo: "skip" });
      return traces.length - 1;
    });
    const mk0 = markerXYZ(0, false), fl0 = markerXYZ(0, true);
    idx.markers = traces.length;
    // Without bones the dots carry their names, or nobody could tell the nose from the tail.
    traces.push({ type: "scatter3d", mode: boneIdx.length ? "markers" : "markers+text", name: "markers",
      x: mk0.x, y: mk0.y, z: mk0.z, text: mk0.text, hovertext: mk0.hover, hovertemplate: "%{hovertext}<extra></extra>",
      textposition: "top center", textfont: { size: 10, color: "#444444" }, marker: { size: 3.5, color: "#222222" } });
    idx.flagged = traces.length;
    traces.push({ type: "scatter3d", mode: "markers+text", name: "flagged markers (◇)", x: fl0.x, y: fl0.y, z: fl0.z,
      text: fl0.text, hovertext: fl0.hover, hovertemplate: "%{hovertext}<extra></extra>", textposition: "top center",
      textfont: { color: COLOR.flag, size: 11 }, marker: { size: 9, symbol: "diamond-open", color: COLOR.flag } });

    /** Axis ranges of the chosen view ("run", "follow" the animal at frame n, or the "scene" with cameras). */
    function sceneLayout(n) {
      let box;
      if (state.view === "scene") box = cube(sceneBox.lo, sceneBox.hi, animalSize);
      else if (state.view === "follow") {
        const b = bbox(P.positions[n].filter(seen));
        const mid = [0, 1, 2].map((k) => (isFinite(b.lo[k]) ? (b.lo[k] + b.hi[k]) / 2 : 0));
        const h = 0.6 * animalSize;
        box = cube(mid.map((v) => v - h), mid.map((v) => v + h), 0.5 * animalSize);
      } else box = cube(runBox.lo, runBox.hi, animalSize * 0.6);
      return {
        "scene.xaxis.range": box.ranges[0], "scene.yaxis.range": box.ranges[1], "scene.zaxis.range": box.ranges[2],
        "scene.aspectratio": box.aspect,
      };
    }

    const layout3d = {
      margin: { l: 0, r: 0, t: 10, b: 0 }, height: 520, uirevision: "keep", showlegend: true,
      legend: { x: 0, y: 1, bgcolor: "rgba(255,255,255,0.7)" },
      scene: {
        aspectmode: "manual", uirevision: "keep",
        xaxis: { title: { text: "x (m)" }, autorange: false },
        yaxis: { title: { text: "y (m)" }, autorange: false },
        zaxis: { title: { text: "z (m)" }, autorange: false },
        camera: { eye: { x: 0.3, y: -1.25, z: 0.5 } },
      },
    };
    const first = sceneLayout(0);
    layout3d.scene.xaxis.range = first["scene.xaxis.range"];
    layout3d.scene.yaxis.range = first["scene.yaxis.range"];
    layout3d.scene.zaxis.range = first["scene.zaxis.range"];
    layout3d.scene.aspectratio = first["scene.aspectratio"];
    const ready = Plotly.newPlot(plot3d, traces, layout3d, PLOT_CONFIG);

    function draw(n) {
      const B = boneGroups.map((g) => boneXYZ(n, g.list));
      const mk = markerXYZ(n, false), fl = markerXYZ(n, true);
      const none = B.map(() => null);
      const upd = {
        x: [...B.map((b) => b.x), mk.x, fl.x], y: [...B.map((b) => b.y), mk.y, fl.y], z: [...B.map((b) => b.z), mk.z, fl.z],
        text: [...none, mk.text, fl.text], hovertext: [...none, mk.hover, fl.hover],
      };
      const lay = state.view === "follow" ? sceneLayout(n) : {};
      return Plotly.update(plot3d, upd, lay, [...idx.bones, idx.markers, idx.flagged]);
    }

    /** Apply a change of state.view. */
    function reframe() { return Plotly.relayout(plot3d, sceneLayout(state.frame)); }

    return { ready, draw, reframe };
  }

  // ------------------------------------------------------------------ reprojection error heat map

  /** Reprojection error per marker and camera, over the run or in the current frame; a click on a
   * cell calls showMarker(m). */
  function errorPanel(ctx, showMarker) {
    const { P, M, C, state, markerIndex } = ctx;
    const section = card("Reprojection error per marker and camera");
    // the noise the solve assumed: measured when the option was "auto" (the report has it)
    const optSigma = P.options && Number(P.options.measurement_std_px);
    const sigmaPx = (P.report && P.report.sigma_px > 0) ? Number(P.report.sigma_px.toFixed(2))
      : (optSigma > 0 ? optSigma : 5);
    section.append(el("p", { class: "hint", text:
      "Pixel distance between each camera's detection and the 3D estimate drawn into that camera. " +
      "Every cell is labelled with its number; (n×) counts detections the robust loss rejected as outliers. " +
      "Click a cell to plot that marker over time." +
      ` The colours run from 0 to at least twice the expected detection noise ` +
      `(${sigmaPx} px): light is as good as the detections allow, dark is worse.` }));
    const modeId = newId("heat-mode");
    const mode = el("select", { id: modeId },
      el("option", { value: "run", text: "Whole run: median over frames" }),
      el("option", { value: "frame", text: "Current frame" }));
    section.append(el("div", { class: "controls" }, el("label", { for: modeId }, "Show ", mode)));
    const plot = el("div", { class: "plot", role: "img", "data-testid": "heatmap",
      "aria-label": "Heat map of reprojection error, markers by cameras; the same numbers are in the table below" });
    const table = el("table", { class: "data" });
    section.append(plot, el("details", {}, el("summary", { text: "Show the numbers as a table" }), table));

    function cells(which, n) {
      const z = [], text = [];
      for (let m = 0; m < M; m++) {
        const zr = [], tr = [];
        for (let c = 0; c < C; c++) {
          if (which === "run") {
            const v = P.error_table.median[c][m], nobs = P.error_table.observations[c][m], nout = P.error_table.outliers[c][m];
            zr.push(v);
            tr.push(nobs === 0 ? "not seen" : (v === null ? "all rejected" : fmt(v, 1)) + (nout ? ` (${nout}×)` : ""));
          } else {
            const v = P.residuals[c][n][m];
            const rej = ctx.outByFrame[n].some(([cc, mm]) => cc === c && mm === m);
            zr.push(v);
            tr.push(v === null ? "not seen" : fmt(v, 1) + (rej ? " rejected" : ""));
          }
        }
        z.push(zr); text.push(tr);
      }
      return { z, text };
    }

    function draw() {
      const d = cells(mode.value, state.frame);
      const trace = { type: "heatmap", z: d.z, x: P.cameras, y: P.markers, text: d.text,
        texttemplate: "%{text}", textfont: { size: 11 }, colorscale: ERROR_SCALE, zmin: 0,
        colorbar: { title: { text: "px" } }, hoverongaps: false, xgap: 1, ygap: 1,
        hovertemplate: "%{y} in %{x}: %{text} px<extra></extra>" };
      if (mode.value === "run") {
        const vals = d.z.flat().filter((v) => v !== null).sort((a, b) => a - b);
        trace.zmax = Math.max(2 * sigmaPx, vals.length ? vals[Math.floor(0.98 * (vals.length - 1))] : 1);
      } else trace.zmax = 4 * sigmaPx;
      const lay = { margin: { l: 110, r: 10, t: 10, b: 40 }, height: Math.max(260, 24 * M + 70),
        yaxis: { autorange: "reversed", automargin: true }, xaxis: { side: "bottom" }, plot_bgcolor: "#eeeeee" };
      Plotly.react(plot, [trace], lay, PLOT_CONFIG).then(() => onPlotClick(plot, (pt) => {
        const m = markerIndex.get(pt.y);
        if (m !== undefined) showMarker(m);
      }));
      table.replaceChildren(
        el("caption", { text: mode.value === "run" ? "Median reprojection error (px), whole run"
          : `Reprojection error (px), frame ${state.frame}` }),
        el("thead", {}, el("tr", {}, el("th", { scope: "col", text: "Marker" }),
          P.cameras.map((c) => el("th", { scope: "col", text: c })))),
        el("tbody", {}, P.markers.map((m, i) => el("tr", {}, el("th", { scope: "row", text: m }),
          d.text[i].map((t) => el("td", { text: t }))))));
    }
    mode.addEventListener("change", draw);

    return { section, draw, followsFrame: () => mode.value === "frame" };
  }

  // ------------------------------------------------------------------ over time

  /** A marker's coordinates, a pose parameter or the fit per frame, with ±2 sd bands; a click
   * calls setFrame. */
  function seriesPanel(ctx, setFrame) {
    const { P, C, fps, frames, outByFrame, track } = ctx;
    const section = card("Over time");
    section.append(el("p", { class: "hint", text:
      "The estimate with a band of ±2 standard deviations. Hatched grey: frames with no marker seen by two " +
      "cameras. The vertical line is the current frame; click the plot to go to a frame." }));
    const whatId = newId("what");
    const what = el("select", { id: whatId, "data-testid": "series-select" },
      el("optgroup", { label: "Marker coordinates" },
        P.markers.map((m, i) => el("option", { value: `m:${i}`, text: m }))),
      P.params && P.param_names.length ? el("optgroup", { label: "Pose parameters" },
        P.param_names.map((p, i) => el("option", { value: `p:${i}`,
          text: `${p} (${P.param_units[i] === "m" ? "m" : "degrees"})` }))) : null,
      el("optgroup", { label: "Fit" }, el("option", { value: "err", text: "Reprojection error per frame" })));
    what.value = `m:${track}`;
    section.append(el("div", { class: "controls" }, el("label", { for: whatId }, "Plot ", what)));
    const plot = el("div", { class: "plot", role: "img", "data-testid": "series",
      "aria-label": "Selected quantity over frames with its uncertainty band" });
    section.append(plot);

    function band(y, s, k, axis, color, fill, name) {
      const up = y.map((v, i) => (v === null || s[i] === null ? null : v + k * s[i]));
      const lo = y.map((v, i) => (v === null || s[i] === null ? null : v - k * s[i]));
      return [
        { x: frames, y: up, xaxis: axis.x, yaxis: axis.y, mode: "lines", line: { width: 0 }, hoverinfo: "skip",
          showlegend: false },
        { x: frames, y: lo, xaxis: axis.x, yaxis: axis.y, mode: "lines", line: { width: 0 }, fill: "tonexty",
          fillcolor: fill, hoverinfo: "skip", showlegend: false },
        { x: frames, y, xaxis: axis.x, yaxis: axis.y, mode: "lines", line: { color, width: 1.6 }, name,
          hovertemplate: `${name}: %{y:.4f}<br>frame %{x}<extra></extra>` },
      ];
    }

    const base = () => ({ margin: { l: 60, r: 10, t: 10, b: 40 }, showlegend: false, hovermode: "x" });
    const frameAxis = () => ({ title: { text: `frame (${fps} fps)` } });

    function markerFigure(m) {
      const data = [];
      ["x", "y", "z"].forEach((a, k) => {
        const y = P.positions.map((f) => (f[m] ? f[m][k] : null));
        const s = P.std.map((f) => (f[m] ? f[m][k] : null));
        data.push(...band(y, s, 2, { x: "x", y: k ? `y${k + 1}` : "y" }, COLOR.left, COLOR.band, `${P.markers[m]} ${a} (m)`));
      });
      const nc = P.ncams.map((f) => f[m]);
      data.push({ x: frames, y: nc, xaxis: "x", yaxis: "y4", mode: "lines", line: { shape: "hvh", color: "#555" },
        name: "cameras", hovertemplate: "seen by %{y} cameras<br>frame %{x}<extra></extra>" });
      const rej = [];
      P.outliers.forEach(([c, n, mm]) => { if (mm === m) rej.push([n, P.cameras[c]]); });
      data.push({ x: rej.map((r) => r[0]), y: rej.map((r) => P.ncams[r[0]][m]), xaxis: "x", yaxis: "y4",
        mode: "markers", marker: { symbol: "x", size: 8, color: COLOR.flag }, text: rej.map((r) => r[1]),
        name: "rejected", hovertemplate: "rejected in %{text}<br>frame %{x}<extra></extra>" });
      const layout = { ...base(), height: 620,
        grid: { rows: 4, columns: 1, pattern: "coupled", roworder: "top to bottom" },
        yaxis: { title: { text: "x (m)" } }, yaxis2: { title: { text: "y (m)" } }, yaxis3: { title: { text: "z (m)" } },
        yaxis4: { title: { text: "cameras" }, range: [-0.3, C + 0.3], dtick: 1 },
        xaxis: frameAxis() };
      return { data, layout, shapes: ["y domain", "y2 domain", "y3 domain"].flatMap((r) => hatchShapes(ctx, r)) };
    }

    function parameterFigure(p) {
      const k = P.param_units[p] === "m" ? 1 : 180 / Math.PI;
      const y = P.params.map((r) => (r[p] === null ? null : r[p] * k));
      const s = P.params_std ? P.params_std.map((r) => (r[p] === null ? null : r[p] * k)) : y.map(() => null);
      const unit = P.param_units[p] === "m" ? "m" : "degrees";
      const data = band(y, s, 2, { x: "x", y: "y" }, COLOR.left, COLOR.band, `${P.param_names[p]} (${unit})`);
      const layout = { ...base(), height: 320, yaxis: { title: { text: `${P.param_names[p]} (${unit})` } },
        xaxis: frameAxis() };
      return { data, layout, shapes: hatchShapes(ctx, "y domain") };
    }

    function fitFigure() {
      const nrej = frames.map((n) => outByFrame[n].length);
      const data = [
        { x: frames, y: P.frame_error, mode: "lines", line: { color: "#000", width: 1.5 }, name: "RMSE (px)",
          hovertemplate: "RMSE %{y:.2f} px<br>frame %{x}<extra></extra>" },
        { x: frames, y: nrej, yaxis: "y2", type: "bar", marker: { color: "rgba(204,0,0,0.35)" },
          name: "rejected detections", hovertemplate: "%{y} rejected<br>frame %{x}<extra></extra>" },
      ];
      const layout = { ...base(), height: 320, showlegend: true, legend: { orientation: "h", y: 1.12 },
        yaxis: { title: { text: "reprojection RMSE (px)" } },
        yaxis2: { title: { text: "rejected" }, overlaying: "y", side: "right", showgrid: false },
        xaxis: frameAxis(), margin: { l: 60, r: 60, t: 30, b: 40 } };
      return { data, layout, shapes: hatchShapes(ctx, "y domain") };
    }

    let shapes = [];
    function draw() {
      const v = what.value;
      const fig = v.startsWith("m:") ? markerFigure(Number(v.slice(2)))
        : v.startsWith("p:") ? parameterFigure(Number(v.slice(2))) : fitFigure();
      shapes = fig.shapes;
      fig.layout.shapes = [...shapes, cursorShape(ctx)];
      Plotly.react(plot, fig.data, fig.layout, PLOT_CONFIG).then(() => onPlotClick(plot, (pt) => setFrame(pt.x)));
    }
    what.addEventListener("change", draw);

    /** Plot marker m and bring the panel into view. */
    function showMarker(m) {
      what.value = `m:${m}`;
      draw();
      section.scrollIntoView({ block: "start" });
    }

    function moveCursor() {
      if (plot.layout) Plotly.relayout(plot, { shapes: [...shapes, cursorShape(ctx)] });
    }

    return { section, draw, showMarker, moveCursor };
  }

  // ------------------------------------------------------------------ flags

  /** Cameras that saw each marker in each frame, rejected detections as crosses; a click calls setFrame. */
  function cameraRaster(ctx, setFrame) {
    const { P, N, M, C, frames } = ctx;
    const plot = el("div", { class: "plot", role: "img",
      "aria-label": "Cameras that saw each marker in each frame, with rejected detections as crosses; the table above has the counts" });
    const nodes = [el("h3", { text: "Cameras per marker and frame" }),
      el("p", { class: "hint", text: "Darker: fewer cameras saw the marker. Crosses: rejected detections. Hatched grey: " +
        "frames with no marker seen by two cameras. Click to go to a frame." }), plot];

    function draw() {
      const z = P.markers.map((_, m) => P.ncams.map((f) => f[m]));
      const xs = P.outliers.map(([, n]) => n), ys = P.outliers.map(([, , m]) => P.markers[m]);
      const data = [
        { type: "heatmap", z, x: frames, y: P.markers, zmin: 0, zmax: C, colorscale: [[0, "#262626"], [1, "#ffffff"]],
          colorbar: { title: { text: "cameras" }, dtick: 1 }, hovertemplate: "%{y}, frame %{x}: %{z} cameras<extra></extra>" },
        { type: "scatter", mode: "markers", x: xs, y: ys, marker: { symbol: "x", size: 7, color: COLOR.flag },
          text: P.outliers.map(([c]) => P.cameras[c]), hovertemplate: "%{y}, frame %{x}: rejected in %{text}<extra></extra>",
          name: "rejected" },
      ];
      const layout = { margin: { l: 110, r: 10, t: 10, b: 40 }, height: Math.max(240, 18 * M + 70), showlegend: false,
        yaxis: { autorange: "reversed", automargin: true, type: "category" }, xaxis: { title: { text: "frame" }, range: [-0.5, N - 0.5] },
        shapes: [...hatchShapes(ctx, "paper"), cursorShape(ctx)] };
      Plotly.react(plot, data, layout, PLOT_CONFIG).then(() => onPlotClick(plot, (pt) => setFrame(pt.x)));
    }

    function moveCursor() {
      if (plot.layout) Plotly.relayout(plot, { shapes: [...hatchShapes(ctx, "paper"), cursorShape(ctx)] });
    }

    return { nodes, draw, moveCursor };
  }

  /** Per marker: rejected detections, frames seen by fewer than two cameras, frames without estimate. */
  function perMarkerTable(ctx) {
    const { P, N } = ctx;
    const rows = P.markers.map((name, m) => {
      let rej = 0, weak = 0, missing = 0;
      for (let n = 0; n < N; n++) {
        if (P.ncams[n][m] < 2) weak++;
        if (!seen(P.positions[n][m])) missing++;
      }
      for (const [, , mm] of P.outliers) if (mm === m) rej++;
      return { name, rej, weak, missing };
    });
    return el("details", {}, el("summary", { text: "Counts per marker" }),
      el("table", { class: "data", "data-testid": "per-marker" },
        el("thead", {}, el("tr", {}, ["Marker", "Rejected detections", "Frames seen by fewer than 2 cameras", "Frames without estimate"]
          .map((t) => el("th", { scope: "col", text: t })))),
        el("tbody", {}, rows.map((r) => el("tr", {}, el("th", { scope: "row", text: r.name }),
          el("td", { text: String(r.rej) }), el("td", { text: String(r.weak) }), el("td", { text: String(r.missing) }))))));
  }

  /** What the solver flagged: counts, the raster, the blind frames and the frames with most rejections;
   * their buttons call showFrame. */
  function flagsPanel(ctx, setFrame, showFrame) {
    const { P, frames, outByFrame, unconstrainedFrames, unconstrainedMarkers } = ctx;
    const section = card("Flagged by the solver");
    const nFramesRej = outByFrame.filter((o) => o.length).length;
    section.append(el("p", { text:
      `${plural(P.outliers.length, "detection")} rejected as outliers in ${plural(nFramesRej, "frame")}; ` +
      `${plural(unconstrainedFrames.size, "frame")} with no marker seen by two cameras; ` +
      `${plural(unconstrainedMarkers.size, "marker")} never seen by two cameras.` }));
    const raster = cameraRaster(ctx, setFrame);
    section.append(...raster.nodes);
    const goto = (n, label) => el("button", { type: "button", class: "link", text: label || `frame ${n}`,
      "aria-label": `Go to frame ${n}`, onclick: () => showFrame(n) });
    if (unconstrainedMarkers.size) {
      section.append(el("h3", { text: "Markers never seen by two cameras" }),
        el("p", { text: [...unconstrainedMarkers].join(", ") + ": their 3D positions rest on the motion model alone." }));
    }
    if (unconstrainedFrames.size) {
      section.append(el("h3", { text: "Frames with no marker seen by two cameras" }),
        el("p", { class: "buttons" }, ranges([...unconstrainedFrames]).slice(0, 40).map(([a, b]) =>
          goto(a, a === b ? `frame ${a}` : `frames ${a}–${b}`))));
    }
    // Frames with the most rejected detections.
    const worst = frames.filter((n) => outByFrame[n].length).sort((a, b) => outByFrame[b].length - outByFrame[a].length || a - b).slice(0, 10);
    if (worst.length) {
      section.append(el("h3", { text: "Frames with the most rejected detections" }));
      section.append(el("table", { class: "data" },
        el("thead", {}, el("tr", {}, ["Frame", "Rejected", "Which (marker in camera)"].map((t) => el("th", { scope: "col", text: t })))),
        el("tbody", {}, worst.map((n) => el("tr", {},
          el("td", {}, goto(n, String(n))), el("td", { text: String(outByFrame[n].length) }),
          el("td", { text: outByFrame[n].map(([c, m]) => `${P.markers[m]} in ${P.cameras[c]}`).join(", ") }))))));
    }
    section.append(perMarkerTable(ctx));
    return { section, drawRaster: raster.draw, moveCursor: raster.moveCursor };
  }

  // ------------------------------------------------------------------ frame control

  /** Playback, stepping and the keyboard: every panel follows the current frame. The page's
   * hooks (render's opts) hear of it too: onFrame(n, fromPlayback) and onPlaying(on, speed). */
  function frameControl(ctx, play, scene, heat, series, flags, hooks) {
    const { N, fps, state } = ctx;
    const { slider, number, playBtn, status } = play;

    function syncOthers() {
      series.moveCursor();
      flags.moveCursor();
      if (heat.followsFrame()) heat.draw();
    }

    // The other plots follow the frame once stepping pauses: redrawing a long run's raster on
    // every key repeat would make the 3D view lag.
    let syncTimer = null;
    function scheduleSync() {
      clearTimeout(syncTimer);
      syncTimer = setTimeout(syncOthers, 150);
    }

    function setFrame(n, fromPlayback) {
      n = Math.max(0, Math.min(N - 1, Math.round(Number(n) || 0)));
      state.frame = n;
      slider.value = String(n);
      if (document.activeElement !== number) number.value = String(n);
      play.plot3d.dataset.frame = String(n);
      scene.draw(n);
      if (hooks.onFrame) hooks.onFrame(n, !!fromPlayback);
      if (!fromPlayback) { play.describe(n); scheduleSync(); }
      else {
        play.showTime(n);
        const now = performance.now();
        if (now - state.lastSync > 400) { state.lastSync = now; syncOthers(); play.describe(n); }
      }
    }

    function tick(now) {
      if (!state.playing) return;
      const dt = (now - state.last) / 1000;
      state.last = now;
      state.acc += dt * fps * state.speed;
      if (state.acc >= 1) {
        const step = Math.floor(state.acc);
        state.acc -= step;
        setFrame((state.frame + step) % N, true);
      }
      requestAnimationFrame(tick);
    }

    function setPlaying(on) {
      state.playing = on && N > 1;
      playBtn.textContent = state.playing ? "❚❚ Pause" : "▶ Play";
      playBtn.setAttribute("aria-pressed", String(state.playing));
      status.setAttribute("aria-live", state.playing ? "off" : "polite");
      if (hooks.onPlaying) hooks.onPlaying(state.playing, state.speed);
      if (state.playing) { state.last = performance.now(); state.acc = 0; requestAnimationFrame(tick); }
      else play.describe(state.frame);
    }

    playBtn.addEventListener("click", () => setPlaying(!state.playing));
    play.prevBtn.addEventListener("click", () => { setPlaying(false); setFrame(state.frame - 1); });
    play.nextBtn.addEventListener("click", () => { setPlaying(false); setFrame(state.frame + 1); });
    slider.addEventListener("input", () => { setPlaying(false); setFrame(slider.value); });
    number.addEventListener("change", () => { setPlaying(false); setFrame(number.value); });
    play.speed.addEventListener("change", () => {
      state.speed = Number(play.speed.value);
      if (hooks.onPlaying && state.playing) hooks.onPlaying(true, state.speed);
    });
    play.view.addEventListener("change", () => {
      state.view = play.view.value;
      scene.reframe();
    });
    play.section.addEventListener("keydown", (ev) => {
      const t = ev.target;
      if (t.tagName === "INPUT" || t.tagName === "SELECT" || t.tagName === "TEXTAREA") return;
      if (ev.key === " " && t.tagName !== "BUTTON") { ev.preventDefault(); setPlaying(!state.playing); }
      else if (ev.key === "ArrowLeft") { ev.preventDefault(); setPlaying(false); setFrame(state.frame - 1); }
      else if (ev.key === "ArrowRight") { ev.preventDefault(); setPlaying(false); setFrame(state.frame + 1); }
      else if (ev.key === "Home") { ev.preventDefault(); setFrame(0); }
      else if (ev.key === "End") { ev.preventDefault(); setFrame(N - 1); }
    });
    play.plot3d.tabIndex = 0;
    play.plot3d.setAttribute("aria-describedby", status.id = newId("status"));

    return { setFrame, setPlaying };
  }

  // ------------------------------------------------------------------ the whole view

  function render(container, P, opts) {
    opts = opts || {};
    container.replaceChildren();
    if (!P || !Array.isArray(P.positions) || !Array.isArray(P.markers)) {
      container.append(el("p", { class: "notice", text: "This result holds no 3D positions to draw." }));
      return null;
    }
    fillGaps(P);
    const ctx = context(P);
    // The panels' clicks go through the frame control, made last (it drives them all).
    let control = null;
    const setFrame = (n) => control.setFrame(n);

    container.append(summaryPanel(ctx));
    const body = bodyAndClocksPanel(ctx);
    if (body) container.append(body);
    const play = playbackPanel(ctx);
    container.append(play.section);
    const scene = skeletonScene(ctx, play.plot3d);
    const heat = errorPanel(ctx, (m) => series.showMarker(m));
    container.append(heat.section);
    const series = seriesPanel(ctx, setFrame);
    container.append(series.section);
    const flags = flagsPanel(ctx, setFrame, (n) => { setFrame(n); play.plot3d.scrollIntoView({ block: "center" }); });
    container.append(flags.section);
    control = frameControl(ctx, play, scene, heat, series, flags,
      { onFrame: opts.onFrame || null, onPlaying: opts.onPlaying || null });

    let firstFrame = 0;
    for (let n = 0; n < ctx.N; n++) if (P.positions[n].some(seen)) { firstFrame = n; break; }
    heat.draw();
    series.draw();
    flags.drawRaster();
    scene.ready.then(() => { control.setFrame(firstFrame); container.dataset.ready = "true"; });

    return { setFrame: control.setFrame, play: () => control.setPlaying(true), pause: () => control.setPlaying(false),
      state: ctx.state, playbackSection: play.section };
  }

  window.AcinoResultView = { render };
})();

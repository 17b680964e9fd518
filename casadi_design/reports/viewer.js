/* The script of viewer.html (casadi_design/reports/viewer.py): draws the data of
 * <script id="viewer-data"> with plotly.js, one pose at a time. It computes nothing of the
 * package's: it applies the placements Pinocchio gave each object in each frame (3 x 4,
 * row-major) to the object's triangles, and shows the numbers as they are.
 *
 * The page's address may end with #view=V&pose=P (1-based), &hide=robot,tool (groups of
 * traces hidden), &zoom=Z (the camera Z times closer) and &check (step through every pose of every view and write a report in
 * <pre id="status">: what the tests read).
 */
"use strict";
(function () {
  const D = JSON.parse(document.getElementById("viewer-data").textContent);
  const G = D.geometry;
  const $ = (id) => document.getElementById(id);
  const plot = $("plot"), panel = $("panel"), slider = $("slider"), select = $("view"), playButton = $("play");
  const status = $("status");

  function bytes(b64) {
    const s = atob(b64), out = new Uint8Array(s.length);
    for (let i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
    return out.buffer;
  }
  const f32 = (b) => new Float32Array(bytes(b));  // little-endian, as every browser's machine
  const u16 = (b) => new Uint16Array(bytes(b));
  const u32 = (b) => new Uint32Array(bytes(b));
  const esc = (s) => String(s).replace(/&/g, "&amp;").replace(/</g, "&lt;");
  const fmt = (v, d) => (v === null || v === undefined || !isFinite(v) ? "-" : Number(v).toFixed(d));

  const nObjects = G.objects.length;
  const meshes = G.traces.map(function (t) {
    const F = u32(t.faces), n = F.length / 3;
    const i = new Int32Array(n), j = new Int32Array(n), k = new Int32Array(n);
    for (let a = 0; a < n; a++) { i[a] = F[3 * a]; j[a] = F[3 * a + 1]; k[a] = F[3 * a + 2]; }
    return Object.assign({}, t, { V: f32(t.vertices), obj: u16(t.objects), i: i, j: j, k: k });
  });
  const views = D.views;
  for (const v of views) {
    v.P = f32(v.frames.placements);
    v.S = f32(v.frames.sticks);
    v.R = f32(v.frames.points);
  }
  const lo = G.bounds_m[0], hi = G.bounds_m[1];
  const span = [0, 1, 2].map((a) => hi[a] - lo[a]), size = Math.max.apply(null, span);
  let cmin = Infinity, cmax = -Infinity, maxLoad = 0;
  for (const v of views) {
    for (const r of v.rms_mm || []) if (r !== null) { cmin = Math.min(cmin, r); cmax = Math.max(cmax, r); }
    for (const p of v.poses) if (p.arrow) maxLoad = Math.max(maxLoad, Math.hypot.apply(null, p.arrow[1]));
  }

  const params = new URLSearchParams(location.hash.slice(1));
  const hidden = new Set((params.get("hide") || "").split(",").filter(Boolean));
  const state = { view: 0, pose: 0, frame: null, playing: false, timer: null };
  state.view = Math.min(Math.max((parseInt(params.get("view"), 10) || 1) - 1, 0), views.length - 1);
  state.pose = Math.min(Math.max((parseInt(params.get("pose"), 10) || 1) - 1, 0), views[state.view].poses.length - 1);

  /* x, y, z of a mesh trace's vertices in frame f of view v */
  function placed(m, v, f) {
    const n = m.obj.length, x = new Float32Array(n), y = new Float32Array(n), z = new Float32Array(n);
    const P = v.P, V = m.V, base = f * nObjects * 12;
    for (let a = 0; a < n; a++) {
      const o = base + m.obj[a] * 12, vx = V[3 * a], vy = V[3 * a + 1], vz = V[3 * a + 2];
      x[a] = P[o] * vx + P[o + 1] * vy + P[o + 2] * vz + P[o + 3];
      y[a] = P[o + 4] * vx + P[o + 5] * vy + P[o + 6] * vz + P[o + 7];
      z[a] = P[o + 8] * vx + P[o + 9] * vy + P[o + 10] * vz + P[o + 11];
    }
    return { x: x, y: y, z: z };
  }

  function framePoints(v, f) {  // the reflectors in frame f: [[x, y, z], ...]
    const k = v.frames.points_per_frame, out = [];
    for (let a = 0; a < k; a++) out.push([0, 1, 2].map((c) => v.R[(f * k + a) * 3 + c]));
    return out;
  }

  function columns(points) {  // [[x, y, z], null, ...] -> {x, y, z} with gaps
    const x = [], y = [], z = [];
    for (const p of points) { x.push(p ? p[0] : null); y.push(p ? p[1] : null); z.push(p ? p[2] : null); }
    return { x: x, y: y, z: z };
  }

  const lighting = { ambient: 0.5, diffuse: 0.75, specular: 0.15, roughness: 0.6, fresnel: 0.1 };

  function traces() {
    const v = views[state.view], pose = v.poses[state.pose];
    const f = state.frame === null ? pose.frame : state.frame, atPose = state.frame === null || state.frame === pose.frame;
    const out = [];
    for (const m of meshes) {
      const p = placed(m, v, f);
      out.push({ type: "mesh3d", uid: "mesh-" + m.group, name: m.name, x: p.x, y: p.y, z: p.z, i: m.i, j: m.j, k: m.k,
                 color: m.colour, opacity: m.opacity, flatshading: false, lighting: lighting,
                 lightposition: { x: 20000, y: -40000, z: 60000 }, hoverinfo: "name", showlegend: true,
                 visible: hidden.has(m.group) ? false : m.visible });
    }
    if (G.sticks) {
      const k = v.frames.sticks_per_frame, pts = [];
      for (let a = 0; a < k; a++) pts.push([0, 1, 2].map((c) => v.S[(f * k + a) * 3 + c]));
      out.push(Object.assign({ type: "scatter3d", uid: "mesh-robot", name: "robot (joint origins)", mode: "lines+markers",
                               line: { color: "#4a5a6a", width: 10 }, marker: { size: 4, color: "#1f2b36" },
                               hoverinfo: "name", visible: !hidden.has("robot") }, columns(pts)));
    }
    G.static.forEach(function (s, a) {
      const c = columns(s.vertices);
      out.push({ type: "mesh3d", uid: "static-" + a, name: s.name, x: c.x, y: c.y, z: c.z,
                 i: s.faces.map((t) => t[0]), j: s.faces.map((t) => t[1]), k: s.faces.map((t) => t[2]),
                 color: "#8a8a8a", opacity: 0.45, lighting: lighting, hoverinfo: "name", visible: !hidden.has("cell") });
    });
    if (G.floor_z_m !== null) {
      const z = G.floor_z_m;
      out.push({ type: "mesh3d", uid: "floor", name: "floor", x: [lo[0], hi[0], hi[0], lo[0]], y: [lo[1], lo[1], hi[1], hi[1]],
                 z: [z, z, z, z], i: [0, 0], j: [1, 2], k: [2, 3], color: "#d8d4cc", opacity: 0.5, hoverinfo: "skip",
                 visible: !hidden.has("cell") });
    }
    if (G.tracker_m) {
      out.push({ type: "scatter3d", uid: "tracker", name: "laser tracker", mode: "markers+text", x: [G.tracker_m[0]],
                 y: [G.tracker_m[1]], z: [G.tracker_m[2]], text: ["tracker"], textposition: "top center",
                 marker: { size: 7, color: "#111", symbol: "diamond" }, hoverinfo: "name" });
    }
    const tp = D.test_poses.position_m, rms = v.rms_mm || tp.map(() => null), c = columns(tp);
    const scale = { color: rms, colorscale: "Viridis", cmin: cmin, cmax: cmax };
    out.push(Object.assign({ type: "scatter3d", uid: "test-poses", name: v.rms_label ? "test poses (colour: " + v.rms_label + ")" : "test poses",
                             mode: D.test_poses.path ? "lines+markers" : "markers",
                             marker: Object.assign({ size: 4, showscale: isFinite(cmin),
                                                     colorbar: { title: { text: v.rms_label || "", side: "top" }, orientation: "h", thickness: 10,
                                                                 len: 0.35, x: 0.98, xanchor: "right", y: 0.02, yanchor: "bottom" } }, scale),
                             line: D.test_poses.path ? Object.assign({ width: 6 }, scale) : undefined,
                             text: tp.map((_, a) => "test pose " + (a + 1) + ": " + fmt(rms[a], 4) + " mm"), hoverinfo: "text" }, c));
    if (v.route) {  // the first measured point along the whole route
      const path = [];
      for (let g = 0; g < v.frames.count; g++) path.push(framePoints(v, g)[0]);
      out.push(Object.assign({ type: "scatter3d", uid: "route", name: "route (the " + D.point + "'s path)", mode: "lines",
                               line: { color: "#9467bd", width: 3 }, hoverinfo: "name" }, columns(path)));
    }
    // every pose's first reflector, numbered as in the plan; this frame's reflectors and beams
    const first = v.poses.map((p) => framePoints(v, p.frame)[0]), cf = columns(first);
    out.push(Object.assign({ type: "scatter3d", uid: "poses", name: "poses (numbers as in the plan)", mode: "markers+text",
                             text: v.poses.map((p) => String(p.number)), textposition: "top center", textfont: { size: 10, color: "#555" },
                             marker: { size: 3, color: "#777" }, hoverinfo: "text" }, cf));
    const refl = framePoints(v, f), cr = columns(refl);
    out.push(Object.assign({ type: "scatter3d", uid: "reflectors", name: D.point + (refl.length > 1 ? "s" : ""),
                             mode: "markers", marker: { size: 5, color: "#d62728" }, hoverinfo: "name" }, cr));
    if (G.tracker_m) {
      const beam = [];
      for (const p of refl) beam.push(G.tracker_m, p, null);
      out.push(Object.assign({ type: "scatter3d", uid: "beam", name: "tracker beam", mode: "lines",
                               line: { color: "#d62728", width: 3, dash: "dash" }, hoverinfo: "name" }, columns(beam)));
    }
    if (atPose && pose.arrow && maxLoad > 0) {
      const a = pose.arrow[0], F = pose.arrow[1], n = Math.hypot.apply(null, F), L = 0.18 * size * n / maxLoad;
      const tip = [0, 1, 2].map((c) => a[c] + L * F[c] / n);
      out.push(Object.assign({ type: "scatter3d", uid: "load", name: "load " + fmt(n, 0) + " N", mode: "lines",
                               line: { color: "#2ca02c", width: 7 }, hoverinfo: "name" }, columns([a, tip])));
      out.push({ type: "cone", uid: "load-tip", name: "load", x: [tip[0]], y: [tip[1]], z: [tip[2]],
                 u: [F[0] / n], v: [F[1] / n], w: [F[2] / n], anchor: "tip", sizemode: "absolute", sizeref: 0.04 * size,
                 colorscale: [[0, "#2ca02c"], [1, "#2ca02c"]], showscale: false, showlegend: false, hoverinfo: "skip" });
    }
    if (v.residuals) {
      const r = v.residuals, arrows = [];
      r.model_m.forEach(function (row, a) { row.forEach(function (p, b) { arrows.push(p, r.arrows_m[a][b], null); }); });
      out.push(Object.assign({ type: "scatter3d", uid: "measured", name: "measured points", mode: "markers",
                               marker: { size: 3, color: "#d62728" }, hoverinfo: "name" }, columns([].concat.apply([], r.measured_m))));
      out.push(Object.assign({ type: "scatter3d", uid: "model", name: "calibrated model's points", mode: "markers",
                               marker: { size: 3, color: "#1f77b4" }, hoverinfo: "name" }, columns([].concat.apply([], r.model_m))));
      out.push(Object.assign({ type: "scatter3d", uid: "residuals", name: r.text, mode: "lines",
                               line: { color: "#ff7f0e", width: 4 }, hoverinfo: "name" }, columns(arrows)));
      if (r.tracker_m) {
        out.push({ type: "scatter3d", uid: "tracker-identified", name: "tracker (identified)", mode: "markers",
                   x: [r.tracker_m[0]], y: [r.tracker_m[1]], z: [r.tracker_m[2]], marker: { size: 6, color: "#9467bd", symbol: "diamond" } });
      }
    }
    return out;
  }

  const layout = {
    uirevision: "keep", margin: { l: 0, r: 0, t: 0, b: 0 }, paper_bgcolor: "#fff",
    legend: { x: 0.0, y: 1.0, bgcolor: "rgba(255,255,255,0.75)", font: { size: 11 } },
    scene: {
      aspectmode: "manual", aspectratio: { x: span[0] / size, y: span[1] / size, z: span[2] / size },
      xaxis: { title: { text: "x (m)" }, range: [lo[0], hi[0]], showbackground: false },
      yaxis: { title: { text: "y (m)" }, range: [lo[1], hi[1]], showbackground: false },
      zaxis: { title: { text: "z (m)" }, range: [lo[2], hi[2]], showbackground: false },
      camera: span[2] < 0.25 * size  // a planar robot: seen from above
        ? { eye: { x: 0, y: -0.25, z: 1.6 }, center: { x: 0, y: 0, z: 0 }, up: { x: 0, y: 1, z: 0 } }
        : { eye: { x: 0.45, y: -1.3, z: 0.65 }, center: { x: 0, y: 0, z: -0.12 } },
    },
  };

  const zoom = parseFloat(params.get("zoom")) || 1;  // #zoom=2: the camera twice as close
  for (const c of ["x", "y", "z"]) layout.scene.camera.eye[c] /= zoom;

  function row(name, value) { return "<tr><td>" + esc(name) + "</td><td class=v>" + value + "</td></tr>"; }

  function describe() {
    const v = views[state.view], pose = v.poses[state.pose], n = v.poses.length, out = [];
    const what = v.kind === "identification" ? "line " + pose.number + " of the measurements" : "experiment " + pose.number;
    out.push("<h2>" + esc(what) + "</h2>");
    if (v.kind === "program") out.push("<div class=note>" + (state.pose + 1) + " of " + n + " in the program's order</div>");
    else if (v.kind === "plan") out.push("<div class=note>row " + (state.pose + 1) + " of " + n + " of " + esc(v.file) + (pose.measured ? " (measured before)" : "") + "</div>");
    if (pose.stop) out.push("<div class=warn>before it: " + esc(pose.stop) + "</div>");
    out.push("<table>");
    D.joints.forEach(function (j, a) { out.push(row(j.name, fmt(pose.q[a], 3) + " " + j.unit)); });
    out.push("</table>");
    out.push("<div>load: " + esc(pose.load_text) + "</div>");
    if (pose.clearance_mm !== null) {
      const low = D.clearance_mm !== null && pose.clearance_mm < D.clearance_mm - 1e-3;
      out.push("<div" + (low ? " class=warn" : "") + ">smallest clearance " + fmt(pose.clearance_mm, 1) + " mm, between " +
               esc(pose.closest) + " <span class=note>(" + esc(D.checked_on) + ")</span></div>");
    } else if (v.kind !== "identification") {
      out.push("<div class=note>no cell: no clearance</div>");
    }
    const f = state.frame === null ? pose.frame : state.frame;
    const refl = framePoints(v, f).map((p) => "(" + p.map((c) => fmt(1000 * c, 1)).join(", ") + ")");
    out.push("<div>" + D.point + (refl.length > 1 ? "s" : "") + " (mm): " + refl.join(" ") + "</div>");
    if (v.residuals) {
      out.push("<div>residual RMS " + fmt(pose.residual_rms_mm, 4) + " mm, max " + fmt(pose.residual_max_mm, 4) + " mm" +
               (pose.used ? "" : " <span class=warn>(outlier: not in the fit)</span>") + "</div>");
      out.push("<div class=note>" + esc(v.residuals.text) + "</div>");
    }
    if (v.route) {
      const moves = v.route.moves;
      let k = moves.findIndex((m) => f > m.start && f <= m.end);
      if (k < 0) k = moves.findIndex((m) => m.end === f);
      if (k >= 0) {
        const m = moves[k];
        out.push("<div>move " + (k + 1) + " of " + moves.length + ": " + esc(m.from) + " &rarr; " + esc(m.to) + ", " + m.vias +
                 " via point" + (m.vias === 1 ? "" : "s") + ", " + fmt(m.time_s, 1) + " s, clearance " + fmt(m.clearance_mm, 1) + " mm" +
                 (m.beam ? " <span class=warn>(beam broken: " + esc(m.beam) + ")</span>" : "") + "</div>");
      }
      out.push("<div class=note>program " + fmt(v.route.time_s, 1) + " s; order " + v.route.order.join(", ") + "</div>");
    }
    return out.join("\n");
  }

  function updateControls() {
    const v = views[state.view], pose = v.poses[state.pose];
    select.value = String(state.view);
    slider.max = String(v.poses.length);
    slider.value = String(state.pose + 1);
    $("which").textContent = (v.kind === "identification" ? "line " : "experiment ") + pose.number +
      " (" + (state.pose + 1) + " / " + v.poses.length + ")";
    playButton.hidden = !v.route;
    playButton.innerHTML = state.playing ? "&#9632; stop" : "&#9655; play the route";
  }

  function render() {
    updateControls();
    panel.innerHTML = describe();
    layout.width = plot.clientWidth;  // the page's size, not plotly's default
    layout.height = plot.clientHeight;
    return Plotly.react(plot, traces(), layout, { displaylogo: false }).then(function () {
      const v = views[state.view];
      status.textContent = JSON.stringify({ view: state.view + 1, pose: state.pose + 1, number: v.poses[state.pose].number,
                                            errors: window.viewerErrors });
      status.dataset.ready = "1";
    });
  }

  function stopPlaying() {
    if (state.timer) clearTimeout(state.timer);
    state.timer = null;
    state.playing = false;
    state.frame = null;
  }

  function show(view, pose) {
    stopPlaying();
    state.view = view;
    state.pose = Math.min(Math.max(pose, 0), views[view].poses.length - 1);
    return render();
  }

  function play() {
    const v = views[state.view];
    if (state.playing) { stopPlaying(); render(); return; }
    if (!v.route) return;
    state.playing = true;
    const times = v.route.times_s, stops = new Map(v.poses.map((p, a) => [p.frame, a]));
    let f = 0;
    function step() {
      if (!state.playing) return;
      state.frame = f;
      if (stops.has(f)) state.pose = stops.get(f);
      render();
      if (f + 1 >= times.length) { state.playing = false; state.timer = null; updateControls(); return; }
      const wait = 1000 * (times[f + 1] - times[f]) + (stops.has(f) ? 700 : 0);
      f += 1;
      state.timer = setTimeout(step, wait);
    }
    step();
  }

  $("title").textContent = D.title;
  views.forEach(function (v, a) {
    const o = document.createElement("option");
    o.value = String(a);
    o.textContent = v.label;
    select.appendChild(o);
  });
  select.addEventListener("change", () => show(parseInt(select.value, 10), 0));
  slider.addEventListener("input", () => show(state.view, parseInt(slider.value, 10) - 1));
  $("prev").addEventListener("click", () => show(state.view, state.pose - 1));
  $("next").addEventListener("click", () => show(state.view, state.pose + 1));
  playButton.addEventListener("click", play);
  window.addEventListener("resize", () => { if (!state.playing) render(); });
  document.addEventListener("keydown", function (e) {
    if (e.target === select || e.target === slider) return;  // (they step on their own)
    if (e.key === "ArrowLeft") show(state.view, state.pose - 1);
    if (e.key === "ArrowRight") show(state.view, state.pose + 1);
  });

  /* what a test reads: every pose of every view drawn, the robot's vertices finite and
   * different from one pose to the next */
  async function check() {
    const report = { views: [] };
    for (let a = 0; a < views.length; a++) {
      const keys = [];
      let finite = true, drawn = true;
      for (let b = 0; b < views[a].poses.length; b++) {
        await show(a, b);
        const robot = plot.data.filter((t) => t.uid === "mesh-robot");
        let sum = 0, count = 0;
        for (const t of robot) {
          for (const c of [t.x, t.y, t.z]) {
            for (let e = 0; e < c.length; e++) { if (!isFinite(c[e])) finite = false; sum += (e % 7 + 1) * c[e]; count += 1; }
          }
        }
        drawn = drawn && count > 0 && plot.querySelector("canvas") !== null;
        keys.push(sum.toFixed(6));
      }
      let frames = 0;  // a route: every frame of its moves placed, 20 of them drawn
      const count = views[a].route ? views[a].frames.count : 0, stride = Math.max(1, Math.ceil(count / 20));
      for (let f = 0; f < count; f++) {
        state.frame = f;
        if (f % stride === 0 || f === count - 1) await render();
        const robot = traces().filter((t) => t.uid === "mesh-robot");
        frames += robot.length > 0 && robot.every((t) => t.x.length > 0 && Array.prototype.every.call(t.x, isFinite)) ? 1 : 0;
      }
      state.frame = null;
      report.views.push({ label: views[a].label, kind: views[a].kind, poses: views[a].poses.length, shown: keys.length,
                          distinct: new Set(keys).size, finite: finite, drawn: drawn,
                          frames: views[a].frames.count, frames_shown: frames });
    }
    report.errors = window.viewerErrors;
    status.textContent = JSON.stringify(report);
    status.dataset.check = "done";
    return report;
  }

  /* for a test's browser: viewer.show(view, pose, hide) (1-based; hide: groups of traces),
   * viewer.check() */
  window.viewer = {
    show: function (view, pose, hide) {
      hidden.clear();
      for (const g of hide || []) hidden.add(g);
      return show(view - 1, pose - 1);
    },
    check: check,
  };

  render().then(function () { if (params.has("check")) return check(); }).catch(function (e) {
    window.viewerErrors.push(String(e && e.stack || e));
    status.textContent = JSON.stringify({ errors: window.viewerErrors });
  });
  window.addEventListener("error", function () {
    const box = $("errors");
    box.hidden = false;
    box.textContent = window.viewerErrors.join("\n");
  });
})();

// The report's 3D view of a run's cameras: an orbit view drawn on a 2D canvas, with no library.
// Drag to turn, wheel to zoom, click a camera to see what it is; the slider picks the round
// whose scores colour the candidates. window.cameraView exposes what is drawn.
(function () {
  "use strict";
  const root = document.getElementById("camera-view");
  const source = document.getElementById("camera-data");
  if (!root || !source) return;
  const data = JSON.parse(source.textContent);
  const canvas = root.querySelector("canvas");
  const ctx = canvas.getContext("2d");
  const controls = root.querySelector(".controls");
  const info = root.querySelector(".info");

  const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const mul = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];

  const all = data.corners.concat(data.candidates.map((c) => c.p), data.heldout.map((c) => c.p));
  const lo = [0, 1, 2].map((k) => Math.min(...all.map((p) => p[k])));
  const hi = [0, 1, 2].map((k) => Math.max(...all.map((p) => p[k])));
  const centre = mul(add(lo, hi), 0.5);
  const radius = Math.max(1e-9, 0.5 * Math.hypot(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]));
  const size = 0.1 * radius;  // frustum depth
  const BOX = [[0, 1], [0, 2], [0, 4], [1, 3], [1, 5], [2, 3], [2, 6], [3, 7], [4, 5], [4, 6], [5, 7], [6, 7]];
  const VIRIDIS = [[68, 1, 84], [59, 82, 139], [33, 145, 140], [94, 201, 98], [253, 231, 37]];

  const state = { yaw: 0.7, pitch: 0.35, zoom: 1, round: data.rounds.length - 1, selected: null };
  const images = data.captured.map((_, n) => document.getElementById("view-" + n));
  const view = { data: data, objects: [], state: state };
  window.cameraView = view;

  function colour(t) {
    if (t === null) return "rgb(190,190,190)";
    const x = Math.min(Math.max(t, 0), 1) * (VIRIDIS.length - 1);
    const i = Math.min(Math.floor(x), VIRIDIS.length - 2), f = x - i;
    const c = VIRIDIS[i].map((v, k) => Math.round(v + f * (VIRIDIS[i + 1][k] - v)));
    return "rgb(" + c.join(",") + ")";
  }

  function eye() {
    const cy = Math.cos(state.yaw), sy = Math.sin(state.yaw), cp = Math.cos(state.pitch), sp = Math.sin(state.pitch);
    const dir = [cp * cy, cp * sy, sp];
    const right = [-sy, cy, 0];
    const up = [-sp * cy, -sp * sy, cp];
    return { pos: add(centre, mul(dir, 2.3 * radius / state.zoom)), dir: dir, right: right, up: up };
  }

  function projector() {
    const e = eye(), f = 0.5 * canvas.height / Math.tan(0.35);
    return function (p) {
      const d = sub(p, e.pos), z = -dot(d, e.dir);
      if (z <= 1e-6 * radius) return null;
      return [0.5 * canvas.width + f * dot(d, e.right) / z, 0.5 * canvas.height - f * dot(d, e.up) / z, z];
    };
  }

  // The frustum's apex and far corners (top-left, top-right, bottom-right, bottom-left of its image).
  function frustum(cam, scale) {
    const tx = Math.tan(cam.fov * Math.PI / 360), ty = tx * cam.aspect, s = size * scale;
    const at = (u, v) => add(cam.p, mul(add(cam.fwd, add(mul(cam.left, u * tx), mul(cam.up, v * ty))), s));
    return [cam.p, at(1, 1), at(-1, 1), at(-1, -1), at(1, -1)];
  }

  function roundScores() {
    const r = data.rounds[state.round];
    if (!r || !r.scores) return null;
    const finite = r.scores.filter((s) => s !== null && isFinite(s));
    if (!finite.length) return null;
    const a = Math.min(...finite), b = Math.max(...finite);
    return { raw: r.scores, min: a, max: b, t: r.scores.map((s) => (s === null ? null : b > a ? (s - a) / (b - a) : 0.5)) };
  }

  function shownCaptures() {
    const r = data.rounds[state.round];
    return r ? r.views : data.captured.length;
  }

  function draw() {
    const project = projector();
    const scores = roundScores();
    const picks = new Set(data.rounds[state.round] ? data.rounds[state.round].picks : []);
    const items = [], objects = [];
    const push = (kind, index, cam, scale, colourText, extra) => {
      const pts = frustum(cam, scale).map(project);
      if (pts.some((p) => p === null)) return;
      const depth = pts.reduce((s, p) => s + p[2], 0) / pts.length;
      const obj = Object.assign({ kind: kind, index: index, x: pts[0][0], y: pts[0][1] }, extra || {});
      objects.push(obj);
      items.push({ depth: depth, pts: pts, colour: colourText, obj: obj });
    };
    data.candidates.forEach((cam, i) => push("candidate", i, cam, 0.6, colour(scores ? scores.t[i] : null),
      { score: scores ? scores.raw[i] : null, picked: picks.has(i) }));
    data.heldout.forEach((cam, i) => push("heldout", i, cam, 0.8, "rgb(30,110,220)"));
    const n = shownCaptures();
    for (let k = 0; k < n; k++) {
      push("captured", k, data.candidates[data.captured[k]], 1.4, k < data.initial ? "rgb(200,90,0)" : "rgb(220,30,30)",
        { candidate: data.captured[k] });
    }
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.clearRect(0, 0, canvas.width, canvas.height);
    ctx.fillStyle = "#fbfbfb";
    ctx.fillRect(0, 0, canvas.width, canvas.height);
    const corners = data.corners.map(project);
    ctx.strokeStyle = "#999";
    ctx.lineWidth = 1;
    BOX.forEach(([a, b]) => {
      if (corners[a] && corners[b]) line(corners[a], corners[b]);
    });
    items.sort((a, b) => b.depth - a.depth);
    items.forEach(drawItem);
    // The path between captured views, in capture order, numbered: the route a moving camera took where
    // the record has it, else a straight line.
    const path = [], routes = data.routes || [];
    let drawnRoutes = 0;
    for (let k = 0; k < n; k++) path.push(project(data.candidates[data.captured[k]].p));
    ctx.strokeStyle = "rgba(220,30,30,0.55)";
    ctx.lineWidth = 1.5;
    for (let k = 1; k < path.length; k++) {
      const route = routes[k] ? routes[k].map(project) : null;
      if (route && route.every((p) => p !== null)) {
        for (let j = 1; j < route.length; j++) line(route[j - 1], route[j]);
        drawnRoutes++;
      } else if (path[k - 1] && path[k]) line(path[k - 1], path[k]);
    }
    view.routes = drawnRoutes;
    ctx.font = "11px sans-serif";
    ctx.fillStyle = "#000";
    path.forEach((p, k) => { if (p) ctx.fillText(String(k), p[0] + 4, p[1] - 4); });
    view.objects = objects;
  }

  function line(a, b) {
    ctx.beginPath();
    ctx.moveTo(a[0], a[1]);
    ctx.lineTo(b[0], b[1]);
    ctx.stroke();
  }

  function drawItem(item) {
    const p = item.pts, obj = item.obj;
    const img = obj.kind === "captured" ? images[obj.index] : null;
    if (img && img.complete && img.naturalWidth) {
      // An affine map of the image onto its frustum's far face.
      const w = img.naturalWidth, h = img.naturalHeight;
      ctx.setTransform((p[2][0] - p[1][0]) / w, (p[2][1] - p[1][1]) / w, (p[4][0] - p[1][0]) / h,
        (p[4][1] - p[1][1]) / h, p[1][0], p[1][1]);
      ctx.drawImage(img, 0, 0);
      ctx.setTransform(1, 0, 0, 1, 0, 0);
    } else if (obj.kind === "candidate") {
      ctx.fillStyle = item.colour;
      ctx.globalAlpha = 0.5;
      ctx.beginPath();
      [1, 2, 3, 4].forEach((k) => ctx.lineTo(p[k][0], p[k][1]));
      ctx.fill();
      ctx.globalAlpha = 1;
    }
    ctx.strokeStyle = item.colour;
    ctx.lineWidth = obj.kind === "captured" || obj === state.selected ? 2 : 1;
    [1, 2, 3, 4].forEach((k) => line(p[0], p[k]));
    [[1, 2], [2, 3], [3, 4], [4, 1]].forEach(([a, b]) => line(p[a], p[b]));
    if (obj.picked) {
      ctx.beginPath();
      ctx.arc(p[0][0], p[0][1], 6, 0, 2 * Math.PI);
      ctx.stroke();
    }
  }

  function describe(obj) {
    const r = data.rounds[state.round];
    const fmt = (s) => (s === null || s === undefined ? "none" : Number(s).toPrecision(4));
    if (obj.kind === "captured") {
      const img = images[obj.index];
      info.innerHTML = "";
      info.append("capture #" + obj.index + ": candidate " + obj.candidate + (obj.index < data.initial ? " (initial, random)" : ""));
      if (img) info.append(img.cloneNode());
    } else if (obj.kind === "candidate") {
      info.textContent = "candidate " + obj.index + ": score " + fmt(obj.score) +
        (r ? " in round " + (state.round + 1) : "") + (obj.picked ? ", picked in that round" : "");
    } else {
      info.textContent = "held-out view " + obj.index;
    }
  }

  if (data.rounds.length) {
    const label = document.createElement("span");
    const slider = document.createElement("input");
    slider.type = "range";
    slider.min = 0;
    slider.max = data.rounds.length - 1;
    slider.value = state.round;
    const legend = document.createElement("span");
    const update = () => {
      state.round = Number(slider.value);
      const r = data.rounds[state.round], s = roundScores();
      label.textContent = "round " + (state.round + 1) + " of " + data.rounds.length + ": picked " + r.picks.join(", ") +
        " (views " + (r.views - r.picks.length + 1) + (r.picks.length > 1 ? "-" + r.views : "") + ")";
      legend.innerHTML = s ? "score " + s.min.toPrecision(3) + ' <span class="legend"></span> ' + s.max.toPrecision(3)
        : "no scores this round";
      draw();
    };
    slider.addEventListener("input", update);
    controls.append(slider, label, legend);
    view.setRound = (k) => { slider.value = k; update(); };
    update();
  } else {
    controls.textContent = "no planning rounds: every view was an initial, random one";
    draw();
  }

  let drag = null;
  canvas.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY, moved: false };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    const dx = e.clientX - drag.x, dy = e.clientY - drag.y;
    if (Math.abs(dx) + Math.abs(dy) > 2) drag.moved = true;
    state.yaw -= dx * 0.01;
    state.pitch = Math.max(-1.5, Math.min(1.5, state.pitch + dy * 0.01));
    drag.x = e.clientX;
    drag.y = e.clientY;
    draw();
  });
  canvas.addEventListener("pointerup", (e) => {
    if (drag && !drag.moved) {
      const box = canvas.getBoundingClientRect();
      const x = (e.clientX - box.left) * canvas.width / box.width, y = (e.clientY - box.top) * canvas.height / box.height;
      let best = null, bestD = 100;
      view.objects.forEach((o) => {
        const d = (o.x - x) ** 2 + (o.y - y) ** 2;
        if (d < bestD) { best = o; bestD = d; }
      });
      state.selected = best;
      if (best) describe(best);
      draw();
    }
    drag = null;
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    state.zoom = Math.max(0.3, Math.min(8, state.zoom * Math.exp(-e.deltaY * 0.001)));
    draw();
  }, { passive: false });
  images.forEach((img) => img && img.addEventListener("load", draw));
  view.draw = draw;
})();

// ps-lab view, part 2 of 2: relight, layers, 3-D and compare for ps-lab results, in plain WebGL 2
// (shaders and helpers: render.js).
// Data (see ps_lab/view/tiles.py): data/manifest.json, half-float RGBA tiles per pyramid level
// (nx, ny, nz, albedo | outliers, error, relief, depth), mesh buffers. No network beyond the
// folder the page comes from.
"use strict";

const MODES = { relight: 0, normal: 1, albedo: 2, outliers: 3, error: 4, relief: 5 };
const BACKGROUND = [0.125, 0.129, 0.141];

const state = {
  mode: "relight",          // relight | layers | mesh
  layer: "normal",
  light: [-0.5, 0.5, Math.SQRT1_2],   // toward the light: x right, y up, z toward the camera
  raking: false,
  elevation: 10,            // degrees, raking mode
  useAlbedo: true,
  appearance: true,         // relight with the fitted appearance model where a result has one
  exposure: 1,
  errorMax: 30,
  view: { cx: 0.5, cy: 0.5, zoom: 1 },   // shared by all panels: centre (fraction), zoom over fit
  orbit: { yaw: 0, pitch: 0, zoom: 1 },
};
const stats = { frames: 0, tilesDrawn: 0, tilesLoaded: 0, pending: 0, meshTriangles: 0, glError: 0, drawMs: 0, fullMs: 0, reduction: 1, refined: true, tileRetries: 0, tilesFailed: 0 };
// A tile whose fetch fails (a keep-alive connection the server closed as it was reused, a
// busy server) is asked for again by the next frame, up to this many times.
const TILE_ATTEMPTS = 3;
// While the light or the view moves, frames that took longer than this are drawn at a lower
// resolution (1/f per axis, then scaled up); the full resolution follows REFINE_MS after the
// last change.
const INTERACTIVE_MS = 30, REFINE_MS = 150;

const canvas = document.getElementById("gl");
const gl = canvas.getContext("webgl2", { antialias: false, preserveDrawingBuffer: false });
let results = [];
let dirty = true;
let lastChange = 0;
const lastFrame = { at: 0, f: 1, moving: false };
let reduced = null;     // { fbo, colour, depth, width, height } for reduced-resolution frames

let imageProgram, meshProgram, quad;

function setupGL() {
  imageProgram = program(gl, IMAGE_VS, IMAGE_FS);
  meshProgram = program(gl, MESH_VS, MESH_FS);
  quad = gl.createVertexArray();
  gl.bindVertexArray(quad);
  const buffer = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([0, 0, 1, 0, 0, 1, 1, 1]), gl.STATIC_DRAW);
  const loc = gl.getAttribLocation(imageProgram.p, "a_corner");
  gl.enableVertexAttribArray(loc);
  gl.vertexAttribPointer(loc, 2, gl.FLOAT, false, 0, 0);
  gl.bindVertexArray(null);
}

// ---- tiles -------------------------------------------------------------------------------------
const MAX_FETCHES = 6;
let fetching = 0;
const queue = [];

function tileKey(r, level, col, row) { return `${r}/${level}/${col}_${row}`; }

function requestTile(r, level, col, row) {
  const result = results[r];
  const key = tileKey(r, level, col, row);
  if (result.tiles.has(key)) return result.tiles.get(key);
  const entry = { level, col, row, ready: false };
  result.tiles.set(key, entry);
  queue.push([r, entry]);
  pump();
  return entry;
}

function pump() {
  while (fetching < MAX_FETCHES && queue.length) {
    const [r, entry] = queue.shift();
    fetching++;
    stats.pending = fetching + queue.length;
    const get = (url) => fetch(url).then((response) => {
      if (!response.ok) throw new Error(`${response.status} ${response.url}`);
      return response.arrayBuffer();
    });
    const tail = `${entry.level}/${entry.col}_${entry.row}.bin`;
    // Colour results: the colour tile (normals, albedo R | G, B) comes with the layer tile.
    const fit = results[r].appearance;
    Promise.all([
      get(`data/r${r}/${tail}`),
      results[r].colour ? get(`data/r${r}/c/${tail}`) : null,
      fit && fit.planes ? get(`data/r${r}/a/${tail}`) : null,
    ])
      .then(([buffer, colour, coefficients]) => {
        if (colour) entry.colourTextures = textures(results[r], entry, colour);
        if (coefficients) entry.coefTexture = coefficientTexture(results[r], entry, coefficients, fit.planes);
        uploadTile(results[r], entry, buffer);
      })
      .catch((error) => {
        const key = tileKey(r, entry.level, entry.col, entry.row);
        const attempts = (results[r].failures.get(key) || 0) + 1;
        results[r].failures.set(key, attempts);
        if (attempts < TILE_ATTEMPTS) { results[r].tiles.delete(key); stats.tileRetries++; }
        else { stats.tilesFailed++; status(`tile failed: ${error.message}`); }
      })
      .finally(() => { fetching--; stats.pending = fetching + queue.length; pump(); redraw(); });
  }
}

function textures(result, entry, buffer) {
  const size = result.levels[entry.level], t = result.tile;
  const w = Math.min(t, size.width - entry.col * t), h = Math.min(t, size.height - entry.row * t);
  const halves = new Uint16Array(buffer);
  return [0, 1].map((plane) => {
    const texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA16F, w, h, 0, gl.RGBA, gl.HALF_FLOAT,
      halves.subarray(plane * w * h * 4, (plane + 1) * w * h * 4));
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, entry.level === 0 ? gl.NEAREST : gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    return texture;
  });
}

function coefficientTexture(result, entry, buffer, planes) {
  // planes of w x h RGBA16F stacked vertically: one texture, read with texelFetch
  const size = result.levels[entry.level], t = result.tile;
  const w = Math.min(t, size.width - entry.col * t), h = Math.min(t, size.height - entry.row * t);
  const texture = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, texture);
  gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
  gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA16F, w, h * planes, 0, gl.RGBA, gl.HALF_FLOAT, new Uint16Array(buffer));
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
  gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
  return texture;
}

function uploadTile(result, entry, buffer) {
  const size = result.levels[entry.level], t = result.tile;
  entry.w = Math.min(t, size.width - entry.col * t);
  entry.h = Math.min(t, size.height - entry.row * t);
  entry.data = new Uint16Array(buffer);
  entry.textures = textures(result, entry, buffer);
  entry.ready = true;
  stats.tilesLoaded++;
}

// ---- layout ------------------------------------------------------------------------------------
function panels(W = canvas.width, H = canvas.height) {
  const n = results.length;
  const cols = n <= 3 ? n : Math.ceil(Math.sqrt(n));
  const rows = Math.ceil(n / cols);
  const out = [];
  for (let i = 0; i < n; i++) {
    const c = i % cols, r = Math.floor(i / cols);
    const x0 = Math.floor((c * W) / cols), x1 = Math.floor(((c + 1) * W) / cols);
    const y0 = Math.floor((r * H) / rows), y1 = Math.floor(((r + 1) * H) / rows);
    out.push({ x: x0, y: y0, w: x1 - x0 - (c < cols - 1 ? 2 : 0), h: y1 - y0 - (r < rows - 1 ? 2 : 0) });
  }
  return out;
}

function transform(result, panel) {
  const fit = Math.min(panel.w / result.width, panel.h / result.height);
  const scale = fit * state.view.zoom;
  return {
    scale,
    center: [Math.round(state.view.cx * result.width), Math.round(state.view.cy * result.height)],
    origin: [Math.floor(panel.w / 2), Math.floor(panel.h / 2)],
  };
}

function imageToPanel(result, panel, x, y) {
  const t = transform(result, panel);
  return [t.origin[0] + (x - t.center[0]) * t.scale, t.origin[1] + (y - t.center[1]) * t.scale];
}

function panelToImage(result, panel, px, py) {
  const t = transform(result, panel);
  return [t.center[0] + (px - t.origin[0]) / t.scale, t.center[1] + (py - t.origin[1]) / t.scale];
}

// ---- drawing -----------------------------------------------------------------------------------
function resize() {
  const dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(canvas.clientWidth * dpr)), h = Math.max(1, Math.round(canvas.clientHeight * dpr));
  if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; dirty = true; }
}

function redraw() { dirty = true; lastChange = performance.now(); }

function reducedTarget(f) {
  const width = Math.ceil(canvas.width / f), height = Math.ceil(canvas.height / f);
  if (reduced && reduced.width === width && reduced.height === height) return reduced;
  if (reduced) { gl.deleteFramebuffer(reduced.fbo); gl.deleteTexture(reduced.colour); gl.deleteRenderbuffer(reduced.depth); }
  const colour = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, colour);
  gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA8, width, height);
  const depth = gl.createRenderbuffer();
  gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
  gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, width, height);
  const fbo = gl.createFramebuffer();
  gl.bindFramebuffer(gl.FRAMEBUFFER, fbo);
  gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, colour, 0);
  gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
  gl.bindFramebuffer(gl.FRAMEBUFFER, null);
  reduced = { fbo, colour, depth, width, height };
  return reduced;
}

function frame() {
  resize();
  const now = performance.now();
  const moving = now - lastChange < REFINE_MS;
  if (results.length && (dirty || (!stats.refined && !moving))) {
    dirty = false;
    // The time a full-resolution frame takes shows as the interval to the next one while things
    // move (WebGL work is asynchronous: the draw calls return long before the pixels exist).
    if (moving && lastFrame.moving && lastFrame.f === 1 && now - lastFrame.at < 1000) {
      const interval = now - lastFrame.at;
      stats.fullMs = stats.fullMs ? 0.5 * stats.fullMs + 0.5 * interval : interval;
    }
    // Reduce only while things move and only when full frames are slow (software WebGL, 4K).
    const f = moving && stats.fullMs > INTERACTIVE_MS
      ? Math.min(4, Math.ceil(Math.sqrt(stats.fullMs / 12))) : 1;
    const started = performance.now();
    if (f > 1) {
      const target = reducedTarget(f);
      gl.bindFramebuffer(gl.FRAMEBUFFER, target.fbo);
      draw(target.width, target.height);
      gl.bindFramebuffer(gl.READ_FRAMEBUFFER, target.fbo);
      gl.bindFramebuffer(gl.DRAW_FRAMEBUFFER, null);
      gl.blitFramebuffer(0, 0, target.width, target.height, 0, 0, canvas.width, canvas.height, gl.COLOR_BUFFER_BIT, gl.LINEAR);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    } else {
      draw(canvas.width, canvas.height);
    }
    stats.drawMs = performance.now() - started;
    Object.assign(lastFrame, { at: now, f, moving });
    stats.reduction = f;
    stats.refined = f === 1;
    stats.frames++;
    stats.glError = gl.getError();
    placeTitles(panels());
  }
  requestAnimationFrame(frame);
}

function lightVector() {
  if (!state.raking) return state.light;
  const [x, y] = state.light;
  const azimuth = Math.atan2(y, x), elevation = (state.elevation * Math.PI) / 180;
  return [Math.cos(elevation) * Math.cos(azimuth), Math.cos(elevation) * Math.sin(azimuth), Math.sin(elevation)];
}

function draw(W, H) {
  gl.disable(gl.SCISSOR_TEST);
  gl.viewport(0, 0, W, H);
  gl.clearColor(0.08, 0.08, 0.09, 1);
  gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  gl.enable(gl.SCISSOR_TEST);
  const layout = panels(W, H);
  let tiles = 0, triangles = 0;
  results.forEach((result, i) => {
    const panel = layout[i];
    const glY = H - panel.y - panel.h;
    gl.viewport(panel.x, glY, panel.w, panel.h);
    gl.scissor(panel.x, glY, panel.w, panel.h);
    gl.clearColor(...BACKGROUND, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    if (state.mode === "mesh") triangles += drawMesh(result, panel);
    else tiles += drawImage(result, panel);
  });
  gl.disable(gl.SCISSOR_TEST);
  stats.tilesDrawn = tiles;
  stats.meshTriangles = triangles;
}

function drawImage(result, panel) {
  const t = transform(result, panel);
  const top = result.levels.length - 1;
  // The level whose pixels are closest to (not smaller than) a screen pixel.
  const level = Math.max(0, Math.min(top, Math.floor(Math.log2(1 / t.scale))));
  const p = imageProgram;
  gl.useProgram(p.p);
  gl.bindVertexArray(quad);
  gl.uniform2f(p.u.u_center, t.center[0], t.center[1]);
  gl.uniform2f(p.u.u_origin, t.origin[0], t.origin[1]);
  gl.uniform2f(p.u.u_panel, panel.w, panel.h);
  gl.uniform1f(p.u.u_scale, t.scale);
  gl.uniform1i(p.u.u_mode, state.mode === "relight" ? 0 : MODES[state.layer]);
  gl.uniform3fv(p.u.u_light, lightVector());
  gl.uniform1f(p.u.u_exposure, state.exposure);
  gl.uniform1i(p.u.u_albedo, state.useAlbedo ? 1 : 0);
  gl.uniform1f(p.u.u_errmax, state.errorMax);
  gl.uniform3fv(p.u.u_bg, BACKGROUND);
  gl.uniform1i(p.u.u_a, 0);
  gl.uniform1i(p.u.u_b, 1);
  gl.uniform1i(p.u.u_c0, 2);
  gl.uniform1i(p.u.u_c1, 3);
  gl.uniform1i(p.u.u_colour, result.colour ? 1 : 0);
  const fit = appearanceUniforms(state.appearance ? result.appearance : null, lightVector());
  gl.uniform1i(p.u.u_model, fit.model);
  gl.uniform1i(p.u.u_terms, fit.terms);
  gl.uniform1fv(p.u["u_basis[0]"], fit.basis);
  gl.uniform1iv(p.u["u_kind[0]"], fit.kind);
  gl.uniform1fv(p.u["u_power[0]"], fit.power);
  gl.uniform1i(p.u.u_vis, fit.vis ? 1 : 0);
  gl.uniform3fv(p.u["u_rbf[0]"], fit.rbf);
  gl.uniform1i(p.u.u_shared, fit.shared ? 1 : 0);
  gl.uniform1i(p.u.u_srgb, fit.srgb ? 1 : 0);
  gl.uniform1f(p.u.u_gain, fit.gain);
  gl.uniform1i(p.u.u_coef, 4);
  // The tiles of that level over the panel; the one-tile top level is drawn under them until
  // they have all arrived.
  const visible = [];
  if (level < top) {
    const [x0, y0] = panelToImage(result, panel, 0, 0);
    const [x1, y1] = panelToImage(result, panel, panel.w, panel.h);
    const span = result.tile * 2 ** level, size = result.levels[level];
    const c0 = Math.max(0, Math.floor(x0 / span)), c1 = Math.min(size.cols - 1, Math.floor(x1 / span));
    const r0 = Math.max(0, Math.floor(y0 / span)), r1 = Math.min(size.rows - 1, Math.floor(y1 / span));
    for (let row = r0; row <= r1; row++) {
      for (let col = c0; col <= c1; col++) visible.push(requestTile(result.index, level, col, row));
    }
  }
  let drawn = 0;
  const base = requestTile(result.index, top, 0, 0);
  if (base.ready && !(visible.length && visible.every((entry) => entry.ready))) { drawTile(result, base); drawn++; }
  for (const entry of visible) if (entry.ready) { drawTile(result, entry); drawn++; }
  return drawn;
}

function drawTile(result, entry) {
  const p = imageProgram, f = 2 ** entry.level, t = result.tile;
  // A level's last pixel may stand for fewer than 2^level level-0 pixels: clamp to the image.
  const x = entry.col * t * f, y = entry.row * t * f;
  gl.uniform4f(p.u.u_rect, x, y, entry.w * f, entry.h * f);
  gl.uniform2i(p.u.u_tsize, entry.w, entry.h);
  gl.activeTexture(gl.TEXTURE4);
  gl.bindTexture(gl.TEXTURE_2D, entry.coefTexture || null);
  gl.activeTexture(gl.TEXTURE0);
  gl.bindTexture(gl.TEXTURE_2D, entry.textures[0]);
  gl.activeTexture(gl.TEXTURE1);
  gl.bindTexture(gl.TEXTURE_2D, entry.textures[1]);
  const colour = entry.colourTextures || entry.textures;
  gl.activeTexture(gl.TEXTURE2);
  gl.bindTexture(gl.TEXTURE_2D, colour[0]);
  gl.activeTexture(gl.TEXTURE3);
  gl.bindTexture(gl.TEXTURE_2D, colour[1]);
  gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
}

// ---- 3-D ---------------------------------------------------------------------------------------
function loadMesh(result) {
  if (result.meshState) return result.meshState;
  result.meshState = { ready: false };
  fetch(`data/r${result.index}/mesh.bin`)
    .then((response) => { if (!response.ok) throw new Error(`${response.status}`); return response.arrayBuffer(); })
    .then((buffer) => {
      const v = result.mesh.vertices, t = result.mesh.triangles;
      const vao = gl.createVertexArray();
      gl.bindVertexArray(vao);
      const attribute = (name, offset, size, type, normalised, stride) => {
        const buf = gl.createBuffer();
        gl.bindBuffer(gl.ARRAY_BUFFER, buf);
        const bytes = stride * v;
        gl.bufferData(gl.ARRAY_BUFFER, new Uint8Array(buffer, offset, bytes), gl.STATIC_DRAW);
        const loc = gl.getAttribLocation(meshProgram.p, name);
        gl.enableVertexAttribArray(loc);
        gl.vertexAttribPointer(loc, size, type, normalised, stride, 0);
      };
      attribute("a_position", 0, 3, gl.FLOAT, false, 12);
      attribute("a_normal", 12 * v, 3, gl.FLOAT, false, 12);
      attribute("a_colour", 24 * v + 12 * t, 4, gl.UNSIGNED_BYTE, true, 4);
      const index = gl.createBuffer();
      gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, index);
      gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, new Uint32Array(buffer, 24 * v, 3 * t), gl.STATIC_DRAW);
      gl.bindVertexArray(null);
      Object.assign(result.meshState, { ready: true, vao, count: 3 * t });
    })
    .catch((error) => status(`mesh failed: ${error.message}`))
    .finally(redraw);
  return result.meshState;
}

function meshMatrix(result, panel) {
  const m = result.mesh;
  const centre = [0, 1, 2].map((k) => (m.min[k] + m.max[k]) / 2);
  const radius = Math.max(1e-6, Math.hypot(...[0, 1, 2].map((k) => m.max[k] - m.min[k])) / 2);
  const fov = (35 * Math.PI) / 180, aspect = panel.w / panel.h;
  const distance = radius / Math.sin(fov / 2) / state.orbit.zoom;
  const f = 1 / Math.tan(fov / 2), near = Math.max(distance - 2 * radius, distance * 0.01), far = distance + 2 * radius;
  const projection = new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) / (near - far), -1, 0, 0, (2 * far * near) / (near - far), 0]);
  const cy = Math.cos(state.orbit.yaw), sy = Math.sin(state.orbit.yaw);
  const cp = Math.cos(state.orbit.pitch), sp = Math.sin(state.orbit.pitch);
  // Column-major: translate(-centre), rotate about y (yaw) then x (pitch), push back by distance.
  const yaw = new Float32Array([cy, 0, -sy, 0, 0, 1, 0, 0, sy, 0, cy, 0, 0, 0, 0, 1]);
  const pitch = new Float32Array([1, 0, 0, 0, 0, cp, sp, 0, 0, -sp, cp, 0, 0, 0, 0, 1]);
  const move = new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, -centre[0], -centre[1], -centre[2], 1]);
  const back = new Float32Array([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, -distance, 1]);
  return multiply(projection, multiply(back, multiply(pitch, multiply(yaw, move))));
}

function drawMesh(result, panel) {
  if (!result.mesh) return 0;
  const mesh = loadMesh(result);
  if (!mesh.ready) return 0;
  const p = meshProgram;
  gl.enable(gl.DEPTH_TEST);
  gl.useProgram(p.p);
  gl.uniformMatrix4fv(p.u.u_mvp, false, meshMatrix(result, panel));
  gl.uniform3fv(p.u.u_light, lightVector());
  gl.uniform1i(p.u.u_albedo, state.useAlbedo ? 1 : 0);
  gl.uniform1f(p.u.u_exposure, state.exposure);
  gl.bindVertexArray(mesh.vao);
  gl.drawElements(gl.TRIANGLES, mesh.count, gl.UNSIGNED_INT, 0);
  gl.bindVertexArray(null);
  gl.disable(gl.DEPTH_TEST);
  return mesh.count / 3;
}

// ---- titles, probe, light widget ---------------------------------------------------------------
function placeTitles(layout) {
  const box = document.getElementById("titles");
  const dpr = window.devicePixelRatio || 1;
  if (box.children.length !== results.length) {
    box.innerHTML = "";
    results.forEach(() => box.appendChild(document.createElement("div")));
  }
  results.forEach((result, i) => {
    const div = box.children[i];
    const error = result.angular_error_deg ? `, mean error ${result.angular_error_deg.mean.toFixed(2)}°` : "";
    const missing = state.mode === "mesh" && !result.mesh ? " - no mesh.ply (ps-lab integrate makes one)" : "";
    div.textContent = `${result.name}${result.method ? ` (${result.method}${error})` : ""}${missing}`;
    div.style.left = `${layout[i].x / dpr}px`;
    div.style.top = `${layout[i].y / dpr}px`;
  });
}

function probeAt(result, x, y) {
  const ix = Math.floor(x), iy = Math.floor(y);
  if (ix < 0 || iy < 0 || ix >= result.width || iy >= result.height) return null;
  let best = null;
  for (const entry of result.tiles.values()) {
    if (!entry.ready) continue;
    const f = 2 ** entry.level, span = result.tile * f;
    if (Math.floor(ix / span) !== entry.col || Math.floor(iy / span) !== entry.row) continue;
    if (!best || entry.level < best.level) best = entry;
  }
  if (!best) return null;
  const f = 2 ** best.level;
  const lx = Math.min(best.w - 1, Math.floor(ix / f) - best.col * result.tile);
  const ly = Math.min(best.h - 1, Math.floor(iy / f) - best.row * result.tile);
  const k = (ly * best.w + lx) * 4, plane = best.w * best.h * 4, d = best.data;
  const v = (i) => HALF[d[i]];
  return {
    x: ix, y: iy, level: best.level,
    normal: [v(k), v(k + 1), v(k + 2)], albedo: v(k + 3) * result.albedo_scale,
    outliers: v(plane + k), error: v(plane + k + 1), relief: v(plane + k + 2), depth: v(plane + k + 3),
  };
}

function showProbe(result, value) {
  const box = document.getElementById("probe");
  if (!value) { box.textContent = "move over the image for values"; return; }
  const n = value.normal, inside = Math.hypot(...n) > 0.5;
  const lines = [`${result.name}`, `pixel   ${value.x}, ${value.y}${value.level ? ` (level ${value.level})` : ""}`];
  if (!inside) lines.push("outside the mask");
  else {
    lines.push(`normal  ${n.map((c) => c.toFixed(3)).join(" ")}`);
    lines.push(`albedo  ${value.albedo.toPrecision(4)}`);
    if (result.has.outliers) lines.push(`outliers ${(100 * value.outliers).toFixed(1)} %`);
    if (result.has.error) lines.push(`error   ${value.error < 0 ? "-" : value.error.toFixed(2) + "°"}`);
    if (result.has.depth) lines.push(`depth   ${Number.isFinite(value.depth) ? value.depth.toPrecision(5) : "-"}${result.depth_unit ? " " + result.depth_unit : ""}`);
  }
  box.textContent = lines.join("\n");
}

const lightCanvas = document.getElementById("light");

function drawLightWidget() {
  const c = lightCanvas.getContext("2d"), w = lightCanvas.width, r = w / 2 - 4;
  c.clearRect(0, 0, w, w);
  c.strokeStyle = "#5f6368";
  c.beginPath(); c.arc(w / 2, w / 2, r, 0, 2 * Math.PI); c.stroke();
  c.beginPath(); c.arc(w / 2, w / 2, r * Math.cos((60 * Math.PI) / 180), 0, 2 * Math.PI); c.stroke();
  // The captured lights (issue 32): a small dot at each direction of the results' light files.
  c.fillStyle = "#8ab4f8";
  for (const result of results) {
    for (const d of result.captured_lights || []) {
      c.beginPath(); c.arc(w / 2 + d[0] * r, w / 2 - d[1] * r, 2, 0, 2 * Math.PI); c.fill();
    }
  }
  const l = lightVector();
  c.fillStyle = "#fdd663";
  c.beginPath(); c.arc(w / 2 + l[0] * r, w / 2 - l[1] * r, 6, 0, 2 * Math.PI); c.fill();
  const elevation = (Math.asin(Math.max(-1, Math.min(1, l[2]))) * 180) / Math.PI;
  const azimuth = (Math.atan2(l[1], l[0]) * 180) / Math.PI;
  document.getElementById("light-value").textContent =
    `light ${l.map((x) => x.toFixed(3)).join(" ")}\nazimuth ${azimuth.toFixed(0)}°, elevation ${elevation.toFixed(0)}°`;
}

function setLightFromDisc(u, v) {
  // (u, v) in the unit disc, v up; outside the disc the light lies on the horizon.
  const r = Math.hypot(u, v);
  if (r > 1) { u /= r; v /= r; }
  setLight([u, v, Math.sqrt(Math.max(0, 1 - u * u - v * v))]);
}

function setLight(l) {
  const n = Math.hypot(...l) || 1;
  state.light = l.map((x) => x / n);
  drawLightWidget();
  redraw();
}

function discFromEvent(element, event) {
  const box = element.getBoundingClientRect();
  const r = Math.min(box.width, box.height) / 2;
  return [(event.clientX - box.left - box.width / 2) / r, -(event.clientY - box.top - box.height / 2) / r];
}

lightCanvas.addEventListener("pointerdown", (event) => {
  lightCanvas.setPointerCapture(event.pointerId);
  const move = (e) => setLightFromDisc(...discFromEvent(lightCanvas, e));
  move(event);
  lightCanvas.onpointermove = move;
  lightCanvas.onpointerup = () => { lightCanvas.onpointermove = null; };
});

// ---- pointer on the image ----------------------------------------------------------------------
function panelAt(event) {
  const dpr = window.devicePixelRatio || 1, box = canvas.getBoundingClientRect();
  const x = (event.clientX - box.left) * dpr, y = (event.clientY - box.top) * dpr;
  const layout = panels();
  for (let i = 0; i < layout.length; i++) {
    const p = layout[i];
    if (x >= p.x && x < p.x + p.w && y >= p.y && y < p.y + p.h) return { i, panel: p, px: x - p.x, py: y - p.y };
  }
  return null;
}

let drag = null;
canvas.addEventListener("contextmenu", (e) => e.preventDefault());
canvas.addEventListener("pointerdown", (event) => {
  const at = panelAt(event);
  if (!at) return;
  canvas.setPointerCapture(event.pointerId);
  const pan = event.shiftKey || event.button !== 0;
  let kind = state.mode === "layers" || (state.mode === "relight" && pan) ? "pan" : state.mode === "relight" ? "light" : pan ? "light" : "orbit";
  drag = { kind, x: event.clientX, y: event.clientY, at, view: { ...state.view }, orbit: { ...state.orbit } };
  if (kind === "light") lightFromPanel(at);
});
canvas.addEventListener("pointermove", (event) => {
  const at = panelAt(event);
  if (at && state.mode !== "mesh") {
    const result = results[at.i];
    const [x, y] = panelToImage(result, at.panel, at.px, at.py);
    showProbe(result, probeAt(result, x, y));
  }
  if (!drag) return;
  const dpr = window.devicePixelRatio || 1;
  const dx = (event.clientX - drag.x) * dpr, dy = (event.clientY - drag.y) * dpr;
  const result = results[drag.at.i];
  if (drag.kind === "pan") {
    const t = transform(result, drag.at.panel);
    state.view.cx = drag.view.cx - dx / t.scale / result.width;
    state.view.cy = drag.view.cy - dy / t.scale / result.height;
  } else if (drag.kind === "orbit") {
    state.orbit.yaw = drag.orbit.yaw + dx * 0.01;
    state.orbit.pitch = Math.max(-1.5, Math.min(1.5, drag.orbit.pitch + dy * 0.01));
  } else if (at && at.i === drag.at.i) {
    lightFromPanel(at);
  }
  redraw();
});
canvas.addEventListener("pointerup", () => { drag = null; });

function lightFromPanel(at) {
  const r = Math.min(at.panel.w, at.panel.h) / 2;
  setLightFromDisc((at.px - at.panel.w / 2) / r, -(at.py - at.panel.h / 2) / r);
}

canvas.addEventListener("wheel", (event) => {
  event.preventDefault();
  const factor = Math.exp(-event.deltaY * 0.0015);
  if (state.mode === "mesh") { state.orbit.zoom = Math.max(0.2, Math.min(50, state.orbit.zoom * factor)); redraw(); return; }
  const at = panelAt(event);
  if (!at) return;
  const result = results[at.i];
  const [x, y] = panelToImage(result, at.panel, at.px, at.py);     // keep this pixel under the cursor
  state.view.zoom = Math.max(0.1, Math.min(256, state.view.zoom * factor));
  const t = transform(result, at.panel);
  state.view.cx = (x - (at.px - t.origin[0]) / t.scale) / result.width;
  state.view.cy = (y - (at.py - t.origin[1]) / t.scale) / result.height;
  redraw();
}, { passive: false });

// ---- controls ----------------------------------------------------------------------------------
function setMode(mode) {
  state.mode = mode;
  for (const b of document.querySelectorAll("#modes button")) b.classList.toggle("on", b.dataset.mode === mode);
  document.getElementById("layer-box").style.display = mode === "layers" ? "" : "none";
  redraw();
}

function status(text) { document.getElementById("status").textContent = text; }

function bindControls() {
  for (const b of document.querySelectorAll("#modes button")) b.addEventListener("click", () => setMode(b.dataset.mode));
  const bind = (id, event, apply) => document.getElementById(id).addEventListener(event, (e) => { apply(e.target); drawLightWidget(); redraw(); });
  bind("layer", "change", (t) => { state.layer = t.value; });
  bind("raking", "change", (t) => { state.raking = t.checked; if (t.checked) state.useAlbedo = false; document.getElementById("albedo").checked = state.useAlbedo; });
  bind("elevation", "input", (t) => { state.elevation = Number(t.value); document.getElementById("elevation-value").textContent = `${t.value}°`; });
  bind("albedo", "change", (t) => { state.useAlbedo = t.checked; });
  bind("appearance", "change", (t) => { state.appearance = t.checked; });
  bind("exposure", "input", (t) => { state.exposure = Number(t.value); });
  bind("errmax", "change", (t) => { state.errorMax = Math.max(1, Number(t.value) || 30); });
  window.addEventListener("resize", redraw);
}

// ---- start -------------------------------------------------------------------------------------
async function start() {
  if (!gl) { status("this browser has no WebGL 2"); throw new Error("no WebGL 2"); }
  setupGL();
  bindControls();
  const response = await fetch("data/manifest.json");
  const manifest = await response.json();
  results = manifest.results.map((r, index) => ({ ...r, index, tiles: new Map(), failures: new Map() }));
  const anyMesh = results.some((r) => r.mesh);
  document.getElementById("mode-mesh").disabled = !anyMesh;
  for (const option of document.querySelectorAll("#layer option")) {
    const need = { outliers: "outliers", error: "error", relief: "depth" }[option.value];
    option.disabled = need ? !results.some((r) => r.has[need]) : false;
  }
  // The error layer's scale: 1.5 x the largest p90 error of the results (at least 1 degree).
  const p90 = Math.max(0, ...results.map((r) => (r.angular_error_deg ? r.angular_error_deg.p90 : 0)));
  if (p90 > 0) {
    state.errorMax = Math.max(1, Math.ceil(1.5 * p90));
    document.getElementById("errmax").value = state.errorMax;
  }
  // The appearance switch: shown when a result has a fitted model; notes for the ones relit Lambertian.
  const fits = results.filter((r) => r.appearance);
  document.getElementById("appearance-box").style.display = fits.length ? "" : "none";
  document.getElementById("appearance-model").textContent = [...new Set(fits.map((r) => r.appearance.model))].join(", ");
  document.getElementById("appearance-note").textContent = fits.map((r) => r.appearance.note).filter(Boolean).join("; ");
  setMode("relight");
  drawLightWidget();
  results.forEach((r) => requestTile(r.index, r.levels.length - 1, 0, 0));
  status(`${results.length} result${results.length > 1 ? "s" : ""}`);
  requestAnimationFrame(frame);
}

// For scripts and tests: the state, the counters, and the functions the controls call.
window.psView = {
  state, stats, setLight, setMode, redraw, lightVector,
  setLayer(layer) { state.layer = layer; document.getElementById("layer").value = layer; redraw(); },
  setView(view) { Object.assign(state.view, view); redraw(); },
  setOrbit(orbit) { Object.assign(state.orbit, orbit); redraw(); },
  set(options) { Object.assign(state, options); drawLightWidget(); redraw(); },
  results: () => results.map(({ tiles, meshState, failures, ...r }) => r),
  // Each reads the layout as it is now (resize() first): a control shown after the results load
  // (the appearance switch) can wrap the toolbar and shrink the canvas before the next frame.
  panels: () => { resize(); return panels().map((p) => { const d = window.devicePixelRatio || 1; const box = canvas.getBoundingClientRect(); return { x: box.left + p.x / d, y: box.top + p.y / d, w: p.w / d, h: p.h / d }; }); },
  // CSS position of level-0 image pixel (x, y)'s centre in panel i.
  imageToClient(i, x, y) {
    resize();
    const d = window.devicePixelRatio || 1, box = canvas.getBoundingClientRect(), p = panels()[i];
    const [px, py] = imageToPanel(results[i], p, x + 0.5, y + 0.5);
    return [box.left + (p.x + px) / d, box.top + (p.y + py) / d];
  },
  // Zoom so that one image pixel is `s` device pixels in panel i.
  pixelScale(i, s) { resize(); const p = panels()[i], r = results[i]; state.view.zoom = s / Math.min(p.w / r.width, p.h / r.height); redraw(); },
  probe(i, x, y) { return probeAt(results[i], x, y); },
  idle() { return !dirty && stats.refined && stats.pending === 0 && results.every((r) => !r.mesh || state.mode !== "mesh" || (r.meshState && r.meshState.ready)); },
  ready: null,
};
window.psView.ready = start().then(() => true, (error) => { status(String(error)); return String(error); });

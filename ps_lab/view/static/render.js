// ps-lab view, part 1 of 2: what does not depend on the page's state. Half-float decoding, the
// shaders (relight and layers on tiles; the mesh), compiling them, 4 x 4 matrices. Loaded before
// viewer.js (classic scripts share one global scope).
"use strict";

// ---- half floats -------------------------------------------------------------------------------
const HALF = new Float32Array(65536);
for (let h = 0; h < 65536; h++) {
  const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 0x1f, f = h & 0x3ff;
  HALF[h] = e === 0 ? s * f * 2 ** -24 : e === 31 ? (f ? NaN : s * Infinity) : s * (1 + f / 1024) * 2 ** (e - 15);
}

// ---- shaders -----------------------------------------------------------------------------------
const IMAGE_VS = `#version 300 es
in vec2 a_corner;
uniform vec4 u_rect;      // tile rectangle in level-0 image pixels: x, y, w, h
uniform vec2 u_center;    // image pixel at the panel's origin
uniform vec2 u_origin;    // that origin in panel pixels
uniform vec2 u_panel;     // panel size in device pixels
uniform float u_scale;    // device pixels per image pixel
out vec2 v_uv;
void main() {
  vec2 p = u_rect.xy + a_corner * u_rect.zw;
  vec2 q = u_origin + (p - u_center) * u_scale;
  gl_Position = vec4(q.x / u_panel.x * 2.0 - 1.0, 1.0 - q.y / u_panel.y * 2.0, 0.0, 1.0);
  v_uv = a_corner;
}`;
const IMAGE_FS = `#version 300 es
precision highp float;
uniform sampler2D u_a;
uniform sampler2D u_b;
uniform sampler2D u_c0;   // colour tiles (issue 32): normals and albedo R
uniform sampler2D u_c1;   // albedo G, B
uniform bool u_colour;
// Appearance (issue 32; ps_lab/view/appearance_tiles.py): coefficient 3k + c of term k, channel c,
// four to an RGBA plane, planes stacked in one texture of u_tsize.x x (u_tsize.y * planes).
uniform highp sampler2D u_coef;
uniform int u_model;      // 0 Lambertian, 1 a basis of the light (ptm, hsh2, hsh3), 2 ps,
                          // 3 weights over the training lights (rbf, bln, gp)
uniform int u_terms;
uniform ivec2 u_tsize;
uniform float u_basis[16];   // the basis at the light (ptm / hsh, and ps's hsh terms)
// ps: 0 lambert, 1 ambient, 2 lobe:P, 3 a term of the light (u_basis: hsh:i), 4 u_basis on the
// lit side (lx, ly, lz: the light's component), 5 lobex:P / lobey:P (u_basis: h's component)
uniform int u_kind[16];
uniform float u_power[16];   // ps lobes: the exponent P
uniform bool u_vis;          // ps visibility: coefficients 3K .. 3K + 3 hold w (appearance/models.py)
uniform vec3 u_rbf[32];      // rbf, bln, gp: sum_i w_i(l) B_c[i, k], channel c in x, y, z
uniform bool u_shared;       // rbf, bln, gp: one coefficient per term (index k), else 3k + c
uniform bool u_srgb;         // a fit in sRGB-encoded space: its prediction decoded to linear
uniform float u_gain;        // ... then times 1 / albedo_scale
uniform int u_mode;
uniform vec3 u_light;
uniform float u_exposure;
uniform bool u_albedo;
uniform float u_errmax;
uniform vec3 u_bg;
in vec2 v_uv;
out vec4 o;
vec3 srgb(vec3 c) {
  c = clamp(c, 0.0, 1.0);
  return mix(c * 12.92, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(0.0031308, c));
}
float coefficient(ivec2 px, int i) {
  vec4 t = texelFetch(u_coef, ivec2(px.x, px.y + (i / 4) * u_tsize.y), 0);
  int j = i - (i / 4) * 4;
  return j == 0 ? t.x : (j == 1 ? t.y : (j == 2 ? t.z : t.w));
}
vec3 linear(vec3 c) {      // io/encoding.py: srgb_to_linear
  return mix(c / 12.92, pow((c + 0.055) / 1.055, vec3(2.4)), step(0.04045, c));
}
vec3 prediction(vec3 n, vec3 albedo) {    // appearance/models.py: evaluate_appearance, per pixel
  ivec2 px = clamp(ivec2(v_uv * vec2(u_tsize)), ivec2(0), u_tsize - 1);
  float nl = dot(n, u_light);
  vec3 h = normalize(u_light + vec3(0.0, 0.0, 1.0));
  // ps visibility (cast shadows): V = clamp(w . [l, 1], 0, 1) on the Lambertian and direct terms
  float V = 1.0;
  if (u_model == 2 && u_vis) {
    vec4 w = vec4(coefficient(px, 3 * u_terms), coefficient(px, 3 * u_terms + 1),
                  coefficient(px, 3 * u_terms + 2), coefficient(px, 3 * u_terms + 3));
    V = clamp(dot(w, vec4(u_light, 1.0)), 0.0, 1.0);
  }
  vec3 c = u_model == 2 ? V * albedo * max(nl, 0.0) : vec3(0.0);
  if (u_model == 3) {
    for (int k = 0; k < 32; k++) {
      if (k >= u_terms) break;
      c += u_rbf[k] * (u_shared ? vec3(coefficient(px, k)) : vec3(coefficient(px, 3 * k),
                       coefficient(px, 3 * k + 1), coefficient(px, 3 * k + 2)));
    }
    return c;
  }
  for (int k = 0; k < 16; k++) {
    if (k >= u_terms) break;
    float b = u_basis[k];
    if (u_model == 2) {
      int kind = u_kind[k];
      float nh = max(dot(n, h), 0.0);
      if (kind == 0) b = max(nl, 0.0);
      else if (kind == 1) b = 1.0;
      else if (kind == 2) b = nl > 0.0 ? pow(nh, u_power[k]) : 0.0;
      else if (kind == 4) b = nl > 0.0 ? u_basis[k] : 0.0;
      else if (kind == 5) {
        float p = u_power[k] - 1.0;
        b = nl > 0.0 ? (p > 0.0 ? pow(nh, p) : 1.0) * u_basis[k] : 0.0;
      }
      if (kind == 0 || kind == 2 || kind == 4 || kind == 5) b *= V;   // appearance/models.py: is_direct
    }
    c += b * vec3(coefficient(px, 3 * k), coefficient(px, 3 * k + 1), coefficient(px, 3 * k + 2));
  }
  return c;
}
vec3 fitted(vec3 n, vec3 albedo) {    // evaluate_appearance's decoding of an sRGB-space fit
  vec3 c = prediction(n, albedo);
  return u_srgb ? linear(clamp(c, 0.0, 1.0)) * u_gain : c;
}
vec3 heat(float t) {       // black - red - yellow - white
  t = clamp(t, 0.0, 1.0);
  return clamp(vec3(3.0 * t, 3.0 * t - 1.0, 3.0 * t - 2.0), 0.0, 1.0);
}
void main() {
  vec4 a = texture(u_a, v_uv);
  vec4 b = texture(u_b, v_uv);
  float len = length(a.xyz);
  if (len < 0.5) { o = vec4(u_bg, 1.0); return; }
  vec3 n = a.xyz / len;
  vec3 c;
  vec3 rgb = u_colour ? vec3(texture(u_c0, v_uv).w, texture(u_c1, v_uv).xy) : vec3(a.w);
  if (u_mode == 0 && u_model > 0) {
    c = srgb(fitted(n, rgb) * u_exposure);
  } else if (u_mode == 0) {
    float shade = max(dot(n, u_light), 0.0);
    c = srgb((u_albedo ? rgb : vec3(1.0)) * shade * u_exposure);
  } else if (u_mode == 1) {
    c = (n + 1.0) * 0.5;
  } else if (u_mode == 2) {
    c = clamp(rgb, 0.0, 1.0);
  } else if (u_mode == 3) {
    c = heat(b.x);
  } else if (u_mode == 4) {
    c = b.y < 0.0 ? vec3(0.3, 0.3, 0.5) : heat(b.y / u_errmax);
  } else {
    c = b.z < 0.0 ? vec3(0.3, 0.3, 0.5) : vec3(b.z);
  }
  o = vec4(c, 1.0);
}`;
const MESH_VS = `#version 300 es
in vec3 a_position;
in vec3 a_normal;
in vec4 a_colour;
uniform mat4 u_mvp;
out vec3 v_normal;
out vec3 v_colour;
void main() {
  gl_Position = u_mvp * vec4(a_position, 1.0);
  v_normal = a_normal;
  v_colour = a_colour.rgb;
}`;
const MESH_FS = `#version 300 es
precision highp float;
uniform vec3 u_light;
uniform bool u_albedo;
uniform float u_exposure;
in vec3 v_normal;
in vec3 v_colour;
out vec4 o;
void main() {
  vec3 n = normalize(v_normal);
  float shade = 0.08 + 0.92 * max(dot(n, u_light), 0.0);
  vec3 c = (u_albedo ? v_colour : vec3(0.8)) * shade * u_exposure;
  o = vec4(pow(clamp(c, 0.0, 1.0), vec3(1.0 / 2.2)), 1.0);
}`;

// ---- appearance bases (ps_lab/appearance/models.py) --------------------------------------------------
function unitVector(l) { const n = Math.hypot(...l) || 1; return l.map((x) => x / n); }

function hshBasis(l) {    // Gautron et al. 2004 as RTIBuilder / RelightLab define them, 9 terms
  const [x, y, z] = unitVector(l);
  const c = Math.min(1, Math.max(0, z)), phi = Math.atan2(y, x), s = Math.sqrt(Math.max(c - c * c, 0));
  const cp = Math.cos(phi), sp = Math.sin(phi), k = Math.sqrt(30 / Math.PI);
  return [
    1 / Math.sqrt(2 * Math.PI), Math.sqrt(6 / Math.PI) * cp * s, Math.sqrt(3 / (2 * Math.PI)) * (2 * c - 1),
    Math.sqrt(6 / Math.PI) * sp * s, k * Math.cos(2 * phi) * (c * c - c), k * cp * (2 * c - 1) * s,
    Math.sqrt(5 / (2 * Math.PI)) * (6 * c * c - 6 * c + 1), k * sp * (2 * c - 1) * s, k * Math.sin(2 * phi) * (c * c - c),
  ];
}

// The interpolating models' weights over the n training lights (appearance/smoothers.py), float64.
function gaussianWeights(lights, sigma, u) {    // gaussian_weights: normalised, of a unit u
  const n = lights.length / 3, w = new Float64Array(n);
  let top = -Infinity, total = 0;
  for (let i = 0; i < n; i++) {
    const dx = u[0] - lights[3 * i], dy = u[1] - lights[3 * i + 1], dz = u[2] - lights[3 * i + 2];
    w[i] = -(dx * dx + dy * dy + dz * dz) / (sigma * sigma);
    top = Math.max(top, w[i]);
  }
  for (let i = 0; i < n; i++) { w[i] = Math.exp(w[i] - top); total += w[i]; }
  for (let i = 0; i < n; i++) w[i] /= total;
  return w;
}

function blnWeights(lights, sigma, r, u) {    // bln_weights: bilinear over the grid's nodes
  const n = lights.length / 3, w = new Float64Array(n), top = r - 1 - 1e-9;
  const g = [0, 1].map((a) => Math.min(Math.max((u[a] + 1) / 2 * (r - 1), 0), top));
  const i0 = g.map(Math.floor), t = [g[0] - i0[0], g[1] - i0[1]];
  for (const dy of [0, 1]) {
    for (const dx of [0, 1]) {
      const x = -1 + 2 * (i0[0] + dx) / (r - 1), y = -1 + 2 * (i0[1] + dy) / (r - 1);   // grid_nodes
      const node = gaussianWeights(lights, sigma, unitVector([x, y, Math.sqrt(Math.min(Math.max(1 - x * x - y * y, 0), 1))]));
      const f = (dx ? t[0] : 1 - t[0]) * (dy ? t[1] : 1 - t[1]);
      for (let i = 0; i < n; i++) w[i] += f * node[i];
    }
  }
  return w;
}

function gpWeights(lights, sigma, solve, u) {    // gp_weights: [k(l, L), ptm(l)] . G
  const n = lights.length / 3, w = new Float64Array(n), row = new Float64Array(n + 6);
  for (let i = 0; i < n; i++) {
    const dx = u[0] - lights[3 * i], dy = u[1] - lights[3 * i + 1], dz = u[2] - lights[3 * i + 2];
    row[i] = Math.exp(-(dx * dx + dy * dy + dz * dz) / (sigma * sigma));
  }
  row.set([1, u[0], u[1], u[0] * u[0], u[0] * u[1], u[1] * u[1]], n);
  for (let i = 0; i < n + 6; i++) for (let j = 0; j < n; j++) w[j] += row[i] * solve[i * n + j];
  return w;
}

// rbf, bln, gp (appearance/models.py: smoother_weights, evaluate_appearance): per channel c and term
// k, sum_i w_i(l) B_c[i, k].
function rbfUniforms(fit, l) {
  const out = new Float32Array(96);
  const { lights, sigma, basis } = fit.rbf, n = lights.length / 3, K = fit.K, u = unitVector(l);
  const w = fit.model === "bln" ? blnWeights(lights, sigma, fit.rbf.resolution, u)
    : fit.model === "gp" ? gpWeights(lights, sigma, fit.rbf.solve, u) : gaussianWeights(lights, sigma, u);
  for (let c = 0; c < 3; c++) {
    for (let k = 0; k < K; k++) {
      let s = 0;
      for (let i = 0; i < n; i++) s += w[i] * basis[(c * n + i) * K + k];
      out[3 * k + c] = s;
    }
  }
  return out;
}

// The uniforms of a fitted model at light l: { model, basis, kind, power, rbf, shared, srgb,
// gain } (model 0: Lambertian).
function appearanceUniforms(fit, l) {
  const basis = new Float32Array(16), kind = new Int32Array(16), power = new Float32Array(16);
  const none = { model: 0, terms: 0, basis, kind, power, vis: false, rbf: new Float32Array(96), shared: false,
                 srgb: false, gain: 1 };
  if (!fit || !fit.planes) return none;
  const space = { srgb: fit.space === "srgb", gain: fit.gain ?? 1 };
  if (fit.rbf) {   // rbf, bln, gp
    return { ...none, ...space, model: 3, terms: fit.K, rbf: rbfUniforms(fit, l), shared: !!fit.shared };
  }
  const [x, y] = unitVector(l);
  if (fit.model === "ptm") basis.set([1, x, y, x * x, x * y, y * y]);
  else if (fit.model === "hsh2" || fit.model === "hsh3") basis.set(hshBasis(l).slice(0, fit.K));
  else {   // appearance/models.py: ps_term
    const hsh = hshBasis(l), u = unitVector(l), h = unitVector([u[0], u[1], u[2] + 1]);
    fit.terms.forEach((term, k) => {
      const [name, arg] = term.split(":");
      if (name === "lambert") kind[k] = 0;
      else if (name === "ambient") kind[k] = 1;
      else if (name === "lobe") { kind[k] = 2; power[k] = Number(arg); }
      else if (name === "hsh") { kind[k] = 3; basis[k] = hsh[Number(arg)]; }
      else if (["lx", "ly", "lz"].includes(name)) { kind[k] = 4; basis[k] = u["xyz".indexOf(name[1])]; }
      else if (name === "lobex" || name === "lobey") { kind[k] = 5; power[k] = Number(arg); basis[k] = h["xy".indexOf(name[4])]; }
      else { kind[k] = 3; basis[k] = 0; }   // a term this page does not know: left out
    });
  }
  return { ...none, ...space, model: fit.model === "ps" ? 2 : 1, terms: fit.K, basis, kind, power, vis: !!fit.visibility };
}

function program(gl, vs, fs) {
  const p = gl.createProgram();
  for (const [kind, src] of [[gl.VERTEX_SHADER, vs], [gl.FRAGMENT_SHADER, fs]]) {
    const s = gl.createShader(kind);
    gl.shaderSource(s, src);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    gl.attachShader(p, s);
  }
  gl.linkProgram(p);
  if (!gl.getProgramParameter(p, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(p));
  const u = {};
  const count = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
  for (let i = 0; i < count; i++) {
    const name = gl.getActiveUniform(p, i).name;
    u[name] = gl.getUniformLocation(p, name);
  }
  return { p, u };
}

function multiply(a, b) {
  const o = new Float32Array(16);
  for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
    let s = 0;
    for (let k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
    o[c * 4 + r] = s;
  }
  return o;
}

// NeuMatEx real-time neural material viewer (docs/viewer.md). Raw WebGL2, no dependencies, no build step.
//
// Loads bundle.json and its float32 .bin files (written by neumatex_core/viewer/web_bundle.py), rasterises the mesh
// and shades every pixel with direct lighting from the environment map: per frame `spp` directions drawn from the
// map's piecewise-constant distribution (the same bins and pdf as neumatex_core/lighting/envmap.py), each weighted
// by f * cos / pdf, accumulated over frames in a float32 buffer with sub-pixel jitter (a box filter, like the path
// tracer's jittered camera rays). f is the neural BSDF of the basis (docs/asset-format.md):
//   f = T(wo) rho_d / pi + f_neu(l, wi, wo),   T = sigmoid(aux(l, wo))[0:3],   f_neu = exp(min(decoder(l, feat), 12))
// with the decoder's direction features of neumatex_core/materials/neural_basis.py (direction_features) in the
// shading frame of neumatex_core/geometry/surface.py (Duff et al. tangents of the shading normal, both normals
// flipped towards the viewer). There are no shadow rays: a rasteriser sees no self-shadowing (exact on convex
// objects). The PBR fallback is neumatex_core/materials/pbr.py (Lambert + GGX, UE4 Schlick).
"use strict";

(() => {
  const params = new URLSearchParams(window.location.search);
  const canvas = document.getElementById("view");
  const statusEl = document.getElementById("status");
  const errorEl = document.getElementById("error");
  const ui = {
    mode: document.getElementById("mode"), envmap: document.getElementById("envmap"),
    exposure: document.getElementById("exposure"), spp: document.getElementById("spp"),
    background: document.getElementById("background"),
  };

  function fail(message) {
    errorEl.textContent = message;
    statusEl.textContent = "";
    api.error = message;
    throw new Error(message);
  }

  const api = { ready: null, error: null, frames: 0, lastFrameMs: 0 };
  window.neumatexViewer = api;

  // ---------------------------------------------------------------------------------------------------------
  const PRELUDE = `#version 300 es
precision highp float;
precision highp int;
precision highp sampler2D;
`;

  const VS_MESH = `#version 300 es
precision highp float;
layout(location = 0) in vec3 aPos;
layout(location = 1) in vec3 aNormal;
layout(location = 2) in vec2 aUv;
layout(location = 3) in vec3 aFaceNormal;
uniform mat4 uViewProj;
out vec3 vPos;
out vec3 vNormal;
out vec2 vUv;
flat out vec3 vFaceNormal;
void main() {
  vPos = aPos; vNormal = aNormal; vUv = aUv; vFaceNormal = aFaceNormal;
  gl_Position = uViewProj * vec4(aPos, 1.0);
}`;

  const VS_QUAD = `#version 300 es
precision highp float;
void main() {
  vec2 p = vec2(float((gl_VertexID & 1) << 2) - 1.0, float((gl_VertexID & 2) << 1) - 1.0);
  gl_Position = vec4(p, 0.0, 1.0);
}`;

  // Shared: the previous sum, the environment map (lookup and sampling), random numbers.
  const COMMON = `
uniform sampler2D uAccum;
uniform sampler2D uEnv;     // [H, W] RGBA32F: radiance, bin probability
uniform sampler2D uCdf;     // [H + 1, W + 1] R32F: conditional CDFs per row, marginal CDF in row H
uniform ivec2 uEnvSize;     // (W, H)
uniform uint uFrame;
uniform int uSpp;
const float PI = 3.14159265358979;

vec4 previous() { return texelFetch(uAccum, ivec2(gl_FragCoord.xy), 0); }

// EnvironmentMap.direction_to_uv / lookup_uv (identity to_world): columns at texel centres, rows at v = j / (H - 1).
vec2 dirToUv(vec3 d) {
  float u = atan(d.x, -d.z) * (0.5 / PI);
  u = u - floor(u);
  return vec2(u, acos(clamp(d.y, -1.0, 1.0)) / PI);
}
vec3 envTexel(int x, int y) { return texelFetch(uEnv, ivec2(x, y), 0).rgb; }
vec3 envLookup(vec2 uv) {
  int w = uEnvSize.x, h = uEnvSize.y;
  float x = uv.x - 0.5 / float(w);
  x = (x - floor(x)) * float(w);
  float y = clamp(uv.y, 0.0, 1.0) * float(h - 1);
  int x0 = clamp(int(floor(x)), 0, w - 1);
  int y0 = clamp(int(floor(y)), 0, h - 2);
  float fx = x - float(x0), fy = y - float(y0);
  int x1 = (x0 + 1) % w;
  vec3 top = envTexel(x0, y0) * (1.0 - fx) + envTexel(x1, y0) * fx;
  vec3 bottom = envTexel(x0, y0 + 1) * (1.0 - fx) + envTexel(x1, y0 + 1) * fx;
  return top * (1.0 - fy) + bottom * fy;
}
vec3 uvToDir(vec2 uv) {
  float phi = 2.0 * PI * uv.x, theta = PI * uv.y;
  float st = sin(theta);
  return vec3(st * sin(phi), cos(theta), -st * cos(phi));
}
float cdf(int x, int y) { return texelFetch(uCdf, ivec2(x, y), 0).r; }
// Largest index k in [0, n - 1] of row y with cdf[k] <= u (rows of zero probability are skipped).
int searchCdf(float u, int y, int n) {
  int lo = 0, hi = n - 1;
  while (lo < hi) {
    int mid = (lo + hi + 1) >> 1;
    if (cdf(mid, y) <= u) lo = mid; else hi = mid - 1;
  }
  return lo;
}
// A direction from the map's distribution: (direction, pdf) and its radiance; pdf as EnvironmentMap._pdf_uv.
vec3 sampleEnv(vec2 u, out float pdf, out vec3 radiance) {
  int w = uEnvSize.x, h = uEnvSize.y;
  int row = searchCdf(u.x, h, h);
  float r0 = cdf(row, h), r1 = cdf(row + 1, h);
  float fv = clamp((u.x - r0) / max(r1 - r0, 1e-30), 0.0, 0.9999999);
  int col = searchCdf(u.y, row, w);
  float c0 = cdf(col, row), c1 = cdf(col + 1, row);
  float fu = clamp((u.y - c0) / max(c1 - c0, 1e-30), 0.0, 0.9999999);
  vec2 uv = vec2((float(col) + fu) / float(w), (float(row) + fv) / float(h));
  float sinTheta = sin(PI * uv.y);
  float p = texelFetch(uEnv, ivec2(col, row), 0).a * float(w * h) / (2.0 * PI * PI);
  pdf = sinTheta > 1e-7 ? p / max(sinTheta, 1e-7) : 0.0;
  radiance = envLookup(uv);
  return uvToDir(uv);
}
// Random numbers: a per-pixel Cranley-Patterson rotation of the R2 sequence, in integers (no float drift).
uint hash(uint x) {
  x ^= x >> 16; x *= 0x7feb352du; x ^= x >> 15; x *= 0x846ca68bu; x ^= x >> 16; return x;
}
vec2 rand2(uint n, uint dim) {
  uvec2 p = uvec2(gl_FragCoord.xy);
  uint seed = hash(p.x + hash(p.y * 7919u + 17u + dim * 104729u));
  uvec2 r = uvec2(seed, hash(seed)) + n * uvec2(3242174889u, 2447445413u);
  return vec2(r >> 8) * (1.0 / 16777216.0);
}
`;

  const FS_BACKGROUND = `
uniform mat3 uCamRot;       // camera-to-world rotation (columns: +X, +Y, +Z)
uniform vec4 uIntrinsics;   // fl_x, fl_y, cx, cy (pixels, y down)
uniform vec3 uImage;        // width, height, 1 to show the map, 0 for black
uniform vec2 uJitter;       // sub-pixel offset of this frame
out vec4 outColor;
void main() {
  float x = gl_FragCoord.x - 0.5 + uJitter.x;
  float y = uImage.y - gl_FragCoord.y - 0.5 + uJitter.y;
  vec3 dCam = vec3((x - uIntrinsics.z) / uIntrinsics.x, -(y - uIntrinsics.w) / uIntrinsics.y, -1.0);
  vec3 d = normalize(uCamRot * dCam);
  vec3 c = uImage.z > 0.5 ? envLookup(dirToUv(d)) : vec3(0.0);
  outColor = previous() + vec4(c, 1.0);
}`;

  function mlpSource(name, layers) {
    // Linear + SiLU stack (neural_basis.mlp). Weights and biases live in the RGBA32F texture uBasis (basis.bin as
    // texels, WEIGHT_WIDTH per row): layer k's 4x4 weight blocks (out block i, in block j at i * n_in4 + j, column
    // major: 4 texels each) from float offset l.offset, its bias at bias_offset + 4 * l.bias_vec4.
    const n0 = layers[0].n_in4, nLast = layers[layers.length - 1].n_out4;
    const args = Array.from({ length: n0 }, (_, j) => `vec4 x${j}`).join(", ");
    let body = `void ${name}Eval(${args}, out vec4 y[${nLast}]) {\n  vec4 x[${n0}];\n`;
    for (let j = 0; j < n0; j++) body += `  x[${j}] = x${j};\n`;
    body += `  vec4 a[16];\n  vec4 b[16];\n`;
    let src = "x", dst = "a";
    layers.forEach((l, k) => {
      const last = k === layers.length - 1;
      if (l.n_out4 > 16 || (k > 0 && layers[k - 1].n_out4 !== l.n_in4)) fail("unsupported basis layer sizes");
      body += `  for (int i = 0; i < ${l.n_out4}; i++) {\n    vec4 acc = basisTexel(${BASIS.bias_offset / 4 + l.bias_vec4} + i);\n` +
        `    for (int j = 0; j < ${l.n_in4}; j++) acc += basisBlock(${l.offset / 16} + i * ${l.n_in4} + j) * ${src}[j];\n`;
      if (last) {
        body += `    y[i] = acc;\n  }\n`;
      } else {
        body += `    ${dst}[i] = acc / (1.0 + exp(-acc));\n  }\n`;
        src = dst; dst = dst === "a" ? "b" : "a";
      }
    });
    body += `}\n`;
    return body;
  }

  const WEIGHT_WIDTH = 2048;  // texels per row of the weight texture (a multiple of 4: blocks never straddle rows)
  let BASIS = null;
  // GLSL for a list of scalar expressions as the vec4 arguments of a network's first layer (zero padded).
  function blocks(scalars) {
    const out = [];
    for (let i = 0; i < scalars.length; i += 4) {
      const part = scalars.slice(i, i + 4);
      while (part.length < 4) part.push("0.0");
      out.push(`vec4(${part.join(", ")})`);
    }
    return out.join(", ");
  }
  function meshFragmentSource(basis, material) {
    const dec = basis.networks.decoder, aux = basis.networks.aux, smp = basis.networks.sampler;
    const K = basis.latent_dim, nTex = material.channels / 4;
    // material.bin's channels (web_bundle.material_texels): rho_d, the K latents, PBR base colour, roughness,
    // metallic, texel mask, zero padding; texture t holds channels 4t..4t+3.
    if (material.channels !== 4 * Math.ceil((K + 9) / 4)) fail("material channels do not fit the basis's latent size");
    if (dec[0].n_in !== K + 11 || aux[0].n_in !== K + 3 || smp[0].n_in !== K + 3) fail("unexpected basis inputs");
    if (dec[dec.length - 1].n_out !== 3 || aux[aux.length - 1].n_out !== 4 || smp[smp.length - 1].n_out !== 5) {
      fail("unexpected basis outputs");
    }
    BASIS = basis;
    const ch = (c) => `m[${c >> 2}].${"xyzw"[c & 3]}`;
    const latents = Array.from({ length: K }, (_, i) => `gLat[${i}]`);
    const decIn = blocks([...latents, "wi.x", "wi.y", "wi.z", "wo.x", "wo.y", "wo.z", "h.x", "h.y", "h.z", "dot(h, wo)",
      "log(sin2H + 1e-6) / 8.0 + 1.0"]);   // neural_basis.direction_features
    const woIn = blocks([...latents, "woL.x", "woL.y", "woL.z"]);
    const texIdx = Array.from({ length: nTex }, (_, t) => t);
    const decSrc = mlpSource("dec", dec);
    const auxSrc = mlpSource("aux", aux);
    const smpSrc = mlpSource("smp", smp);
    return `
uniform sampler2D uBasis;
vec4 basisTexel(int k) { return texelFetch(uBasis, ivec2(k % ${WEIGHT_WIDTH}, k / ${WEIGHT_WIDTH}), 0); }
mat4 basisBlock(int m) {
  int k = 4 * m;
  ivec2 p = ivec2(k % ${WEIGHT_WIDTH}, k / ${WEIGHT_WIDTH});
  return mat4(texelFetch(uBasis, p, 0), texelFetch(uBasis, p + ivec2(1, 0), 0), texelFetch(uBasis, p + ivec2(2, 0), 0),
              texelFetch(uBasis, p + ivec2(3, 0), 0));
}
${texIdx.map((t) => `uniform sampler2D uMat${t};`).join("\n")}
uniform int uMatSize;
uniform int uMode;         // 0 neural, 1 PBR, 2 base colour (Lambert)
uniform vec3 uCamPos;
in vec3 vPos;
in vec3 vNormal;
in vec2 vUv;
flat in vec3 vFaceNormal;
out vec4 outColor;
${decSrc}
${auxSrc}
${smpSrc}
// fields/uv_textures.sample_uv: bilinear, align_corners=False, border padding, texel row 0 at v = 1.
vec4 tex4(sampler2D t, ivec2 p) { return texelFetch(t, p, 0); }
void lookup(vec2 uv, out vec4 m[${nTex}]) {
  float n = float(uMatSize);
  float x = clamp(uv.x * n - 0.5, 0.0, n - 1.0);
  float y = clamp((1.0 - uv.y) * n - 0.5, 0.0, n - 1.0);
  int x0 = min(int(floor(x)), uMatSize - 1), y0 = min(int(floor(y)), uMatSize - 1);
  int x1 = min(x0 + 1, uMatSize - 1), y1 = min(y0 + 1, uMatSize - 1);
  float fx = x - float(x0), fy = y - float(y0);
  ivec2 p00 = ivec2(x0, y0), p10 = ivec2(x1, y0), p01 = ivec2(x0, y1), p11 = ivec2(x1, y1);
  float w00 = (1.0 - fx) * (1.0 - fy), w10 = fx * (1.0 - fy), w01 = (1.0 - fx) * fy, w11 = fx * fy;
${texIdx.map((t) => `  m[${t}] = tex4(uMat${t}, p00) * w00 + tex4(uMat${t}, p10) * w10 + tex4(uMat${t}, p01) * w01 + ` +
  `tex4(uMat${t}, p11) * w11;`).join("\n")}
}
// microfacet.py: GGX D, separable Smith G1, UE4 Schlick.
float ggxD(float cosH, float alpha) {
  float a2 = alpha * alpha, c2 = cosH * cosH, denom = c2 * (a2 - 1.0) + 1.0;
  return cosH > 0.0 ? a2 / max(PI * denom * denom, 1e-30) : 0.0;
}
float smithG1(vec3 w, float alpha) {
  float c2 = clamp(w.z * w.z, 1e-12, 1.0);
  return 2.0 / (1.0 + sqrt(1.0 + alpha * alpha * (1.0 - c2) / c2));
}
vec3 pbrEval(vec3 wi, vec3 wo, vec3 base, float rough, float metal) {
  if (wi.z <= 0.0 || wo.z <= 0.0) return vec3(0.0);
  float alpha = max(rough * rough, 1e-3);
  vec3 f0 = 0.04 * (1.0 - metal) + base * metal;
  vec3 h = wi + wo; h = h / max(length(h), 1e-12);
  float spec = ggxD(h.z, alpha) * smithG1(wi, alpha) * smithG1(wo, alpha) / max(4.0 * wi.z * wo.z, 1e-12);
  float m = clamp(1.0 - clamp(dot(wo, h), 0.0, 1.0), 0.0, 1.0);
  float fc = m * m * m * m * m;
  vec3 fresnel = clamp(50.0 * f0.g, 0.0, 1.0) * fc + (1.0 - fc) * f0;
  return base * (1.0 - metal) / PI + fresnel * spec;
}
// base.cosine_sample (Malley's method, concentric disk).
vec3 cosineSample(vec2 u) {
  vec2 a = 2.0 * u - 1.0;
  if (a.x == 0.0 && a.y == 0.0) return vec3(0.0, 0.0, 1.0);
  float r, phi;
  if (abs(a.x) > abs(a.y)) { r = a.x; phi = (PI / 4.0) * (a.y / a.x); }
  else { r = a.y; phi = PI / 2.0 - (PI / 4.0) * (a.x / a.y); }
  float x = r * cos(phi), y = r * sin(phi);
  return vec3(x, y, sqrt(max(1.0 - x * x - y * y, 0.0)));
}
// microfacet.ggx_sample_visible (Heitz 2018) and ggx_pdf_visible.
vec3 ggxSample(vec3 wo, float alpha, vec2 u) {
  vec3 vh = normalize(vec3(alpha * wo.x, alpha * wo.y, wo.z));
  float lensq = vh.x * vh.x + vh.y * vh.y;
  vec3 t1 = lensq > 0.0 ? vec3(-vh.y, vh.x, 0.0) * inversesqrt(max(lensq, 1e-20)) : vec3(1.0, 0.0, 0.0);
  vec3 t2 = cross(vh, t1);
  float r = sqrt(u.x), phi = 2.0 * PI * u.y;
  float p1 = r * cos(phi), p2 = r * sin(phi);
  float s = 0.5 * (1.0 + vh.z);
  p2 = (1.0 - s) * sqrt(max(1.0 - p1 * p1, 0.0)) + s * p2;
  vec3 nh = t1 * p1 + t2 * p2 + vh * sqrt(max(1.0 - p1 * p1 - p2 * p2, 0.0));
  vec3 h = normalize(vec3(alpha * nh.x, alpha * nh.y, max(nh.z, 1e-6)));
  return 2.0 * dot(wo, h) * h - wo;
}
float ggxPdf(vec3 wi, vec3 wo, float alpha) {
  if (wo.z <= 0.0 || wi.z <= 0.0) return 0.0;
  vec3 h = wi + wo; h = h / max(length(h), 1e-12);
  return smithG1(wo, alpha) * ggxD(h.z, alpha) / max(4.0 * wo.z, 1e-12);
}
// EnvironmentMap.pdf
float envPdf(vec3 d) {
  vec2 uv = dirToUv(d);
  int w = uEnvSize.x, h = uEnvSize.y;
  int col = clamp(int(uv.x * float(w)), 0, w - 1), row = clamp(int(uv.y * float(h)), 0, h - 1);
  float sinTheta = sin(PI * uv.y);
  float p = texelFetch(uEnv, ivec2(col, row), 0).a * float(w * h) / (2.0 * PI * PI);
  return sinTheta > 1e-7 ? p / max(sinTheta, 1e-7) : 0.0;
}

float gLat[${K}];   // the latent at this pixel
vec3 gRho, gT;   // rho_d and T(wo)
// NeuralMaterial.eval: T rho_d / pi + f_neu, zero below the surface.
vec3 neuralEval(vec3 wi, vec3 wo) {
  if (wi.z <= 0.0 || wo.z <= 0.0) return vec3(0.0);
  vec3 h = wi + wo; h = h / max(length(h), 1e-12);   // neural_basis.direction_features
  float sin2H = max(1.0 - h.z * h.z, 0.0);
  vec4 y[1];
  decEval(${decIn}, y);
  return gT * gRho / PI + exp(min(y[0].rgb, 12.0));
}
// NeuralMaterial.mixture / _pdf: lobe probabilities (cosine, GGX 1, GGX 2) and the two GGX widths.
float mixturePdf(vec3 wi, vec3 wo, vec3 probs, vec2 alphas) {
  if (wi.z <= 0.0 || wo.z <= 0.0) return 0.0;
  return probs.x * wi.z / PI + probs.y * ggxPdf(wi, wo, alphas.x) + probs.z * ggxPdf(wi, wo, alphas.y);
}

void main() {
  vec3 wo = normalize(uCamPos - vPos);
  // surface.surface_interaction: flip both normals to the viewer's side; shading normal facing away -> geometric.
  vec3 ng = vFaceNormal;
  float flipSign = dot(ng, wo) < 0.0 ? -1.0 : 1.0;
  ng *= flipSign;
  vec3 ns = normalize(vNormal) * flipSign;
  if (dot(ns, wo) <= 0.0) ns = ng;
  // surface._tangent_frame (Duff et al. 2017).
  float sgn = ns.z >= 0.0 ? 1.0 : -1.0;
  float a = -1.0 / (sgn + ns.z);
  float b = ns.x * ns.y * a;
  vec3 t = vec3(1.0 + sgn * ns.x * ns.x * a, sgn * b, -sgn * ns.x);
  vec3 bt = vec3(b, sgn + ns.y * ns.y * a, -ns.y);
  vec3 woL = vec3(dot(wo, t), dot(wo, bt), dot(wo, ns));
  vec4 m[${nTex}];
  lookup(vUv, m);
  gRho = vec3(${ch(0)}, ${ch(1)}, ${ch(2)});
${latents.map((l, i) => `  ${l} = ${ch(3 + i)};`).join("\n")}
  vec3 pbrBase = vec3(${ch(K + 3)}, ${ch(K + 4)}, ${ch(K + 5)});
  float pbrRough = ${ch(K + 6)}, pbrMetal = ${ch(K + 7)};
  vec3 probs = vec3(1.0, 0.0, 0.0);
  vec2 alphas = vec2(1.0);
  if (uMode == 0) {
    vec4 y[1];
    auxEval(${woIn}, y);
    vec4 tr = 1.0 / (1.0 + exp(-y[0]));
    gT = tr.rgb;
    vec4 z[2];
    smpEval(${woIn}, z);
    vec3 e = exp(z[0].xyz - max(z[0].x, max(z[0].y, z[0].z)));
    vec3 lobes = e / (e.x + e.y + e.z);
    alphas = 1e-3 + (1.0 - 1e-3) / (1.0 + exp(-vec2(z[0].w, z[1].x)));
    float diffuse = dot(gT * gRho, vec3(0.2126, 0.7152, 0.0722));
    float pd = diffuse + tr.a > 0.0 ? diffuse / max(diffuse + tr.a, 1e-12) : 1.0;
    probs = (1.0 - pd) * lobes;
    probs.x += pd;
    probs = 0.9 * probs;   // P_COSINE_MIN
    probs.x += 0.1;
  }
  vec3 sum = vec3(0.0);
  for (int k = 0; k < uSpp; k++) {
    uint n = uFrame * uint(uSpp) + uint(k);
    // Light sampling (next-event estimation), MIS-weighted against BSDF sampling in the neural mode.
    float pdf; vec3 le;
    vec3 dir = sampleEnv(rand2(n, 0u), pdf, le);
    vec3 wi = vec3(dot(dir, t), dot(dir, bt), dot(dir, ns));
    if (wi.z > 0.0 && dot(dir, ng) > 0.0 && pdf > 0.0) {
      vec3 f;
      float w = 1.0;
      if (uMode == 0) {
        f = neuralEval(wi, woL);
        float pb = mixturePdf(wi, woL, probs, alphas);
        w = pdf / (pdf + pb);
      } else if (uMode == 1) {
        f = pbrEval(wi, woL, pbrBase, pbrRough, pbrMetal);
      } else {
        f = woL.z > 0.0 ? gRho / PI : vec3(0.0);
      }
      sum += f * wi.z * le * (w / pdf);
    }
    if (uMode != 0) continue;
    // BSDF sampling (NeuralMaterial.sample); the ray leaves the convex object and sees the map.
    vec2 ud = rand2(n, 1u);
    float ul = rand2(n, 2u).x;
    vec3 wb = ul < probs.x ? cosineSample(ud) : ggxSample(woL, ul < probs.x + probs.y ? alphas.x : alphas.y, ud);
    float pb = mixturePdf(wb, woL, probs, alphas);
    vec3 wbWorld = wb.x * t + wb.y * bt + wb.z * ns;
    if (pb > 0.0 && wb.z > 0.0 && dot(wbWorld, ng) > 0.0) {
      vec3 f = neuralEval(wb, woL);
      float pl = envPdf(wbWorld);
      sum += f * wb.z / pb * envLookup(dirToUv(wbWorld)) * (pb / (pb + pl));
    }
  }
  outColor = previous() + vec4(sum / float(uSpp), 1.0);
}`;
  }

  const FS_DISPLAY = `
uniform sampler2D uAccum;
uniform float uExposure;
uniform float uCount;
out vec4 outColor;
// capture/tonemap.Tonemap: clip(exposure * x, 0, 1), then the sRGB OETF.
vec3 oetf(vec3 x) {
  vec3 power = 1.055 * pow(max(x, vec3(1e-12)), vec3(1.0 / 2.4)) - 0.055;
  return mix(power, 12.92 * x, lessThanEqual(x, vec3(0.0031308)));
}
void main() {
  vec3 c = texelFetch(uAccum, ivec2(gl_FragCoord.xy), 0).rgb / max(uCount, 1.0);
  outColor = vec4(oetf(clamp(c * uExposure, 0.0, 1.0)), 1.0);
}`;

  // ---------------------------------------------------------------------------------------------------------
  const gl = canvas.getContext("webgl2", { antialias: false, alpha: false, depth: false,
    preserveDrawingBuffer: true, powerPreference: "high-performance" });
  if (!gl) fail("this browser has no WebGL2");
  if (!gl.getExtension("EXT_color_buffer_float")) fail("this browser cannot render to float buffers (EXT_color_buffer_float)");

  function compile(type, source) {
    const s = gl.createShader(type);
    gl.shaderSource(s, source);
    gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) fail("shader: " + gl.getShaderInfoLog(s));
    return s;
  }
  function program(vs, fs) {
    const p = gl.createProgram();
    gl.attachShader(p, compile(gl.VERTEX_SHADER, vs));
    gl.attachShader(p, compile(gl.FRAGMENT_SHADER, fs));
    gl.linkProgram(p);
    if (!gl.getProgramParameter(p, gl.LINK_STATUS)) fail("program: " + gl.getProgramInfoLog(p));
    const loc = {};
    const n = gl.getProgramParameter(p, gl.ACTIVE_UNIFORMS);
    for (let i = 0; i < n; i++) {
      const name = gl.getActiveUniform(p, i).name;
      loc[name] = gl.getUniformLocation(p, name);
    }
    return { p, loc };
  }
  function floatTexture(width, height, channels, data) {
    const fmt = { 1: [gl.R32F, gl.RED], 4: [gl.RGBA32F, gl.RGBA] }[channels];
    const t = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, t);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    gl.pixelStorei(gl.UNPACK_ALIGNMENT, 1);
    gl.texImage2D(gl.TEXTURE_2D, 0, fmt[0], width, height, 0, fmt[1], gl.FLOAT, data);
    return t;
  }
  async function fetchFloats(name) {
    const r = await fetch(name, { credentials: "same-origin" });
    if (!r.ok) fail(`${name}: HTTP ${r.status}`);
    return new Float32Array(await r.arrayBuffer());
  }

  // ---------------------------------------------------------------------------------------------------------
  const state = {
    mode: params.get("mode") || "neural", envName: params.get("envmap") || "", exposure: 1.0,
    spp: parseInt(params.get("spp") || "1", 10), background: params.get("background") !== "0",
    maxFrames: parseInt(params.get("frames") || "4096", 10), auto: params.get("auto") !== "0",
    camera: null, orbit: { azimuth: 0.0, elevation: 20.0, distance: 3.2, fov: 40.0 },
  };
  let bundle, progs, meshVao, corners, matTex, basisTex, envs = {}, env;
  let accum = [], fbo = [], depth, ping = 0, width = 0, height = 0;

  function resize(w, h) {
    width = w; height = h;
    canvas.width = w; canvas.height = h;
    accum.forEach((t) => gl.deleteTexture(t));
    fbo.forEach((f) => gl.deleteFramebuffer(f));
    if (depth) gl.deleteRenderbuffer(depth);
    depth = gl.createRenderbuffer();
    gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_COMPONENT24, w, h);
    accum = [floatTexture(w, h, 4, null), floatTexture(w, h, 4, null)];
    fbo = accum.map((t) => {
      const f = gl.createFramebuffer();
      gl.bindFramebuffer(gl.FRAMEBUFFER, f);
      gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, t, 0);
      gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_ATTACHMENT, gl.RENDERBUFFER, depth);
      if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) fail("float framebuffer incomplete");
      gl.clearColor(0, 0, 0, 0);
      gl.clear(gl.COLOR_BUFFER_BIT);
      return f;
    });
    reset();
  }
  function reset() {
    api.frames = 0;
    for (const f of fbo) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, f);
      gl.clearColor(0, 0, 0, 0);
      gl.clear(gl.COLOR_BUFFER_BIT);
    }
  }

  // Cameras in the torch convention (geometry/camera.py): c2w columns +X, +Y, +Z (OpenGL axes), intrinsics in px.
  function orbitCamera() {
    const o = state.orbit, az = o.azimuth * Math.PI / 180, el = o.elevation * Math.PI / 180;
    const eye = [o.distance * Math.cos(el) * Math.sin(az), o.distance * Math.sin(el), o.distance * Math.cos(el) * Math.cos(az)];
    const f = norm([-eye[0], -eye[1], -eye[2]]);
    const r = norm(cross(f, [0, 1, 0]));
    const u = cross(r, f);
    const fl = width / (2 * Math.tan(o.fov * Math.PI / 360));
    return { c2w: [r[0], u[0], -f[0], eye[0], r[1], u[1], -f[1], eye[1], r[2], u[2], -f[2], eye[2], 0, 0, 0, 1],
      flX: fl, flY: fl, cx: width / 2, cy: height / 2 };
  }
  function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
  function norm(a) { const l = Math.hypot(a[0], a[1], a[2]); return [a[0] / l, a[1] / l, a[2] / l]; }
  function camera() { return state.camera || orbitCamera(); }

  // Column-major view-projection for pixel-centre sampling at image point (i + jx, j + jy) (pixel i, j, y down).
  function viewProj(cam, jx, jy) {
    const m = cam.c2w; // row-major 4x4
    const R = [[m[0], m[1], m[2]], [m[4], m[5], m[6]], [m[8], m[9], m[10]]];
    const pos = [m[3], m[7], m[11]];
    // world-to-camera: R^T (p - pos)
    const view = [];
    for (let r = 0; r < 3; r++) {
      const row = [R[0][r], R[1][r], R[2][r]];
      view.push([row[0], row[1], row[2], -(row[0] * pos[0] + row[1] * pos[1] + row[2] * pos[2])]);
    }
    view.push([0, 0, 0, 1]);
    const cx = cam.cx + 0.5 - jx, cy = cam.cy + 0.5 - jy;
    const near = 0.01, far = 100.0;
    const proj = [
      [2 * cam.flX / width, 0, -(2 * cx / width - 1), 0],
      [0, 2 * cam.flY / height, -(1 - 2 * cy / height), 0],
      [0, 0, -(far + near) / (far - near), -2 * far * near / (far - near)],
      [0, 0, -1, 0],
    ];
    const out = new Float32Array(16);
    for (let r = 0; r < 4; r++) for (let c = 0; c < 4; c++) {
      let s = 0;
      for (let k = 0; k < 4; k++) s += proj[r][k] * view[k][c];
      out[c * 4 + r] = s;
    }
    return { matrix: out, rot: new Float32Array([R[0][0], R[1][0], R[2][0], R[0][1], R[1][1], R[2][1], R[0][2], R[1][2], R[2][2]]), pos };
  }

  function bindEnv(p, unit) {
    gl.activeTexture(gl.TEXTURE0 + unit);
    gl.bindTexture(gl.TEXTURE_2D, env.tex);
    gl.uniform1i(p.loc.uEnv, unit);
    gl.activeTexture(gl.TEXTURE0 + unit + 1);
    gl.bindTexture(gl.TEXTURE_2D, env.cdf);
    gl.uniform1i(p.loc.uCdf, unit + 1);
    gl.uniform2i(p.loc.uEnvSize, env.width, env.height);
  }

  function jitter(n) {  // R2 sequence over frames
    return [(0.5 + n * 0.7548776662466927) % 1, (0.5 + n * 0.5698402909980532) % 1];
  }

  function renderFrame() {
    const cam = camera();
    const [jx, jy] = jitter(api.frames);
    const vp = viewProj(cam, jx, jy);
    const src = accum[ping], dst = fbo[1 - ping];
    gl.bindFramebuffer(gl.FRAMEBUFFER, dst);
    gl.viewport(0, 0, width, height);
    // background
    gl.disable(gl.DEPTH_TEST);
    let p = progs.background;
    gl.useProgram(p.p);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, src);
    gl.uniform1i(p.loc.uAccum, 0);
    bindEnv(p, 1);
    gl.uniformMatrix3fv(p.loc.uCamRot, false, vp.rot);
    gl.uniform4f(p.loc.uIntrinsics, cam.flX, cam.flY, cam.cx, cam.cy);
    gl.uniform3f(p.loc.uImage, width, height, state.background ? 1 : 0);
    gl.uniform2f(p.loc.uJitter, jx, jy);
    gl.bindVertexArray(null);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    // mesh
    gl.enable(gl.DEPTH_TEST);
    gl.depthFunc(gl.LESS);
    gl.clear(gl.DEPTH_BUFFER_BIT);
    p = progs.mesh;
    gl.useProgram(p.p);
    gl.uniform1i(p.loc.uAccum, 0);
    bindEnv(p, 1);
    matTex.forEach((t, i) => {
      gl.activeTexture(gl.TEXTURE3 + i);
      gl.bindTexture(gl.TEXTURE_2D, t);
      gl.uniform1i(p.loc[`uMat${i}`], 3 + i);
    });
    gl.activeTexture(gl.TEXTURE3 + matTex.length);
    gl.bindTexture(gl.TEXTURE_2D, basisTex);
    gl.uniform1i(p.loc.uBasis, 3 + matTex.length);
    gl.uniform1i(p.loc.uMatSize, bundle.material.resolution);
    gl.uniform1i(p.loc.uMode, { neural: 0, pbr: 1, base_color: 2 }[state.mode] ?? 0);
    gl.uniform3f(p.loc.uCamPos, vp.pos[0], vp.pos[1], vp.pos[2]);
    gl.uniformMatrix4fv(p.loc.uViewProj, false, vp.matrix);
    gl.uniform1ui(p.loc.uFrame, api.frames);
    gl.uniform1i(p.loc.uSpp, state.spp);
    gl.bindVertexArray(meshVao);
    gl.drawArrays(gl.TRIANGLES, 0, corners);
    gl.bindVertexArray(null);
    ping = 1 - ping;
    api.frames += 1;
    display();
    statusEl.textContent = `${api.frames} frames x ${state.spp} samples/pixel` +
      (api.lastFrameMs ? `, ${api.lastFrameMs.toFixed(0)} ms/frame` : "");
  }

  function display() {
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, width, height);
    gl.disable(gl.DEPTH_TEST);
    const p = progs.display;
    gl.useProgram(p.p);
    gl.activeTexture(gl.TEXTURE0);
    gl.bindTexture(gl.TEXTURE_2D, accum[ping]);
    gl.uniform1i(p.loc.uAccum, 0);
    gl.uniform1f(p.loc.uExposure, state.exposure);
    gl.uniform1f(p.loc.uCount, api.frames);
    gl.drawArrays(gl.TRIANGLES, 0, 3);
  }

  // ---------------------------------------------------------------------------------------------------------
  async function loadEnv(name) {
    if (!envs[name]) {
      const e = bundle.envmaps.find((m) => m.name === name);
      if (!e) fail(`no map named ${name}`);
      const data = await fetchFloats(e.file);
      const n = e.width * e.height * 4;
      envs[name] = { width: e.width, height: e.height, tex: floatTexture(e.width, e.height, 4, data.subarray(0, n)),
        cdf: floatTexture(e.width + 1, e.height + 1, 1, data.subarray(n)) };
    }
    env = envs[name];
    state.envName = name;
    ui.envmap.value = name;
    reset();
  }

  async function load() {
    const r = await fetch("bundle.json", { credentials: "same-origin" });
    if (!r.ok) fail(`bundle.json: HTTP ${r.status}`);
    bundle = await r.json();
    document.getElementById("title").textContent = bundle.name;
    document.title = `${bundle.name} - NeuMatEx viewer`;
    const [mesh, mat, basis] = await Promise.all([fetchFloats(bundle.mesh.file), fetchFloats(bundle.material.file),
      fetchFloats(bundle.basis.file)]);
    // mesh
    corners = bundle.mesh.corners;
    meshVao = gl.createVertexArray();
    gl.bindVertexArray(meshVao);
    const vbo = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, vbo);
    gl.bufferData(gl.ARRAY_BUFFER, mesh, gl.STATIC_DRAW);
    [[0, 3, 0], [1, 3, 3], [2, 2, 6], [3, 3, 8]].forEach(([loc, n, off]) => {
      gl.enableVertexAttribArray(loc);
      gl.vertexAttribPointer(loc, n, gl.FLOAT, false, 44, off * 4);
    });
    gl.bindVertexArray(null);
    // material textures: [R, R, C] -> C / 4 RGBA32F textures
    const res = bundle.material.resolution, nc = bundle.material.channels;
    matTex = Array.from({ length: nc / 4 }, (_, k) => {
      const part = new Float32Array(res * res * 4);
      for (let i = 0; i < res * res; i++) for (let c = 0; c < 4; c++) part[i * 4 + c] = mat[i * nc + k * 4 + c];
      return floatTexture(res, res, 4, part);
    });
    // programs and the basis's uniform blocks
    const b = bundle.basis;
    progs = {
      background: program(VS_QUAD, PRELUDE + COMMON + FS_BACKGROUND),
      mesh: program(VS_MESH, PRELUDE + COMMON + meshFragmentSource(b, bundle.material)),
      display: program(VS_QUAD, PRELUDE + FS_DISPLAY),
    };
    const texels = Math.ceil(basis.length / 4);
    const rows = Math.ceil(texels / WEIGHT_WIDTH);
    const padded = new Float32Array(rows * WEIGHT_WIDTH * 4);
    padded.set(basis);
    basisTex = floatTexture(WEIGHT_WIDTH, rows, 4, padded);
    // the menu of maps
    for (const e of bundle.envmaps) {
      const o = document.createElement("option");
      o.value = o.textContent = e.name;
      ui.envmap.appendChild(o);
    }
    state.orbit.distance = Math.max(1.5, 3.2 * (bundle.bounds_radius || 1));
    const size = parseInt(params.get("size") || "0", 10) || Math.min(window.innerWidth, window.innerHeight, 1024);
    resize(size, size);
    await loadEnv(bundle.envmaps.some((e) => e.name === state.envName) ? state.envName : bundle.default_envmap);
    ui.mode.value = state.mode;
    ui.spp.value = String(state.spp);
    ui.background.checked = state.background;
  }

  // ---------------------------------------------------------------------------------------------------------
  // UI: orbit by dragging, zoom with the wheel, menus.
  let drag = null;
  canvas.addEventListener("pointerdown", (e) => { drag = [e.clientX, e.clientY]; canvas.setPointerCapture(e.pointerId); });
  canvas.addEventListener("pointerup", () => { drag = null; });
  canvas.addEventListener("pointermove", (e) => {
    if (!drag) return;
    state.camera = null;
    state.orbit.azimuth -= (e.clientX - drag[0]) * 0.4;
    state.orbit.elevation = Math.max(-89, Math.min(89, state.orbit.elevation + (e.clientY - drag[1]) * 0.4));
    drag = [e.clientX, e.clientY];
    reset();
  });
  canvas.addEventListener("wheel", (e) => {
    e.preventDefault();
    state.camera = null;
    state.orbit.distance = Math.max(1.05, Math.min(20, state.orbit.distance * Math.exp(e.deltaY * 0.001)));
    reset();
  }, { passive: false });
  ui.mode.addEventListener("change", () => { state.mode = ui.mode.value; reset(); });
  ui.envmap.addEventListener("change", () => loadEnv(ui.envmap.value));
  ui.exposure.addEventListener("input", () => { state.exposure = Math.pow(2, parseFloat(ui.exposure.value)); display(); });
  ui.spp.addEventListener("change", () => { state.spp = parseInt(ui.spp.value, 10); });
  ui.background.addEventListener("change", () => { state.background = ui.background.checked; reset(); });

  function loop() {
    if (state.auto && api.frames < state.maxFrames) {
      const t0 = performance.now();
      renderFrame();
      api.lastFrameMs = performance.now() - t0;
    }
    requestAnimationFrame(loop);
  }

  // Programmatic control (tests, benchmarks, screenshots).
  Object.assign(api, {
    setAuto(on) { state.auto = !!on; },
    setMode(mode) { state.mode = mode; ui.mode.value = mode; reset(); },
    setSpp(n) { state.spp = n; ui.spp.value = String(n); },
    setBackground(on) { state.background = !!on; reset(); },
    setExposure(x) { state.exposure = x; display(); },
    setEnvmap(name) { return loadEnv(name); },
    resize(w, h) { resize(w, h); },
    // c2w: row-major 4x4 (geometry/camera.py), intrinsics in pixels for the current canvas size.
    setCamera(c2w, flX, flY, cx, cy) { state.camera = { c2w, flX, flY, cx, cy }; reset(); },
    setOrbit(o) { state.camera = null; Object.assign(state.orbit, o); reset(); },
    // Render n frames now; resolves with the mean wall time per frame (GPU finished: readPixels waits for it).
    renderFrames(n) {
      const px = new Uint8Array(4);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
      const t0 = performance.now();
      for (let i = 0; i < n; i++) renderFrame();
      gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, px);
      api.lastFrameMs = (performance.now() - t0) / n;
      statusEl.textContent = `${api.frames} frames x ${state.spp} samples/pixel, ${api.lastFrameMs.toFixed(0)} ms/frame`;
      return api.lastFrameMs;
    },
    // The displayed image: 8-bit sRGB RGBA rows from the top, as a plain array.
    readDisplay() {
      display();
      const px = new Uint8Array(width * height * 4);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.readPixels(0, 0, width, height, gl.RGBA, gl.UNSIGNED_BYTE, px);
      return { width, height, data: Array.from(px) };
    },
    // The accumulated linear radiance (mean over frames), float32 RGBA rows from the bottom.
    readLinear() {
      const px = new Float32Array(width * height * 4);
      gl.bindFramebuffer(gl.FRAMEBUFFER, fbo[ping]);
      gl.readPixels(0, 0, width, height, gl.RGBA, gl.FLOAT, px);
      const n = Math.max(api.frames, 1);
      return { width, height, frames: api.frames, data: Array.from(px, (v) => v / n) };
    },
    info() {
      const dbg = gl.getExtension("WEBGL_debug_renderer_info");
      return { renderer: dbg ? gl.getParameter(dbg.UNMASKED_RENDERER_WEBGL) : gl.getParameter(gl.RENDERER),
        version: gl.getParameter(gl.VERSION), corners, material: bundle.material.resolution,
        envmaps: bundle.envmaps.map((e) => e.name), envmap: state.envName };
    },
  });

  api.ready = load().then(() => { requestAnimationFrame(loop); return true; }).catch((e) => {
    if (!api.error) { api.error = String(e); errorEl.textContent = api.error; }
    throw e;
  });
})();

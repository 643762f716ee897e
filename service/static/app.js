// The registration viewer: two clouds in (file input, drag and drop, or a demo pair) -> POST register
// (base64 float32) -> the source animated along the agent's trajectory onto the target, with the result.
import {
  AxesHelper,
  BufferGeometry,
  Color,
  Float32BufferAttribute,
  Matrix4,
  OrbitControls,
  PerspectiveCamera,
  Points,
  PointsMaterial,
  Scene,
  Sphere,
  Vector3,
  WebGLRenderer,
} from "./vendor/three.min.js";
import { CloudParseError, encodeCloud, parseCloud } from "./parsers.js";

const MAX_DRAWN = 100000; // points drawn per cloud (all of them are sent)
const FRAME_MS = 90; // animation: one trajectory step per frame
const COLORS = { source: 0xf28e2b, target: 0x4e79a7 };
const IDENTITY = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]];

const $ = (id) => document.getElementById(id);
// Everything the page knows; exposed for the browser test and the console.
const state = { source: null, target: null, result: null, frames: [], frame: 0, timer: null, busy: false };
window.pranetViewer = state;

// ---- messages ---------------------------------------------------------------------------------------

function setMessage(text, isError = false) {
  const el = $("message");
  el.textContent = text;
  el.classList.toggle("error", isError);
}

function errorText(status, body) {
  const detail = body && body.detail;
  if (Array.isArray(detail)) {
    return detail.map((d) => `${(d.loc || []).join(".")}: ${d.msg}`).join("; ");
  }
  return typeof detail === "string" ? detail : `HTTP ${status}`;
}

// ---- 3-D view ---------------------------------------------------------------------------------------

let view = null;

function createView() {
  const host = $("canvas-host");
  let renderer;
  try {
    renderer = new WebGLRenderer({ antialias: true });
  } catch (e) {
    const note = document.createElement("div");
    note.className = "notice";
    note.textContent = `3-D view unavailable (this browser has no WebGL): ${e.message}`;
    $("view").appendChild(note);
    return null;
  }
  renderer.setPixelRatio(window.devicePixelRatio || 1);
  renderer.setClearColor(new Color(0xf7f7f5));
  host.appendChild(renderer.domElement);
  const scene = new Scene();
  const camera = new PerspectiveCamera(45, 1, 0.01, 100);
  camera.position.set(2, 1.5, 2.5);
  const controls = new OrbitControls(camera, renderer.domElement);
  const axes = new AxesHelper(1);
  scene.add(axes);
  const v = { renderer, scene, camera, controls, axes, clouds: {}, center: [0, 0, 0], pending: false };
  controls.addEventListener("change", () => requestRender(v));
  new ResizeObserver(() => resize(v)).observe(host);
  resize(v);
  return v;
}

function resize(v) {
  const host = $("canvas-host");
  const w = Math.max(1, host.clientWidth);
  const h = Math.max(1, host.clientHeight);
  v.renderer.setSize(w, h, false);
  v.camera.aspect = w / h;
  v.camera.updateProjectionMatrix();
  requestRender(v);
}

function requestRender(v) {
  if (!v || v.pending) return;
  v.pending = true;
  requestAnimationFrame(() => {
    v.pending = false;
    v.renderer.render(v.scene, v.camera);
  });
}

// Clouds are drawn relative to a common centre c (the target's centroid): float32 keeps its precision
// for clouds far from the origin. A world transform T = [R, t] then draws as [R, R c + t - c].
function displayMatrix(T, c) {
  const R = [0, 1, 2].map((i) => T[i].slice(0, 3));
  const t = [0, 1, 2].map((i) => T[i][3] + R[i][0] * c[0] + R[i][1] * c[1] + R[i][2] * c[2] - c[i]);
  const m = new Matrix4();
  m.set(...R[0], t[0], ...R[1], t[1], ...R[2], t[2], 0, 0, 0, 1);
  return m;
}

function centroid(values) {
  const c = [0, 0, 0];
  const n = values.length / 3;
  for (let i = 0; i < values.length; i += 3) {
    c[0] += values[i];
    c[1] += values[i + 1];
    c[2] += values[i + 2];
  }
  return c.map((x) => x / n);
}

function drawnPositions(values, c) {
  const n = values.length / 3;
  const step = Math.max(1, Math.ceil(n / MAX_DRAWN));
  const out = new Float32Array(Math.ceil(n / step) * 3);
  let j = 0;
  for (let i = 0; i < n; i += step) {
    out[j++] = values[3 * i] - c[0];
    out[j++] = values[3 * i + 1] - c[1];
    out[j++] = values[3 * i + 2] - c[2];
  }
  return out.subarray(0, j);
}

function applyT(T, p) {
  return [0, 1, 2].map((i) => T[i][0] * p[0] + T[i][1] * p[1] + T[i][2] * p[2] + T[i][3]);
}

// Bounding sphere (drawn frame) of the target, the source as given, and the source at the final pose.
function fitCamera(v) {
  const pts = [];
  const c = v.center;
  const push = (values, T) => {
    const n = values.length / 3;
    const step = Math.max(1, Math.floor(n / 2000));
    for (let i = 0; i < n; i += step) {
      const p = applyT(T, [values[3 * i], values[3 * i + 1], values[3 * i + 2]]);
      pts.push(new Vector3(p[0] - c[0], p[1] - c[1], p[2] - c[2]));
    }
  };
  if (state.target) push(state.target.values, IDENTITY);
  if (state.source) push(state.source.values, IDENTITY);
  if (state.source && state.result) push(state.source.values, state.result.transform);
  if (!pts.length) return;
  const sphere = new Sphere().setFromPoints(pts);
  const r = Math.max(sphere.radius, 1e-9);
  v.camera.near = r / 100;
  v.camera.far = r * 100;
  v.camera.position.copy(sphere.center).add(new Vector3(1.2, 0.9, 1.6).normalize().multiplyScalar(r * 2.8));
  v.camera.updateProjectionMatrix();
  v.controls.target.copy(sphere.center);
  v.controls.update();
  v.axes.scale.setScalar(r * 0.3);
  for (const cloud of Object.values(v.clouds)) cloud.material.size = r * 0.015;
  requestRender(v);
}

function showCloud(role) {
  if (!view) return;
  const old = view.clouds[role];
  if (old) {
    view.scene.remove(old);
    old.geometry.dispose();
    old.material.dispose();
    delete view.clouds[role];
  }
  const cloud = state[role];
  if (!cloud) return;
  view.center = state.target ? state.target.centroid : cloud.centroid;
  for (const r of ["source", "target"]) {
    // the centre may have changed: rebuild both geometries relative to it
    if (r !== role && view.clouds[r] && state[r]) {
      view.clouds[r].geometry.setAttribute("position", new Float32BufferAttribute(drawnPositions(state[r].values, view.center), 3));
    }
  }
  const geometry = new BufferGeometry();
  geometry.setAttribute("position", new Float32BufferAttribute(drawnPositions(cloud.values, view.center), 3));
  const points = new Points(geometry, new PointsMaterial({ color: COLORS[role], size: 0.01, sizeAttenuation: true }));
  points.matrixAutoUpdate = false;
  view.clouds[role] = points;
  view.scene.add(points);
  fitCamera(view);
}

function setSourcePose(T) {
  if (!view || !view.clouds.source) return;
  view.clouds.source.matrix.copy(displayMatrix(T, view.center));
  view.clouds.source.matrixWorldNeedsUpdate = true;
  requestRender(view);
}

// ---- loading clouds ---------------------------------------------------------------------------------

function formatCount(n) {
  return n.toLocaleString("en-US");
}

function setCloud(role, name, values) {
  state[role] = { name, values, n: values.length / 3, centroid: centroid(values) };
  const info = $(`info-${role}`);
  info.textContent = `${name}: ${formatCount(values.length / 3)} points`;
  info.classList.remove("error");
  clearResult();
  showCloud(role);
  $("register").disabled = !(state.source && state.target);
  $("empty-hint").hidden = true;
  setMessage(state.source && state.target ? "ready: press Register" : `now the ${role === "source" ? "target" : "source"}`);
}

async function loadFile(role, file) {
  const info = $(`info-${role}`);
  info.textContent = `reading ${file.name} ...`;
  try {
    const values = parseCloud(file.name, await file.arrayBuffer());
    setCloud(role, file.name, values);
  } catch (e) {
    state[role] = null;
    $("register").disabled = true;
    info.textContent = e instanceof CloudParseError ? e.message : `${file.name}: ${e.message}`;
    info.classList.add("error");
  }
}

// A deterministic demo: an asymmetric shape and its copy turned by 40° and shifted, with a little noise.
function demoPair() {
  let seed = 12345;
  const random = () => {
    seed = (seed + 0x6d2b79f5) | 0;
    let t = Math.imul(seed ^ (seed >>> 15), 1 | seed);
    t = (t + Math.imul(t ^ (t >>> 7), 61 | t)) ^ t;
    return ((t ^ (t >>> 14)) >>> 0) / 4294967296;
  };
  const n = 3000;
  const src = new Float64Array(n * 3);
  for (let i = 0; i < n; i++) {
    const u = random() * 2 * Math.PI;
    const w = random() * 2 * Math.PI;
    let p;
    if (i < n * 0.8) {
      p = [(1 + 0.35 * Math.cos(w)) * Math.cos(u), (1 + 0.35 * Math.cos(w)) * Math.sin(u) * 0.6, 0.35 * Math.sin(w)];
    } else {
      p = [1.2 + 0.25 * Math.cos(u) * Math.sin(w), 0.25 * Math.sin(u) * Math.sin(w), 0.5 + 0.4 * Math.cos(w)];
    }
    src.set(p, 3 * i);
  }
  const a = (40 * Math.PI) / 180;
  const k = [1, 2, 3].map((x) => x / Math.sqrt(14));
  const [c, s] = [Math.cos(a), Math.sin(a)];
  const R = [0, 1, 2].map((i) => [0, 1, 2].map((j) => (i === j ? c : 0) + (1 - c) * k[i] * k[j]
    + s * [[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]][i][j]));
  const t = [0.3, -0.2, 0.15];
  const tgt = new Float64Array(n * 3);
  for (let i = 0; i < n; i++) {
    const p = [src[3 * i], src[3 * i + 1], src[3 * i + 2]];
    for (let r = 0; r < 3; r++) {
      tgt[3 * i + r] = R[r][0] * p[0] + R[r][1] * p[1] + R[r][2] * p[2] + t[r] + (random() - 0.5) * 0.01;
    }
  }
  setCloud("source", "demo source", src);
  setCloud("target", "demo target (source turned by 40°)", tgt);
}

// ---- registration -----------------------------------------------------------------------------------

function clearResult() {
  stop();
  state.result = null;
  state.frames = [];
  $("result").hidden = true;
  $("player").hidden = true;
  setSourcePose(IDENTITY);
}

async function register() {
  if (!state.source || !state.target || state.busy) return;
  clearResult();
  const body = {
    source: encodeCloud(state.source.values),
    target: encodeCloud(state.target.values),
    icp: $("opt-icp").checked,
    init: $("opt-init").value,
    return_trajectory: true,
  };
  if (body.init === "global") body.starts = Number($("opt-starts").value) || 24;
  const steps = $("opt-steps").value.trim();
  if (steps) {
    body.steps = steps.split(/[\s,]+/).map(Number);
    if (body.steps.some((n) => !Number.isInteger(n) || n < 0)) {
      setMessage("agent steps: whole numbers separated by commas, e.g. 20,40", true);
      return;
    }
  }
  const headers = { "Content-Type": "application/json" };
  const key = $("api-key").value.trim();
  if (key) headers.Authorization = `Bearer ${key}`;
  state.busy = true;
  $("register").disabled = true;
  setMessage(body.init === "global" ? "registering from every start rotation ..." : "registering ...");
  const t0 = performance.now();
  try {
    let response;
    try {
      response = await fetch("register", { method: "POST", headers, body: JSON.stringify(body) });
    } catch (e) {
      setMessage(`cannot reach the service: ${e.message}`, true);
      return;
    }
    const json = await response.json().catch(() => null);
    if (!response.ok) {
      if (response.status === 401) {
        setMessage(key ? "the API key was refused: check it" : "this server needs an API key: enter it above", true);
        $("api-key").focus();
      } else {
        setMessage(`HTTP ${response.status}: ${errorText(response.status, json)}`, true);
      }
      return;
    }
    showResult(json, performance.now() - t0);
  } finally {
    state.busy = false;
    $("register").disabled = !(state.source && state.target);
  }
}

function isIdentity(T) {
  return T.every((row, i) => row.every((x, j) => Math.abs(x - (i === j ? 1 : 0)) < 1e-12));
}

function rotationAngleAxis(T) {
  const tr = T[0][0] + T[1][1] + T[2][2];
  const angle = Math.acos(Math.min(1, Math.max(-1, (tr - 1) / 2)));
  const axis = [T[2][1] - T[1][2], T[0][2] - T[2][0], T[1][0] - T[0][1]];
  const norm = Math.hypot(...axis);
  return { deg: (angle * 180) / Math.PI, axis: norm > 1e-12 ? axis.map((x) => x / norm) : [0, 0, 0] };
}

function fmt(x, digits = 4) {
  return Number(x).toPrecision(digits);
}

// Fixed decimals without "-0.000000" for tiny negative values.
function fixed(x, digits) {
  const s = Number(x).toFixed(digits);
  return /^-0\.0*$/.test(s) ? s.slice(1) : s;
}

function showResult(r, roundTripMs) {
  state.result = r;
  const rot = rotationAngleAxis(r.transform);
  const t = r.translation;
  $("status-badge").textContent = r.status;
  $("status-badge").className = `badge ${r.status}`;
  $("confidence").textContent = `${r.confidence.toFixed(3)} (${r.status})`;
  $("rotation").textContent = `${rot.deg.toFixed(2)}° about [${rot.axis.map((x) => fixed(x, 3)).join(", ")}]`;
  $("translation").textContent = `[${t.map((x) => fmt(x)).join(", ")}] (|t| ${fmt(Math.hypot(...t))})`;
  $("icp").textContent = r.icp.applied
    ? `fitness ${fmt(r.icp.fitness, 3)}, inlier RMSE ${fmt(r.icp.inlier_rmse, 3)}`
    : "not applied";
  $("timing").textContent = `${Math.round(r.timing_ms.total)} ms on the server, ${Math.round(roundTripMs)} ms round trip`;
  $("model").textContent = `${r.model.name} ${r.model.version}`;
  $("transform").textContent = r.transform
    .map((row) => row.map((x) => fixed(x, 6).padStart(9)).join("  "))
    .join("\n");
  $("result").hidden = false;
  // Frames: the input, the global mode's start, every agent step, the final transform (after ICP).
  const frames = [{ label: "input (identity)", T: IDENTITY }];
  if (r.initial_transform && !isIdentity(r.initial_transform)) {
    frames.push({ label: "start rotation (global mode)", T: r.initial_transform });
  }
  for (const s of r.trajectory) frames.push({ label: `agent step ${s.step + 1}: ${s.action}`, T: s.transform });
  frames.push({ label: r.icp.applied ? "final: after ICP" : "final", T: r.transform });
  state.frames = frames;
  const slider = $("frame");
  slider.max = String(frames.length - 1);
  $("player").hidden = false;
  setMessage(r.status === "converged" ? "done" : "done, but the result looks suspect: check it", r.status !== "converged");
  if (view) fitCamera(view);
  play();
}

// ---- animation --------------------------------------------------------------------------------------

function showFrame(i) {
  state.frame = i;
  const f = state.frames[i];
  if (!f) return;
  $("frame").value = String(i);
  $("frame-label").textContent = `${i} / ${state.frames.length - 1}: ${f.label}`;
  setSourcePose(f.T);
}

function stop() {
  if (state.timer) clearInterval(state.timer);
  state.timer = null;
  $("play").textContent = "Play";
}

function play() {
  stop();
  if (!state.frames.length) return;
  if (state.frame >= state.frames.length - 1) state.frame = 0;
  showFrame(state.frame);
  $("play").textContent = "Pause";
  state.timer = setInterval(() => {
    if (state.frame >= state.frames.length - 1) {
      stop();
      return;
    }
    showFrame(state.frame + 1);
  }, FRAME_MS);
}

// ---- wiring -----------------------------------------------------------------------------------------

function wire() {
  for (const role of ["source", "target"]) {
    $(`file-${role}`).addEventListener("change", (e) => {
      if (e.target.files.length) loadFile(role, e.target.files[0]);
    });
    const zone = $(`drop-${role}`);
    zone.addEventListener("dragover", (e) => {
      e.preventDefault();
      zone.classList.add("over");
    });
    zone.addEventListener("dragleave", () => zone.classList.remove("over"));
    zone.addEventListener("drop", (e) => {
      e.preventDefault();
      zone.classList.remove("over");
      if (e.dataTransfer.files.length) loadFile(role, e.dataTransfer.files[0]);
    });
  }
  // Two files dropped on the view at once: the first is the source, the second the target.
  const viewEl = $("view");
  viewEl.addEventListener("dragover", (e) => e.preventDefault());
  viewEl.addEventListener("drop", (e) => {
    e.preventDefault();
    const files = [...e.dataTransfer.files];
    if (files.length >= 2) {
      loadFile("source", files[0]);
      loadFile("target", files[1]);
    } else if (files.length === 1) {
      loadFile(state.source ? "target" : "source", files[0]);
    }
  });
  $("demo").addEventListener("click", demoPair);
  $("register").addEventListener("click", register);
  $("opt-init").addEventListener("change", (e) => {
    $("row-starts").hidden = e.target.value !== "global";
  });
  $("play").addEventListener("click", () => (state.timer ? stop() : play()));
  $("frame").addEventListener("input", (e) => {
    stop();
    showFrame(Number(e.target.value));
  });
}

view = createView();
wire();
setMessage("load a source and a target cloud");

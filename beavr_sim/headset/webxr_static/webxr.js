// beavr_sim WebXR teleoperation page: an immersive session with hand tracking; every XR frame
// sends both hands' joints to the simulator over a WebSocket, and the twin it sends back is
// drawn in the session. Protocol version 1: docs/formats.md ("WebXR page messages").

import { CameraQuads } from "./camera_quad.js";
import { PanelOffset } from "./panel_offset.js";
import { TwinRenderer, lookAt, perspective } from "./twin_gl.js";

const PROTOCOL_VERSION = 1;
const PAGE_VERSION = "1";
const FINGERS = ["index-finger", "middle-finger", "ring-finger", "pinky-finger"];
const FINGER_JOINTS = ["metacarpal", "phalanx-proximal", "phalanx-intermediate",
  "phalanx-distal", "tip"];
// WebXR Hand Input joints in the specification's order (the detector's webxr25 layout).
const JOINTS = ["wrist", "thumb-metacarpal", "thumb-phalanx-proximal", "thumb-phalanx-distal",
  "thumb-tip", ...FINGERS.flatMap((f) => FINGER_JOINTS.map((j) => `${f}-${j}`))];
const THUMB_TIP = JOINTS.indexOf("thumb-tip");
const RING_TIP = JOINTS.indexOf("ring-finger-tip");
// Pinch (thumb tip to ring tip, the detector's pause gesture on the left hand), with hysteresis.
const PINCH_CLOSE_M = 0.015;
const PINCH_OPEN_M = 0.03;
// A frame is skipped (counted) rather than queued when the socket has this much unsent.
const MAX_BUFFERED_BYTES = 32 * 1024;
const DECIMALS = 1e5;

const byId = (id) => document.getElementById(id);
const ui = {
  status: byId("status"), start: byId("start"), pause: byId("pause"), ar: byId("ar"),
  arLabel: byId("ar-label"), twin: byId("twin-status"), stats: byId("stats"),
  scene: byId("scene-status"), canvas: byId("view"), overlay: byId("overlay"),
};

const state = {
  ws: null, session: null, mode: null, refSpace: null, paused: false, seq: 0, sent: 0,
  skipped: 0, pinch: { left: false, right: false }, server: null, twin: null,
  xrModes: [], previewDue: false, workMs: 0, frameMs: 0, lastFrame: null,
};

const gl = ui.canvas.getContext("webgl2", { xrCompatible: true, antialias: false });
const renderer = gl ? new TwinRenderer(gl) : null;
// The streamed cameras as quads in the scene (the overlay's panels are their page twins), moved
// by the user's offset (the page's buttons and keys; kept in localStorage).
const panelOffset = new PanelOffset(pageStorage());
const quads = gl ? new CameraQuads(gl, panelOffset) : null;

function pageStorage() {
  try {
    return window.localStorage;
  } catch {
    return null; // storage refused (a private window's policy): the offset lasts this page
  }
}

function round(x) {
  return Math.round(x * DECIMALS) / DECIMALS;
}

function send(message) {
  const ws = state.ws;
  if (!ws || ws.readyState !== WebSocket.OPEN) return false;
  ws.send(JSON.stringify(message));
  return true;
}

function connect() {
  const scheme = location.protocol === "https:" ? "wss" : "ws";
  const token = new URLSearchParams(location.search).get("token");
  const query = token ? `?token=${encodeURIComponent(token)}` : "";
  const ws = new WebSocket(`${scheme}://${location.host}/ws${query}`);
  state.ws = ws;
  ws.onopen = () => {
    send({ v: PROTOCOL_VERSION, type: "hello", agent: navigator.userAgent, page: PAGE_VERSION });
    updateUi();
  };
  ws.onclose = () => {
    state.ws = null;
    state.server = null;
    clearCameras();
    updateUi();
    setTimeout(connect, 1000);
  };
  ws.onmessage = (event) => {
    let msg;
    try {
      msg = JSON.parse(event.data);
    } catch {
      return;
    }
    if (msg.v !== PROTOCOL_VERSION) return;
    if (msg.type === "welcome") {
      state.server = msg;
    } else if (msg.type === "scene" && renderer) {
      renderer.setScene(msg);
      showScene();
    } else if (msg.type === "twin") {
      state.twin = msg;
      if (renderer) renderer.setPoses(msg.pose);
    } else if (msg.type === "camera") {
      showCamera(msg);
      if (quads) quads.update(msg);
    }
    requestPreview();
    updateUi();
  };
}

// A real camera's panel: the streamed image with its capture age, or NO SIGNAL (never the last
// image left showing as if live).
function showCamera(msg) {
  const root = byId("cameras");
  if (!root || typeof msg.name !== "string") return;
  const id = "camera-" + msg.name.replace(/[^A-Za-z0-9_-]/g, "_");
  let panel = document.getElementById(id);
  if (!panel) {
    panel = document.createElement("div");
    panel.id = id;
    panel.append(document.createElement("img"), document.createElement("p"));
    root.append(panel);
  }
  const [img, label] = panel.children;
  img.src = "data:image/jpeg;base64," + msg.jpeg;
  label.textContent = String(msg.label);
  label.className = msg.state === "live" ? "small" : "small nosignal";
}

// Nothing streams any more (the connection dropped): no panel keeps its last image.
function clearCameras() {
  const root = byId("cameras");
  if (root) root.replaceChildren();
  if (quads) quads.clear();
  byId("camera-status").textContent = "";
  byId("panel-move").hidden = true;
  requestPreview();
}

// The in-scene panels stepped by the user (a button's data-move, or a key), kept for next time.
const PANEL_KEYS = { ArrowLeft: "left", ArrowRight: "right", ArrowUp: "up", ArrowDown: "down",
  PageUp: "farther", PageDown: "nearer", Home: "reset" };

function movePanels(direction) {
  if (direction === "reset") panelOffset.reset();
  else panelOffset.step(direction);
  if (quads) quads.relayout();
  const [x, y, z] = panelOffset.value.map((v) => v.toFixed(1));
  byId("panel-offset").textContent = `moved (m): nearer ${-x}, right ${-y}, up ${z}`;
  requestPreview();
}

// One hand's joints in the session's reference space; a joint without a pose is null.
function readHand(frame, hand, side) {
  const p = [], q = [], r = [], points = [];
  for (let i = 0; i < JOINTS.length; i++) {
    const space = hand.get(JOINTS[i]);
    let pose = null;
    try {
      pose = space ? frame.getJointPose(space, state.refSpace) : null;
    } catch {
      pose = null;
    }
    if (!pose || !(pose.radius > 0)) {
      p.push(null, null, null);
      q.push(null, null, null, null);
      r.push(null);
      continue;
    }
    const a = pose.transform.position, o = pose.transform.orientation;
    p.push(round(a.x), round(a.y), round(a.z));
    q.push(round(o.x), round(o.y), round(o.z), round(o.w));
    r.push(round(pose.radius));
    points.push([a.x, a.y, a.z, pose.radius]);
  }
  const tip = (j) => p.slice(3 * j, 3 * j + 3);
  const [t, g] = [tip(THUMB_TIP), tip(RING_TIP)];
  let pinch = false;
  if (t[0] !== null && g[0] !== null) {
    const d = Math.hypot(t[0] - g[0], t[1] - g[1], t[2] - g[2]);
    pinch = state.pinch[side] ? d < PINCH_OPEN_M : d < PINCH_CLOSE_M;
  }
  state.pinch[side] = pinch;
  return { message: { p, q, r, pinch }, points };
}

function onXRFrame(time, frame) {
  const began = performance.now();
  const session = frame.session;
  session.requestAnimationFrame(onXRFrame);
  const hands = { right: null, left: null };
  const points = [];
  for (const source of session.inputSources) {
    if (source.hand && (source.handedness === "right" || source.handedness === "left")) {
      const hand = readHand(frame, source.hand, source.handedness);
      hands[source.handedness] = hand.message;
      points.push(...hand.points);
    }
  }
  const ws = state.ws;
  if (ws && ws.readyState === WebSocket.OPEN) {
    if (ws.bufferedAmount > MAX_BUFFERED_BYTES) {
      state.skipped++;
    } else {
      send({ v: PROTOCOL_VERSION, type: "hands", seq: ++state.seq,
        t: performance.timeOrigin + time, paused: state.paused, hands });
      state.sent++;
    }
  }
  const layer = session.renderState.baseLayer;
  const viewer = frame.getViewerPose(state.refSpace);
  gl.bindFramebuffer(gl.FRAMEBUFFER, layer.framebuffer);
  const passthrough = state.mode === "immersive-ar";
  gl.clearColor(0.08, 0.09, 0.11, passthrough ? 0 : 1);
  if (passthrough) gl.clearColor(0, 0, 0, 0);
  gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  if (!viewer) return;
  for (const view of viewer.views) {
    const viewport = layer.getViewport(view);
    gl.viewport(viewport.x, viewport.y, viewport.width, viewport.height);
    renderer.draw(view.projectionMatrix, view.transform.inverse.matrix, points);
    if (quads) quads.draw(view.projectionMatrix, view.transform.inverse.matrix);
  }
  // This page's own work per frame (ms, smoothed): what it costs the headset.
  state.workMs += 0.05 * (performance.now() - began - state.workMs);
  if (state.lastFrame !== null) state.frameMs += 0.05 * (time - state.lastFrame - state.frameMs);
  state.lastFrame = time;
}

async function start() {
  if (state.session) {
    await state.session.end();
    return;
  }
  const mode = ui.ar.checked ? "immersive-ar" : "immersive-vr";
  let session;
  try {
    session = await navigator.xr.requestSession(mode, {
      requiredFeatures: ["hand-tracking", "local-floor"],
      optionalFeatures: ["dom-overlay"],
      domOverlay: { root: ui.overlay },
    });
  } catch (err) {
    ui.status.textContent = `could not start the XR session: ${err.message || err}`;
    return;
  }
  try {
    if (gl.makeXRCompatible) await gl.makeXRCompatible();
    session.updateRenderState({ baseLayer: new XRWebGLLayer(session, gl) });
    state.refSpace = await session.requestReferenceSpace("local-floor");
  } catch (err) {
    ui.status.textContent = `the XR session could not be set up: ${err.message || err}`;
    await session.end();
    return;
  }
  state.session = session;
  state.mode = mode;
  session.addEventListener("end", () => {
    state.session = null;
    state.refSpace = null;
    send({ v: PROTOCOL_VERSION, type: "session", state: "ended", mode });
    updateUi();
    requestPreview();
  });
  send({ v: PROTOCOL_VERSION, type: "session", state: "started", mode });
  session.requestAnimationFrame(onXRFrame);
  updateUi();
}

function togglePause() {
  state.paused = !state.paused;
  updateUi();
}

function updateUi() {
  const connected = state.ws && state.ws.readyState === WebSocket.OPEN;
  const xr = state.xrModes.length > 0;
  ui.start.disabled = !(connected && xr);
  ui.start.textContent = state.session ? "Exit XR" : "Start";
  ui.pause.textContent = state.paused ? "Resume" : "Pause";
  ui.pause.classList.toggle("paused", state.paused);
  ui.arLabel.hidden = !state.xrModes.includes("immersive-ar");
  if (!navigator.xr) {
    ui.status.textContent = "This browser has no WebXR here: open the page over HTTPS " +
      "(or on localhost) in a headset's browser.";
  } else if (!connected) {
    ui.status.textContent = "connecting to the simulator...";
  } else if (!xr) {
    ui.status.textContent = "connected; this browser offers no immersive session";
  } else {
    const s = state.server || {};
    const scene = renderer && renderer.geomCount ? "" : " (waiting for the twin)";
    ui.status.textContent = state.session
      ? `in session (${state.mode}): your hands drive the robot${state.paused ? ", paused" : ""}`
      : `connected${s.task ? `: ${s.task}` : ""}${scene}. Press Start.`;
  }
  const twin = state.twin;
  if (twin) {
    const holds = Object.entries(twin.holds || {}).map(([k, v]) => `${k}: ${v}`).join(", ");
    ui.twin.textContent = `twin t=${twin.t.toFixed(1)} s${twin.paused ? ", paused" : ""}` +
      (holds ? `, holding (${holds})` : "");
  }
  ui.stats.textContent = state.sent
    ? `frames sent ${state.sent}, skipped ${state.skipped}; XR frame ${state.frameMs.toFixed(1)} ms` +
      `, page work ${state.workMs.toFixed(1)} ms`
    : "";
}

// What the twin is drawn with; meshes that could not be read are drawn as their boxes.
function showScene() {
  const s = renderer.meshStats;
  let text = `twin: ${renderer.geomCount} shapes, ${s.meshes} meshes ` +
    `(${s.triangles} triangles, read in ${s.ms.toFixed(0)} ms)`;
  if (s.failed) text += `; ${s.failed} could not be read, drawn as boxes: ${s.errors.join("; ")}`;
  ui.scene.textContent = text;
}

// Outside a session: the twin from behind the robot, redrawn when its poses change.
function requestPreview() {
  if (state.previewDue || state.session || !renderer) return;
  state.previewDue = true;
  requestAnimationFrame(() => {
    state.previewDue = false;
    if (state.session) return;
    const c = ui.canvas;
    const w = c.clientWidth * devicePixelRatio, h = c.clientHeight * devicePixelRatio;
    if (c.width !== w || c.height !== h) [c.width, c.height] = [w, h];
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    gl.viewport(0, 0, c.width, c.height);
    gl.clearColor(0.08, 0.09, 0.11, 1);
    gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    const projection = perspective(Math.PI / 3, c.width / Math.max(c.height, 1), 0.05, 20);
    const view = lookAt([0.0, 1.5, 0.25], [0, 0.8, -0.9], [0, 1, 0]);
    renderer.draw(projection, view);
    if (quads) quads.draw(projection, view);
  });
}

async function detectXR() {
  if (!navigator.xr) return;
  for (const mode of ["immersive-vr", "immersive-ar"]) {
    try {
      if (await navigator.xr.isSessionSupported(mode)) state.xrModes.push(mode);
    } catch {
      // not offered
    }
  }
}

if (quads) {
  quads.onShown = () => {
    const names = [...quads.quads.keys()].join(", ");
    byId("camera-status").textContent = names
      ? `in the scene: ${names} (${quads.shown} images shown)` : "";
    byId("panel-move").hidden = !names;
    requestPreview();
  };
}
for (const button of document.querySelectorAll("#panel-move button[data-move]")) {
  button.addEventListener("click", () => movePanels(button.dataset.move));
}
window.addEventListener("keydown", (event) => {
  const direction = PANEL_KEYS[event.key];
  if (!direction || byId("panel-move").hidden) return;
  event.preventDefault();
  movePanels(direction);
});
ui.start.addEventListener("click", start);
ui.pause.addEventListener("click", togglePause);
window.addEventListener("resize", requestPreview);
if (!gl) ui.status.textContent = "WebGL 2 is not available in this browser.";
detectXR().then(updateUi);
setInterval(updateUi, 500);
connect();
updateUi();

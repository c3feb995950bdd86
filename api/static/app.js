// Operator page of the cell service. Plain script, no build step: it talks only to /api/v1.
//
// Safety stance: the page never makes the arm move on its own. Jogging is a dead-man control —
// a continuous jog is started on press and kept alive by heartbeats only while the button is
// physically held; release, losing focus, hiding the page or losing the connection all stop
// the heartbeats AND send an explicit stop, so the arm halts even if one of the two is lost.
"use strict";

const API = "/api/v1";
const TOKEN_KEY = "cell.token";
const HEARTBEAT_MS = 100;
const STATUS_MS = 250;
const FRAME_MIN_MS = 150; // at most ~6-7 camera frames per second: enough to watch, light on CPU
const OFFLINE_AFTER_MS = 1500;

// Fallback only: what each role may do besides reading (api.auth.PERMISSIONS); the live
// answer comes from GET /me. STOP is not listed: every valid token may stop.
const ROLE_ACTIONS = {
  viewer: [],
  operator: ["jog", "locate", "approach", "track", "gripper"],
  plc: ["locate", "approach", "track"],
};

// Jog speed levels: linear mm/s -> angular deg/s for the rotation axes.
const ANGULAR_DEG_S = { 5: 2, 20: 5, 50: 10 };
const AXES = ["x", "y", "z", "rx", "ry", "rz"];

const $ = (id) => document.querySelector(`[data-testid="${id}"]`);

const state = {
  token: sessionStorage.getItem(TOKEN_KEY) || "",
  role: "",
  permissions: null, // from GET /me
  lastOk: 0, // time of the last successful response (connection watchdog)
  online: false,
  jog: null, // {btn, timer} while a jog button is held
  frames: 0,
  frameTimes: [],
  frameUrl: "",
  frameAgeS: NaN,
  lastJob: null, // the running job, or the last one this page saw, until it is shown finished
};

// ---------------------------------------------------------------------------------------------
// HTTP

class ApiError extends Error {
  constructor(words, status, code) {
    super(words);
    this.status = status; // kept for logic only; never shown to the operator
    this.code = code;
  }
}

// The operator reads words, not status codes: the server's message when it gives one,
// otherwise a sentence for the kind of failure.
const FALLBACK_WORDS = {
  400: "The request was not understood.",
  401: "The token was not accepted. Please log in again.",
  403: "Your role is not allowed to do this.",
  404: "The cell does not offer this function.",
  409: "The cell cannot do this now: it is busy or not ready.",
  422: "Some of the values entered are not valid.",
  429: "Too many requests; please wait a moment.",
  503: "The cell hardware is not available right now.",
};

function wordsFor(status, body) {
  const err = body && typeof body === "object" ? body.error : null;
  const said = err && typeof err.message === "string" ? err.message.trim() : "";
  if (status === 401) return `${FALLBACK_WORDS[401]}${said ? ` (${said})` : ""}`;
  if (said) return said;
  if (body && typeof body.detail === "string") return body.detail;
  if (FALLBACK_WORDS[status]) return FALLBACK_WORDS[status];
  return status >= 500 ? "The cell service had an internal problem." : "The request failed.";
}

async function api(method, path, body, { raw = false, timeoutMs = 5000 } = {}) {
  const headers = {};
  if (state.token) headers.Authorization = `Bearer ${state.token}`;
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const ctrl = new AbortController();
  const timer = setTimeout(() => ctrl.abort(), timeoutMs);
  let resp;
  try {
    resp = await fetch(API + path, {
      method, headers, cache: "no-store", signal: ctrl.signal,
      body: body === undefined ? undefined : JSON.stringify(body),
    });
  } catch (e) {
    throw new ApiError("The cell service cannot be reached. Check the network.", 0, "offline");
  } finally {
    clearTimeout(timer);
  }
  markOnline();
  if (!resp.ok) {
    let data = null;
    try { data = await resp.json(); } catch (e) { /* not JSON: use the fallback words */ }
    const code = data && data.error ? data.error.code : "";
    if (resp.status === 401 && state.token) logout(wordsFor(401, data));
    throw new ApiError(wordsFor(resp.status, data), resp.status, code);
  }
  if (raw) return resp;
  const text = await resp.text();
  return text ? JSON.parse(text) : {};
}

// ---------------------------------------------------------------------------------------------
// Messages and connection

let messageTimer = 0;
function say(words, kind = "error") {
  const el = $("message");
  el.textContent = words;
  el.className = `message ${kind === "error" ? "" : "info"}`;
  el.hidden = false;
  el.dataset.kind = kind;
  clearTimeout(messageTimer);
  messageTimer = setTimeout(() => { el.hidden = true; }, kind === "error" ? 15000 : 5000);
}

function markOnline() {
  state.lastOk = Date.now();
  if (!state.online) setOnline(true);
}

function setOnline(online) {
  state.online = online;
  const el = $("connection");
  el.dataset.state = online ? "online" : "offline";
  el.textContent = online ? "online" : "offline";
  if (!online) releaseJog("the connection to the cell was lost");
}

setInterval(() => {
  if (state.online && Date.now() - state.lastOk > OFFLINE_AFTER_MS) setOnline(false);
}, 250);

// ---------------------------------------------------------------------------------------------
// Login and role-based controls

function applyRole() {
  const everything = ["jog", "locate", "approach", "track", "gripper"];
  const granted = state.permissions || (state.role ? ROLE_ACTIONS[state.role] || [] : everything);
  const allowed = new Set(state.token ? granted : []);
  document.querySelectorAll("[data-needs]").forEach((el) => {
    el.disabled = !allowed.has(el.dataset.needs);
  });
  $("role").textContent = state.token ? `role: ${state.role || "unknown"}` : "";
  $("logout").hidden = !state.token;
  $("login").hidden = !!state.token;
  $("token").hidden = !!state.token;
}

// The server says which permissions the token has (GET /me), so the page disables exactly
// what the API would refuse. Against a service without /me the token is checked with
// /status and the role table below decides; the API still refuses what a role may not do.
async function fetchRole() {
  try {
    const me = await api("GET", "/me");
    return { role: me.role || "", permissions: me.permissions || null };
  } catch (e) {
    if (e.status !== 404) throw e;
  }
  await api("GET", "/status");
  return { role: "", permissions: null };
}

async function login(token) {
  state.token = token;
  try {
    ({ role: state.role, permissions: state.permissions } = await fetchRole());
  } catch (e) {
    state.token = "";
    state.role = "";
    applyRole();
    say(e.message);
    return false;
  }
  sessionStorage.setItem(TOKEN_KEY, token);
  applyRole();
  say(state.role ? `Logged in as ${state.role}.` : "Logged in.", "info");
  return true;
}

function logout(reason) {
  releaseJog("logged out");
  state.token = "";
  state.role = "";
  state.permissions = null;
  sessionStorage.removeItem(TOKEN_KEY);
  applyRole();
  if (reason) say(reason);
}

// ---------------------------------------------------------------------------------------------
// Status (robot state, pose, job) by polling: one small GET every 250 ms works through any
// proxy and lets the page notice a dead connection quickly.

const fmt = (v, digits = 1) => (Number.isFinite(v) ? v.toFixed(digits) : "–");
const deg = (rad) => (rad * 180) / Math.PI;

function showPose(pose) {
  if (!pose || !pose.position_mm) return "–";
  const [x, y, z] = pose.position_mm;
  // Rotation vector shown in degrees (same axis-angle as the pendant), not converted to RPY.
  const [rx, ry, rz] = pose.rotvec_rad.map(deg);
  return `x ${fmt(x)}  y ${fmt(y)}  z ${fmt(z)} mm · rx ${fmt(rx)}  ry ${fmt(ry)}  rz ${fmt(rz)} °`;
}

function renderStatus(s) {
  const robot = s.robot || {};
  $("state").textContent = [s.state, robot.mode, robot.safety].filter(Boolean).join(" · ") || "–";
  $("state").dataset.state = s.state || "";
  $("tcp-pose").textContent = robot.connected === false
    ? `arm not connected${robot.error ? `: ${robot.error}` : ""}` : showPose(robot.T_base_tcp);
  const pstop = !!robot.protective_stop;
  $("protective-stop").textContent = pstop ? "PROTECTIVE STOP" : "no";
  $("protective-stop").classList.toggle("bad", pstop);
  $("gripper-state").textContent = describeGripper(s.gripper);
  renderQuality(s.camera || {}, s.last_locate);
  if (s.job) {
    state.lastJob = s.job;
    renderJob(s.job);
  } else if (state.lastJob && state.lastJob.state === "running") {
    // The status only carries the running job; fetch how the last one ended.
    refreshLastJob();
  } else {
    renderJob(state.lastJob);
  }
}

function describeGripper(g) {
  if (!g) return "none";
  if (g.error) return `not available: ${g.error}`;
  if (g.fault) return `fault: ${g.fault}`;
  if (!g.activated) return "not activated";
  const width = Number.isFinite(g.position_mm) ? `${fmt(g.position_mm)} mm open` : "";
  return [width, g.moving ? "moving" : "", g.object_detected ? "holding an object" : ""]
    .filter(Boolean).join(", ") || "ready";
}

async function refreshLastJob() {
  const id = state.lastJob.id;
  try {
    const job = await api("GET", `/jobs/${encodeURIComponent(id)}`);
    if (state.lastJob && state.lastJob.id === id) state.lastJob = job;
  } catch (e) { /* shown as it was; the next status poll retries */ }
  renderJob(state.lastJob);
}

function renderJob(job) {
  const bar = $("job-progress");
  if (!job) {
    $("job").textContent = "none";
    bar.value = 0;
    return;
  }
  const p = job.progress || {};
  let text = `${job.kind || "job"} ${job.id}: ${job.state.replace(/_/g, " ")}`;
  if (job.state === "running") {
    // The number of look-and-move cycles is not known in advance: show the phase, and an
    // indeterminate bar rather than a made-up percentage.
    if (p.phase) text += ` — ${p.phase}${p.cycle ? `, cycle ${p.cycle}` : ""}`;
    bar.removeAttribute("value");
  } else {
    bar.value = job.state === "succeeded" ? 1 : 0;
    if (job.error && job.error.message) text += ` — ${job.error.message}`;
    const r = job.result || {};
    if (Number.isFinite(r.reach_error_mm)) text += ` — reached within ${fmt(r.reach_error_mm, 2)} mm`;
  }
  $("job").textContent = text;
  $("job").dataset.state = job.state;
  renderServo(p);
}

// The live servo error (approach mode "servo", tracking): the job's progress carries the
// newest error and a short history, plotted as a line (mm).
function renderServo(p) {
  const recent = Array.isArray(p.recent) ? p.recent : [];
  if (!Number.isFinite(p.error_mm)) return;
  $("servo-error").textContent = `error ${fmt(p.error_mm, 2)} mm / ${fmt(p.error_deg, 2)} deg`;
  const c = $("servo-plot");
  const g = c.getContext("2d");
  g.clearRect(0, 0, c.width, c.height);
  if (recent.length < 2) return;
  const t0 = recent[0].t_s, t1 = recent[recent.length - 1].t_s;
  const top = Math.max(...recent.map((r) => r.error_mm), 0.1);
  g.beginPath();
  recent.forEach((r, i) => {
    const x = ((r.t_s - t0) / Math.max(t1 - t0, 1e-3)) * (c.width - 1);
    const y = c.height - 1 - (r.error_mm / top) * (c.height - 2);
    if (i === 0) g.moveTo(x, y); else g.lineTo(x, y);
  });
  g.strokeStyle = "#2a7";
  g.stroke();
  g.fillStyle = "#888";
  g.fillText(`${fmt(top, 1)} mm`, 2, 10);
}

function renderQuality(cam, located) {
  const q = (located && located.quality) || {};
  $("quality-rms").textContent = Number.isFinite(q.rms_px) ? `${fmt(q.rms_px, 2)} px` : "–";
  $("quality-ambiguity").textContent = q.ambiguous === undefined ? "–"
    : q.ambiguous ? "AMBIGUOUS: two poses fit" : "unique";
  // Age of the frame on screen when the camera view gave it, else the cell's newest frame.
  const age = Number.isFinite(state.frameAgeS) ? state.frameAgeS : cam.last_frame_age_s;
  $("quality-age").textContent = Number.isFinite(age) ? `${Math.round(age * 1000)} ms`
    : cam.connected === false ? "camera not connected" : "–";
}

async function statusLoop() {
  for (;;) {
    const t0 = Date.now();
    if (!document.hidden) {
      try {
        if (state.token) renderStatus(await api("GET", "/status", undefined, { timeoutMs: 2000 }));
        else await api("GET", "/health", undefined, { timeoutMs: 2000 }); // connection light
      } catch (e) {
        if (e.status === 0) setOnline(false);
      }
    }
    await sleep(Math.max(0, STATUS_MS - (Date.now() - t0)));
  }
}

// ---------------------------------------------------------------------------------------------
// Camera: fetch (so the bearer token can go in a header), show as an object URL, repeat.

async function cameraLoop() {
  const img = $("camera");
  for (;;) {
    const t0 = Date.now();
    if (state.token && !document.hidden) {
      try {
        const resp = await api("GET", "/camera/frame.png?overlay=true", undefined,
          { raw: true, timeoutMs: 3000 });
        const age = Number(resp.headers.get("X-Frame-Age-S"));
        const url = URL.createObjectURL(await resp.blob());
        await new Promise((resolve) => {
          img.onload = resolve;
          img.onerror = resolve;
          img.src = url;
        });
        if (state.frameUrl) URL.revokeObjectURL(state.frameUrl);
        state.frameUrl = url;
        state.frames += 1;
        img.dataset.frames = String(state.frames);
        countFps();
        $("camera-note").textContent = "";
        if (resp.headers.has("X-Frame-Age-S") && Number.isFinite(age)) {
          state.frameAgeS = age;
          $("quality-age").textContent = `${Math.round(age * 1000)} ms`;
        }
      } catch (e) {
        state.frameAgeS = NaN;
        $("camera-note").textContent = e.message;
        await sleep(500);
      }
    }
    await sleep(Math.max(0, FRAME_MIN_MS - (Date.now() - t0)));
  }
}

function countFps() {
  const now = Date.now();
  state.frameTimes.push(now);
  while (state.frameTimes.length && now - state.frameTimes[0] > 2000) state.frameTimes.shift();
  $("camera-fps").textContent = `${fmt(state.frameTimes.length / 2, 1)} frames/s`;
}

// ---------------------------------------------------------------------------------------------
// Hold-to-jog

// Body of POST /jog (api.schemas.JogContinuous): one axis moving, in base or tool frame.
function jogRequest(axis, dir) {
  const speed = Number($("jog-speed").value);
  const linear = [0, 0, 0];
  const angular = [0, 0, 0];
  const i = AXES.indexOf(axis);
  if (i < 3) linear[i] = dir * speed;
  else angular[i - 3] = dir * (ANGULAR_DEG_S[speed] || 2);
  return { mode: "continuous", frame: $("jog-frame").value, linear_mm_s: linear,
           angular_deg_s: angular };
}

async function pressJog(btn) {
  if (state.jog || btn.disabled) return;
  const jog = { btn, timer: 0 };
  state.jog = jog;
  btn.classList.add("held");
  try {
    await api("POST", "/jog", jogRequest(btn.dataset.axis, Number(btn.dataset.dir)));
  } catch (e) {
    if (state.jog === jog) endJogLocally();
    say(e.message);
    return;
  }
  if (state.jog !== jog) {
    // Released while the start request was in flight: the jog began after release, stop it.
    sendStop();
    return;
  }
  jog.timer = setInterval(() => heartbeat(jog), HEARTBEAT_MS);
}

async function heartbeat(jog) {
  if (state.jog !== jog) return;
  try {
    await api("POST", "/jog/heartbeat", {}, { timeoutMs: 1000 });
  } catch (e) {
    if (state.jog === jog) releaseJog(e.message);
  }
}

function endJogLocally() {
  const jog = state.jog;
  if (!jog) return null;
  clearInterval(jog.timer);
  jog.btn.classList.remove("held");
  state.jog = null;
  return jog;
}

function releaseJog(reason) {
  const jog = endJogLocally();
  if (!jog) return;
  sendStop();
  if (reason && reason !== "released") say(`Jog stopped: ${reason}.`, "info");
}

function sendStop() {
  // keepalive lets the request finish even while the page is being hidden or closed.
  return fetch(`${API}/stop`, {
    method: "POST", keepalive: true, cache: "no-store",
    headers: { Authorization: `Bearer ${state.token}`, "Content-Type": "application/json" },
    body: JSON.stringify({ reason: "operator page: jog released" }),
  }).catch(() => { /* the server-side dead-man stops the arm when we cannot reach it */ });
}

function wireJogButtons() {
  document.querySelectorAll("button.jog").forEach((btn) => {
    btn.addEventListener("pointerdown", (ev) => {
      if (ev.button !== 0) return;
      ev.preventDefault();
      btn.setPointerCapture(ev.pointerId);
      pressJog(btn);
    });
    for (const type of ["pointerup", "pointercancel", "lostpointercapture"]) {
      btn.addEventListener(type, () => { if (state.jog && state.jog.btn === btn) releaseJog("released"); });
    }
    btn.addEventListener("contextmenu", (ev) => ev.preventDefault());
    // Keyboard: hold Space or Enter on a focused jog button.
    btn.addEventListener("keydown", (ev) => {
      if ((ev.key === " " || ev.key === "Enter") && !ev.repeat) { ev.preventDefault(); pressJog(btn); }
    });
    btn.addEventListener("keyup", (ev) => {
      if (ev.key === " " || ev.key === "Enter") releaseJog("released");
    });
    btn.addEventListener("blur", () => { if (state.jog && state.jog.btn === btn) releaseJog("released"); });
  });
  window.addEventListener("blur", () => releaseJog("the page lost focus"));
  window.addEventListener("pagehide", () => releaseJog("the page was closed"));
  document.addEventListener("visibilitychange", () => {
    if (document.hidden) releaseJog("the page was hidden");
  });
}

// ---------------------------------------------------------------------------------------------
// Commands

async function command(label, fn) {
  try {
    const result = await fn();
    if (result !== undefined) $("result").textContent = result;
  } catch (e) {
    say(`${label} failed: ${e.message}`);
  }
}

function wireCommands() {
  $("stop").addEventListener("click", async () => {
    endJogLocally();
    try {
      await api("POST", "/stop", { reason: "operator page: STOP button" });
      say("Stopped.", "info");
    } catch (e) {
      say(`STOP could not be sent: ${e.message}`);
    }
  });

  $("locate").addEventListener("click", () => command("Locate", async () => {
    const r = await api("POST", "/locate", {});
    const q = r.quality || {};
    return `target in base: ${showPose(r.T_base_target)}\n`
      + `rms ${fmt(q.rms_px, 2)} px, ${q.ambiguous ? "AMBIGUOUS" : "unique"} pose, `
      + `frame age ${Math.round((q.frame_age_s || 0) * 1000)} ms`;
  }));

  $("approach").addEventListener("click", () => command("Approach", async () => {
    const standoff = Number($("standoff").value);
    if (!Number.isFinite(standoff) || $("standoff").value === "" || standoff < 0) {
      throw new ApiError("the standoff must be a distance in millimetres, 0 or more", 0, "input");
    }
    const mode = $("approach-mode").value;
    const job = await api("POST", "/approach", { standoff_mm: standoff, mode, wait: false });
    state.lastJob = job;
    renderJob(job);
    return `${mode} approach started (job ${job.id})`;
  }));

  $("track-start").addEventListener("click", () => command("Track", async () => {
    const standoff = Number($("standoff").value);
    if (!Number.isFinite(standoff) || $("standoff").value === "" || standoff < 0) {
      throw new ApiError("the standoff must be a distance in millimetres, 0 or more", 0, "input");
    }
    const job = await api("POST", "/track", { standoff_mm: standoff, duration_s: 600 });
    state.lastJob = job;
    renderJob(job);
    return `tracking started (job ${job.id}); Stop tracking or STOP ends it`;
  }));

  $("track-stop").addEventListener("click", () => command("Stop tracking", async () => {
    await api("POST", "/stop", { reason: "stop tracking (operator page)" });
    return "tracking stopped";
  }));

  for (const action of ["open", "close"]) {
    $(`gripper-${action}`).addEventListener("click", () => command(`Gripper ${action}`, async () => {
      await api("POST", "/gripper", { action });
      return `gripper ${action} sent`;
    }));
  }

  $("login-form").addEventListener("submit", (ev) => {
    ev.preventDefault();
    const token = $("token").value.trim();
    if (!token) { say("Enter an access token first."); return; }
    $("token").value = "";
    login(token);
  });
  $("logout").addEventListener("click", () => logout(""));
}

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

function main() {
  wireJogButtons();
  wireCommands();
  applyRole();
  if (state.token) login(state.token);
  statusLoop();
  cameraLoop();
}

main();

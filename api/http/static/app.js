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
// The live view is one JPEG per camera frame shared by every viewer (GET /camera/frame.jpg);
// asking faster than the server produces frames only repeats one, so ~8 per second is enough.
const FRAME_MIN_MS = 125;
const ALARMS_MS = 1000;
const LOGS_MS = 3000;
const PAGE_ROWS = 8;
const OFFLINE_AFTER_MS = 1500;

// Fallback only: what each role may do besides reading (api.auth.PERMISSIONS); the live
// answer comes from GET /me. STOP is not listed: every valid token may stop.
const ROLE_ACTIONS = {
  viewer: [],
  operator: ["jog", "locate", "approach", "track", "gripper", "pick", "check_calibration", "camera",
    "alarm_ack"],
  plc: ["locate", "approach", "track", "pick", "check_calibration"],
};
// Controls marked data-needs="operator" (home, unlock, teach, calibration) need that role.
const OPERATOR_ONLY = "operator";

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
  resultJobId: "", // the job whose outcome the Tasks result line follows
  alarmOffset: 0,
  historyOffset: 0,
  calibJob: null,
  settingsLoaded: false,
  busy: false, // a job is running: motion controls are disabled
  frameQuality: null, // what the overlay of the frame on screen says (X-Locate-* headers)
  statusCamera: {}, // the last status's camera and last_locate, for the quality row
  lastLocate: null,
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
    const err = new ApiError(wordsFor(resp.status, data), resp.status, code);
    err.hadToken = !!headers.Authorization;
    if (resp.status === 401 && state.token) logout(wordsFor(401, data));
    throw err;
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

// A new attempt makes an earlier failure's words stale: they go as the next command starts,
// so a second failure is never read next to the first one's reason.
function clearError() {
  const el = $("message");
  if (el.dataset.kind !== "error") return;
  clearTimeout(messageTimer);
  el.hidden = true;
  el.textContent = "";
  el.dataset.kind = "";
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
  const everything = [...ROLE_ACTIONS.operator, OPERATOR_ONLY];
  const granted = state.permissions || (state.role ? ROLE_ACTIONS[state.role] || [] : everything);
  const allowed = new Set(state.token ? granted : []);
  if (state.token && state.role === "operator") allowed.add(OPERATOR_ONLY);
  // While a job runs, nothing else may start the arm (the cell would refuse it as busy):
  // only STOP, Stop tracking and the non-motion controls stay live. A held jog button keeps
  // its state so its release still stops the jog.
  document.querySelectorAll("[data-needs]").forEach((el) => {
    const busy = state.busy && "motion" in el.dataset && !(state.jog && state.jog.btn === el);
    el.disabled = !allowed.has(el.dataset.needs) || busy;
  });
  if (!state.calibJob || state.calibJob.state !== "succeeded") $("calib-apply").disabled = true;
  applyRecipeChoice();
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
  state.settingsLoaded = false;
  loadTaught();
  loadRecipes();
  loadCameraSettings();
  refreshLogs();
  refreshImages();
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

// A value that rounds to zero reads "0.0", never "-0.0" (a sign that means nothing).
const fmt = (v, digits = 1) => {
  if (!Number.isFinite(v)) return "–";
  const t = v.toFixed(digits);
  return /^-0(\.0*)?$/.test(t) ? t.slice(1) : t;
};
const deg = (rad) => (rad * 180) / Math.PI;

// One rotation has many rotation vectors: angle theta about u equals 2 pi - theta about -u,
// and at exactly pi both u and -u. The page shows the one the cell reports
// (estimator.transforms.canonical_rotvec): angle in [0, pi], except within PI_BAND of pi, where
// the two readings look alike ("180.0") and the one whose axis has its first non-zero
// component positive is shown (the same rotation, so its angle may pass pi by up to PI_BAND).
// The same pose never reads once as rx -127.3 ry -127.3 and once as +127.3 +127.3.
const PI_BAND = 1e-3;
function canonicalRotvec(r) {
  let theta = Math.hypot(...r);
  if (!Number.isFinite(theta) || theta < 1e-12) return [0, 0, 0];
  let u = r.map((v) => v / theta);
  theta %= 2 * Math.PI;
  if (theta > Math.PI) { theta = 2 * Math.PI - theta; u = u.map((v) => -v); }
  if (Math.PI - theta <= PI_BAND && (u.find((v) => Math.abs(v) > 1e-6) || 1) < 0) {
    theta = 2 * Math.PI - theta;
    u = u.map((v) => -v);
  }
  return u.map((v) => v * theta);
}

function showPose(pose) {
  if (!pose || !pose.position_mm) return "–";
  const [x, y, z] = pose.position_mm;
  // Rotation vector shown in degrees (same axis-angle as the pendant), not converted to RPY.
  const [rx, ry, rz] = canonicalRotvec(pose.rotvec_rad).map(deg);
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
  state.statusCamera = s.camera || {};
  state.lastLocate = s.last_locate;
  renderQuality(state.statusCamera, state.lastLocate);
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
    if (job.state !== "running") { refreshLogs(); refreshAlarms(); }
  } catch (e) { /* shown as it was; the next status poll retries */ }
  renderJob(state.lastJob);
}

function renderJob(job) {
  const bar = $("job-progress");
  if (!job) {
    $("job").textContent = "none";
    bar.value = 0;
    setBusy(false);
    return;
  }
  const p = job.progress || {};
  let text = `${job.kind || "job"} ${job.id}${recipeLabel(job)}: ${job.state.replace(/_/g, " ")}`;
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
    if (r.part) text += ` — ${describePick(r)}`;
  }
  $("job").textContent = text;
  $("job").title = text;
  setBusy(job.state === "running");
  $("job").dataset.state = job.state;
  if (job.id === state.resultJobId) $("result").textContent = text;
  renderServo(p);
}

// A pick's line: the part it took, the grip, where it went, and each phase's seconds.
function describePick(r) {
  const phases = Object.entries(r.phases_s || {}).map(([k, v]) => `${k} ${fmt(v, 1)} s`).join(", ");
  const where = r.place ? `placed at ${r.place.taught}` : "kept in the gripper";
  return `part ${r.part.id} of ${r.part.parts_seen}, grip ${r.grip.verdict} at `
    + `${fmt(r.grip.width_mm, 1)} mm, ${where}; ${fmt(r.cycle_s, 1)} s (${phases})`;
}

function setBusy(busy) {
  if (state.busy === busy) return;
  state.busy = busy;
  document.body.dataset.busy = String(busy);
  applyRole();
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

// The quality row says what the overlay of the frame on screen says (the live view's
// X-Locate-* headers: the same estimate that drew it); only without a live view does it fall
// back to the last locate's quality, labelled as such.
function renderQuality(cam, located) {
  const live = state.frameQuality;
  const q = live ? live : (located && located.quality) || {};
  const row = $("quality-rms");
  row.dataset.source = live ? "live" : "last-locate";
  if (live && !live.located) {
    row.textContent = "not located"; // the reason in full is on the image, and on hover
    row.title = live.error || "";
    $("quality-ambiguity").textContent = "–";
  } else {
    row.title = "";
    const rms = Number.isFinite(q.rms_px) ? `${fmt(q.rms_px, 2)} px` : "–";
    row.textContent = live || rms === "–" ? rms : `${rms} (last locate)`;
    $("quality-ambiguity").textContent = q.ambiguous === undefined || q.ambiguous === null ? "–"
      : q.ambiguous ? "AMBIGUOUS: two poses fit" : "unique";
  }
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
        const resp = await api("GET", "/camera/frame.jpg?overlay=true", undefined,
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
        state.frameQuality = frameQuality(resp.headers);
        renderQuality(state.statusCamera, state.lastLocate);
        if (resp.headers.has("X-Frame-Age-S") && Number.isFinite(age)) {
          state.frameAgeS = age;
          $("quality-age").textContent = `${Math.round(age * 1000)} ms`;
        }
      } catch (e) {
        state.frameAgeS = NaN;
        state.frameQuality = null;
        $("camera-note").textContent = e.message;
        await sleep(500);
      }
    }
    await sleep(Math.max(0, FRAME_MIN_MS - (Date.now() - t0)));
  }
}

function frameQuality(headers) {
  const located = headers.get("X-Located");
  if (located === null) return null;
  if (located !== "true") {
    return { located: false, error: headers.get("X-Locate-Error") || "" };
  }
  const amb = headers.get("X-Locate-Ambiguous");
  return { located: true, rms_px: Number(headers.get("X-Locate-Rms-Px")),
           ambiguous: amb === null ? undefined : amb === "true" };
}

function countFps() {
  const now = Date.now();
  state.frameTimes.push(now);
  while (state.frameTimes.length && now - state.frameTimes[0] > 2000) state.frameTimes.shift();
  $("camera-fps").textContent = `${fmt(state.frameTimes.length / 2, 1)} frames/s`;
}

// ---------------------------------------------------------------------------------------------
// Hold-to-jog

// Body of POST /jog (api.http.schemas.JogContinuous): one axis moving, in base or tool frame.
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

// STOP needs no login: the cell takes a STOP without a token ([api] anonymous_stop, on by
// default). Logged out the page sends it without one; a token the cell no longer accepts
// logs the page out (api) and the STOP goes again without it, so STOP never fails for a login.
async function stopNow(reason) {
  try {
    return await api("POST", "/stop", { reason });
  } catch (e) {
    if (e.status !== 401) throw e;
    if (!e.hadToken) {
      throw new ApiError("STOP without a login is switched off on this cell; log in to stop.",
        e.status, e.code);
    }
    return stopNow(reason); // api() has logged out: this one goes without the token
  }
}

function sendStop() {
  // keepalive lets the request finish even while the page is being hidden or closed.
  const headers = { "Content-Type": "application/json" };
  if (state.token) headers.Authorization = `Bearer ${state.token}`;
  return fetch(`${API}/stop`, {
    method: "POST", keepalive: true, cache: "no-store", headers,
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
  clearError();
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
      await stopNow("operator page: STOP button");
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
    if (chosenRecipe()) return approachWithRecipe(standoff);
    // "" (the first option): no mode in the body, so the config's [approach] mode applies
    const mode = $("approach-mode").value || undefined;
    // IBVS goes to the taught view itself: no standoff
    const body = { standoff_mm: mode === "ibvs" ? undefined : standoff, mode, wait: false };
    if ($("taught").value) body.taught = $("taught").value;
    const job = await api("POST", "/approach", body);
    state.lastJob = job;
    state.resultJobId = job.id;
    renderJob(job);
    const how = (job.params && job.params.mode) || body.mode || "default";
    return `${how} approach started (job ${job.id})`;
  }));

  $("pick").addEventListener("click", () => command("Pick", async () => {
    const body = { wait: false };
    const recipe = chosenRecipe();
    if (recipe) {
      body.recipe = recipe.name;
      body.target = recipeTarget(recipe).name;
    }
    if ($("place").value) body.place = $("place").value;
    const job = await api("POST", "/pick", body);
    state.lastJob = job;
    state.resultJobId = job.id;
    renderJob(job);
    return `pick started (job ${job.id})`;
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

  $("home").addEventListener("click", () => command("Home", async () => {
    const r = await api("POST", "/arm/home", {});
    if (r && r.id) { state.lastJob = r; state.resultJobId = r.id; renderJob(r); }
    return "moving to the home pose";
  }));
  $("unlock").addEventListener("click", () => command("Unlock", async () => {
    await api("POST", "/arm/unlock", {});
    state.resultJobId = "";  // the result line is the unlock's now, not the last job's
    return "protective stop unlocked";
  }));
  wireExtras();

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


// ---------------------------------------------------------------------------------------------
// Alarms: a banner that stays until each alarm is acknowledged (by the server, so every page
// and the PLC see the same), and the alarm log with paging.

// Today's times as the clock shows them; older ones with their date.
function when(t) {
  if (!Number.isFinite(t)) return "–";
  const d = new Date(t * 1000);
  return d.toDateString() === new Date().toDateString()
    ? d.toLocaleTimeString() : d.toLocaleString();
}
const mayAck = () => !!state.token && (state.permissions
  ? state.permissions.includes("alarm_ack") : state.role === "operator");

function el(tag, props = {}, ...children) {
  const e = document.createElement(tag);
  for (const [k, v] of Object.entries(props)) {
    if (k === "dataset") Object.assign(e.dataset, v);
    else if (k in e) e[k] = v;
    else e.setAttribute(k, v);
  }
  for (const c of children) e.append(c);
  return e;
}

function renderBanner(list) {
  const banner = $("alarm-banner");
  const ul = $("alarm-list");
  const key = `${mayAck()}:${list.alarms.map((a) => a.id).join(",")}`;
  if (ul.dataset.key !== key) ul.dataset.key = key;
  else list = { ...list, unchanged: true };
  if (!list.unchanged) ul.replaceChildren(...list.alarms.map((a) => {
    const ack = el("button", { type: "button", textContent: "Acknowledge", disabled: !mayAck(),
      dataset: { testid: "alarm-ack", alarmId: String(a.id) } });
    ack.addEventListener("click", () => acknowledge(a.id));
    return el("li", { dataset: { testid: "alarm", alarmId: String(a.id), code: a.code } },
      el("span", { className: "text" }, el("span", { className: "when", textContent: when(a.raised_at) }),
        el("code", { textContent: a.code }), a.message), ack);
  }));
  banner.hidden = list.alarms.length === 0;
  const count = $("alarm-count");
  count.hidden = list.active === 0;
  count.dataset.count = String(list.active);
  count.textContent = `${list.active} alarm${list.active === 1 ? "" : "s"}`;
}

async function acknowledge(id) {
  try {
    await api("POST", `/alarms/${id}/ack`, {});
    say("Alarm acknowledged.", "info");
  } catch (e) {
    say(`Acknowledge failed: ${e.message}`);
  }
  refreshAlarms();
  refreshLogs();
}

async function acknowledgeAll() {
  const ids = [...document.querySelectorAll('[data-testid="alarm"]')].map((li) => li.dataset.alarmId);
  try {
    for (const id of ids) await api("POST", `/alarms/${id}/ack`, {});
    say(`${ids.length} alarm(s) acknowledged.`, "info");
  } catch (e) {
    say(`Acknowledge failed: ${e.message}`);
  }
  refreshAlarms();
  refreshLogs();
}

async function refreshAlarms() {
  if (!state.token) { renderBanner({ alarms: [], active: 0 }); return; }
  try {
    renderBanner(await api("GET", "/alarms?active=true&limit=20", undefined, { timeoutMs: 3000 }));
  } catch (e) { /* the connection light tells; keep what is shown */ }
}

async function alarmLoop() {
  for (;;) {
    if (!document.hidden) await refreshAlarms();
    await sleep(ALARMS_MS);
  }
}

function pager(prefix, offset, shown, total) {
  $(`${prefix}-page`).textContent = total ? `${offset + 1}–${offset + shown} of ${total}` : "none";
  $(`${prefix}-prev`).disabled = offset <= 0;
  $(`${prefix}-next`).disabled = offset + shown >= total;
}

async function refreshAlarmLog() {
  const r = await api("GET", `/alarms?limit=${PAGE_ROWS}&offset=${state.alarmOffset}`);
  $("alarm-log").replaceChildren(...r.alarms.map((a) => el("tr",
    { dataset: { active: String(a.active), alarmId: String(a.id) } },
    el("td", { textContent: when(a.raised_at) }), el("td", { textContent: a.code }),
    el("td", { textContent: a.message }),
    el("td", { textContent: a.active ? "open" : `${a.acknowledged_by} ${when(a.acknowledged_at)}` }))));
  pager("alarm-log", state.alarmOffset, r.alarms.length, r.total);
}

async function refreshHistory() {
  const r = await api("GET", `/jobs?limit=${PAGE_ROWS}&offset=${state.historyOffset}`);
  $("history").replaceChildren(...r.jobs.map((j) => {
    const res = j.result || {};
    const detail = j.error ? j.error.message
      : res.part ? describePick(res)
      : Number.isFinite(res.reach_error_mm) ? `reached within ${fmt(res.reach_error_mm, 2)} mm` : "";
    return el("tr", { dataset: { state: j.state, jobId: j.id } },
      el("td", { textContent: when(j.created_at) }), el("td", { textContent: `${j.kind} ${j.id}${recipeLabel(j)}` }),
      el("td", { textContent: j.state }), el("td", { textContent: j.caller }),
      el("td", { textContent: detail }));
  }));
  pager("history", state.historyOffset, r.jobs.length, r.total || r.jobs.length);
}

async function refreshLogs() {
  if (!state.token) return;
  try {
    await Promise.all([refreshAlarmLog(), refreshHistory(), refreshImages(), loadRecipes(),
      refreshChecks()]);
  } catch (e) { /* retried on the next round */ }
}

async function logsLoop() {
  for (;;) {
    await sleep(LOGS_MS);
    if (!document.hidden) await refreshLogs();
  }
}

// ---------------------------------------------------------------------------------------------
// Taught poses, calibration, camera settings, image log

async function loadTaught(select) {
  if (!state.token) return;
  try {
    const r = await api("GET", "/teach");
    const sel = $("taught");
    const keep = select !== undefined ? select : sel.value;
    // tool poses relative to the target for the approach; base-frame poses are place poses
    const tools = r.taught.filter((t) => t.frame !== "base");
    const places = r.taught.filter((t) => t.frame === "base");
    sel.replaceChildren(el("option", { value: "", textContent: "default (config)" }),
      ...tools.map((t) => el("option", { value: t.name, textContent: t.name })));
    sel.value = tools.some((t) => t.name === keep) ? keep : "";
    const place = $("place");
    const keepPlace = place.value;
    place.replaceChildren(el("option", { value: "", textContent: "keep in the gripper" }),
      ...places.map((t) => el("option", { value: t.name, textContent: t.name })));
    place.value = places.some((t) => t.name === keepPlace) ? keepPlace : "";
    $("taught-list").replaceChildren(...r.taught.map((t) => el("li", {
      textContent: t.frame === "base"
        ? `${t.name} (base frame): ${showPose(t.T_base_tcp)} (${t.taught_by})`
        : `${t.name}: ${showPose(t.T_target_tcp)} (spread ${fmt(t.spread_mm, 2)} mm, `
          + `${t.taught_by})` })));
  } catch (e) { /* a service without taught poses: the default stays */ }
}

function showCalibration(job) {
  state.calibJob = job;
  const p = job.progress || {};
  const bar = $("calib-progress");
  $("calib-status").dataset.state = job.state;
  if (job.state === "running") {
    const total = p.total || 0;
    bar.max = Math.max(1, total);
    bar.value = p.done || 0;
    $("calib-status").textContent = `running: ${p.stage || "starting"} ${p.done || 0} / ${total}`;
  } else {
    bar.max = 1;
    bar.value = job.state === "succeeded" ? 1 : 0;
    $("calib-status").textContent = `${job.state}${job.error ? `: ${job.error.message}` : ""}`;
  }
  const r = job.result;
  if (r) {
    const v = r.verdict || {};
    const resid = r.residual || {};
    $("calib-result").textContent = `verdict: ${v.text || (v.consistent ? "consistent" : "inconsistent")}\n`
      + `${r.transform || "T_flange_camera"} (${r.chosen}): ${showPose(r.T_flange_camera)}\n`
      + (Number.isFinite(resid.mean_mm) ? `residual ${fmt(resid.mean_mm, 2)} mm / ${fmt(resid.mean_deg, 3)} °\n` : "")
      + (r.change_from_current ? `change from current: ${fmt(r.change_from_current.distance_mm, 2)} mm / `
        + `${fmt(r.change_from_current.distance_deg, 3)} °` : "");
    $("calib-result").dataset.consistent = String(!!v.consistent);
  } else {
    $("calib-result").textContent = "";
  }
  $("calib-apply").disabled = job.state !== "succeeded" || state.role !== "operator";
}

async function followCalibration(id) {
  for (;;) {
    let job;
    try {
      job = await api("GET", `/calibration/hand-eye/${encodeURIComponent(id)}`);
    } catch (e) {
      await sleep(1000);
      continue;
    }
    if (!state.calibJob || state.calibJob.id !== id) return;
    showCalibration(job);
    if (job.state !== "running") return;
    await sleep(400);
  }
}

async function loadCameraSettings() {
  if (!state.token) return;
  try {
    showCameraSettings(await api("GET", "/camera/settings"));
  } catch (e) {
    $("cam-state").textContent = `camera settings not available: ${e.message}`;
  }
}

function showCameraSettings(s) {
  const put = (id, v) => {
    $(id).value = v === null || v === undefined ? "" : String(v);
    $(id).placeholder = v === null ? "not on this camera" : $(id).placeholder;
    if (v === null) $(id).disabled = true;
  };
  put("cam-exposure", s.exposure_us);
  put("cam-iso", s.iso);
  put("cam-focus", s.focus);
  $("cam-state").textContent = `in force: exposure ${s.exposure_us ?? "–"} µs, gain ISO ${s.iso ?? "–"}, `
    + `focus ${s.focus === null ? "fixed" : s.focus}`;
  state.settingsLoaded = true;
}

async function refreshImages() {
  if (!state.token) return;
  let r;
  try {
    r = await api("GET", "/images?limit=12");
  } catch (e) {
    $("images-note").textContent = e.message;
    return;
  }
  if (!r.enabled) {
    $("images-note").textContent = "The image log is off (set [api] image_log_dir in the config).";
    $("images").replaceChildren();
    $("images").dataset.key = "";
    return;
  }
  $("images-note").textContent = r.total ? `${r.total} frame(s) whose locate failed, newest first`
    : "No failed locates logged.";
  const key = r.images.map((img) => img.name).join(",");
  if ($("images").dataset.key === key) return;
  $("images").dataset.key = key;
  $("images").replaceChildren(...r.images.map((img) => {
    const b = el("button", { type: "button", textContent: `${when(img.saved_at)} · ${img.code || "?"}: ${img.message || ""}`,
      dataset: { testid: "image-entry", name: img.name } });
    b.addEventListener("click", () => showImage(img.url));
    return el("li", {}, b);
  }));
}

async function showImage(url) {
  try {
    const resp = await fetch(url, { headers: { Authorization: `Bearer ${state.token}` }, cache: "no-store" });
    if (!resp.ok) throw new ApiError("the image could not be loaded", resp.status, "");
    const view = $("image-view");
    if (view.src) URL.revokeObjectURL(view.src);
    view.src = URL.createObjectURL(await resp.blob());
    view.hidden = false;
  } catch (e) {
    say(e.message);
  }
}

function wireExtras() {
  $("alarm-count").addEventListener("click", () => $("alarm-banner").scrollIntoView());
  $("alarm-ack-all").addEventListener("click", acknowledgeAll);
  for (const [prefix, key, refresh] of [["alarm-log", "alarmOffset", refreshAlarmLog],
    ["history", "historyOffset", refreshHistory]]) {
    $(`${prefix}-prev`).addEventListener("click", () => {
      state[key] = Math.max(0, state[key] - PAGE_ROWS);
      refresh().catch((e) => say(e.message));
    });
    $(`${prefix}-next`).addEventListener("click", () => {
      state[key] += PAGE_ROWS;
      refresh().catch((e) => say(e.message));
    });
  }

  $("teach").addEventListener("click", () => command("Teach", async () => {
    const name = $("teach-name").value.trim();
    if (!/^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$/.test(name)) {
      throw new ApiError("give the pose a name of letters, digits, '_', '.' or '-'", 0, "input");
    }
    const frame = $("teach-frame").value;
    const t = await api("POST", "/teach", { name, samples: 3, frame }, { timeoutMs: 20000 });
    await loadTaught(frame === "base" ? undefined : t.name);
    if (t.frame === "base") return `taught the place pose ${t.name}: ${showPose(t.T_base_tcp)}`;
    return `taught ${t.name}: ${showPose(t.T_target_tcp)} (spread ${fmt(t.spread_mm, 2)} mm)`;
  }));

  $("calib-start").addEventListener("click", () => command("Calibration", async () => {
    const views = Number($("calib-views").value);
    if (!Number.isInteger(views) || views < 3 || views > 30) {
      throw new ApiError("the number of views must be a whole number from 3 to 30", 0, "input");
    }
    const job = await api("POST", "/calibration/hand-eye", { views });
    showCalibration(job);
    followCalibration(job.id);
    return `calibration started (job ${job.id})`;
  }));

  $("calib-apply").addEventListener("click", () => command("Apply calibration", async () => {
    const job = state.calibJob;
    if (!job) return undefined;
    const r = await api("POST", `/calibration/hand-eye/${encodeURIComponent(job.id)}/apply`, {});
    $("calib-status").textContent = `applied: the cell now uses ${r.transform || "T_flange_camera"} ${showPose(r.T_flange_camera)}`;
    $("calib-status").dataset.state = "applied";
    return "calibration applied";
  }));

  $("check-start").addEventListener("click", () => command("Calibration check", async () => {
    const job = await api("POST", "/calibration/check", { wait: false });
    state.lastJob = job;
    state.resultJobId = job.id;
    renderJob(job);
    return `calibration check started (job ${job.id})`;
  }));

  $("reference-record").addEventListener("click", () => command("Record reference", async () => {
    const job = await api("POST", "/calibration/reference", { wait: false });
    state.lastJob = job;
    state.resultJobId = job.id;
    renderJob(job);
    return `recording the calibration reference (job ${job.id})`;
  }));

  $("cam-apply").addEventListener("click", () => command("Camera settings", async () => {
    const body = {};
    const num = (id, key) => {
      const raw = $(id).value.trim();
      if ($(id).disabled || raw === "") return;
      const v = Number(raw);
      if (!Number.isInteger(v) || v <= 0) throw new ApiError(`${key.replace("_us", "")} must be a positive whole number`, 0, "input");
      body[key] = v;
    };
    num("cam-exposure", "exposure_us");
    num("cam-iso", "iso");
    const focus = $("cam-focus").value.trim();
    if (!$("cam-focus").disabled && focus !== "") body.focus = focus === "auto" ? "auto" : Number(focus);
    const s = await api("PUT", "/camera/settings", body);
    showCameraSettings(s);
    return "camera settings applied";
  }));
}

// ---------------------------------------------------------------------------------------------
// Calibration check: every check's error at the tool over time against the tolerance (drifted
// checks in red), and the last check's views, drawn as inline SVG from GET /calibration/checks.

const SVG_NS = "http://www.w3.org/2000/svg";
const checks = { key: "" };

function svg(tag, attrs = {}, text = "") {
  const node = document.createElementNS(SVG_NS, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, String(v));
  if (text) node.textContent = text;
  return node;
}

async function refreshChecks() {
  const r = await api("GET", "/calibration/checks?limit=50", undefined, { timeoutMs: 3000 });
  const done = (r.jobs || []).filter((j) => j.state === "succeeded" && j.result).reverse();
  const key = done.map((j) => j.id).join(",");
  if (key === checks.key) return;
  checks.key = key;
  drawChecks(done);
  drawViews(done.length ? done[done.length - 1] : null);
}

function drawChecks(done) {
  const chart = $("check-chart");
  const W = 320, H = 130, L = 34, R = 8, T = 8, B = 18;
  chart.replaceChildren();
  chart.dataset.points = String(done.length);
  if (!done.length) {
    $("check-status").textContent = "no check yet";
    chart.append(svg("text", { x: L, y: H / 2 }, "no checks yet"));
    return;
  }
  const last = done[done.length - 1];
  const res = last.result;
  $("check-status").textContent = `last check ${when(last.ended_at || last.created_at)}: `
    + `${res.verdict}, ${fmt(res.tcp_error_mm, 3)} mm / ${fmt(res.tcp_error_deg, 3)} deg at the tool `
    + `(tolerance ${res.tolerance_mm} mm / ${res.tolerance_deg} deg${res.verdict === "drifted" ? `, cause ${res.cause}` : ""})`;
  $("check-status").dataset.verdict = res.verdict;
  const tol = res.tolerance_mm;
  const top = Math.max(tol * 1.5, ...done.map((j) => j.result.tcp_error_mm)) * 1.1;
  const t0 = done[0].created_at, t1 = done[done.length - 1].created_at;
  const x = (t) => (done.length < 2 ? (L + W - R) / 2 : L + ((t - t0) / Math.max(t1 - t0, 1e-6)) * (W - L - R));
  const y = (mm) => H - B - (mm / top) * (H - T - B);
  chart.dataset.top = String(top);
  chart.append(svg("line", { x1: L, y1: H - B, x2: W - R, y2: H - B, stroke: "#999" }));
  chart.append(svg("line", { x1: L, y1: T, x2: L, y2: H - B, stroke: "#999" }));
  chart.append(svg("text", { x: 2, y: T + 8 }, `${fmt(top, 2)}`));
  chart.append(svg("text", { x: 2, y: H - B }, "0 mm"));
  chart.append(svg("line", { class: "tolerance", "data-testid": "check-tolerance", "data-mm": tol,
    x1: L, y1: y(tol), x2: W - R, y2: y(tol) }));
  chart.append(svg("text", { x: W - R - 2, y: y(tol) - 3, "text-anchor": "end" }, `tolerance ${tol} mm`));
  chart.append(svg("polyline", { class: "trend",
    points: done.map((j) => `${x(j.created_at)},${y(j.result.tcp_error_mm)}`).join(" ") }));
  chart.append(svg("text", { x: L, y: H - 4 }, when(t0)));
  if (done.length > 1) chart.append(svg("text", { x: W - R - 50, y: H - 4 }, when(t1)));
  for (const j of done) {
    const dot = svg("circle", { cx: x(j.created_at), cy: y(j.result.tcp_error_mm),
      r: j.result.verdict === "drifted" ? 4.5 : 3, "data-verdict": j.result.verdict,
      "data-job-id": j.id, "data-mm": j.result.tcp_error_mm });
    dot.append(svg("title", {}, `${when(j.created_at)}: ${j.result.verdict}, `
      + `${fmt(j.result.tcp_error_mm, 3)} mm / ${fmt(j.result.tcp_error_deg, 3)} deg`));
    chart.append(dot);
  }
}

// The last check's views: one bar per view, how far the plate seemed to move seen from there.
function drawViews(job) {
  const chart = $("check-views");
  chart.replaceChildren();
  const views = job ? job.result.views || [] : [];
  chart.dataset.views = String(views.length);
  if (!views.length) return;
  const W = 320, H = 70, L = 34, B = 14, T = 6;
  const tol = job.result.tolerance_mm;
  const top = Math.max(tol, ...views.map((v) => v.distance_mm)) * 1.1;
  const w = (W - L - 8) / views.length;
  chart.append(svg("text", { x: 2, y: T + 8 }, `${fmt(top, 2)}`));
  chart.append(svg("text", { x: 2, y: H - B }, "0 mm"));
  views.forEach((v, i) => {
    const h = (v.distance_mm / top) * (H - T - B);
    const bar = svg("rect", { x: L + i * w + 2, y: H - B - h, width: Math.max(w - 4, 1), height: h,
      "data-verdict": v.distance_mm > tol ? "drifted" : "ok", "data-mm": v.distance_mm });
    bar.append(svg("title", {}, `view ${v.view}: ${fmt(v.distance_mm, 3)} mm, ${fmt(v.rotation_deg, 3)} deg`));
    chart.append(bar);
    chart.append(svg("text", { x: L + i * w + 2, y: H - 2 }, `view ${v.view} ${fmt(v.distance_mm, 2)}`));
  });
  chart.append(svg("line", { class: "tolerance", x1: L, y1: H - B - (tol / top) * (H - T - B),
    x2: W - 8, y2: H - B - (tol / top) * (H - T - B) }));
}

// ---------------------------------------------------------------------------------------------
// Recipes: the Approach controls' recipe choice (GET /recipes). "no recipe" is the plain
// approach as before; a recipe brings its target's dot layout, tool pose, mode and speed
// (POST /recipes/{name}/approach), so the page's mode and tool pose choices do not apply
// and are disabled. Its standoff is shown in the standoff field (what is shown is sent); the
// operator's own value comes back with "no recipe". The job line names the recipe and version
// from the job's record (params.recipe), which is what the cell really ran.

const recipes = { list: [], key: "", manualStandoff: null };

function recipeLabel(job) {
  const r = job && job.params && job.params.recipe;
  if (!r || typeof r !== "object" || !r.name) return "";
  return ` · recipe ${r.name} v${r.version}${r.target ? `, target ${r.target}` : ""}`;
}

function chosenRecipe() {
  const name = $("recipe").value;
  return name ? recipes.list.find((r) => r.name === name) || null : null;
}

function recipeTarget(recipe) {
  const name = $("recipe-target").value;
  return recipe.targets.find((t) => t.name === name) || recipe.targets[0];
}

async function loadRecipes() {
  if (!state.token) return;
  let r;
  try {
    r = await api("GET", "/recipes", undefined, { timeoutMs: 3000 });
  } catch (e) {
    return; // a service without recipes: "no recipe" stays the only choice
  }
  const list = Array.isArray(r.recipes) ? r.recipes : [];
  const key = list.map((x) => `${x.name}@${x.version}`).join(",");
  if (key === recipes.key) return; // rebuilding an open select would close it
  const sel = $("recipe");
  const keep = sel.value;
  const before = chosenRecipe();
  recipes.list = list;
  recipes.key = key;
  sel.replaceChildren(el("option", { value: "", textContent: "no recipe" }),
    ...list.map((x) => el("option", { value: x.name,
      textContent: `${x.name} v${x.version} (no. ${x.number})` })));
  if (keep && !list.some((x) => x.name === keep)) {
    sel.value = "";
    chooseRecipe();
    say(`Recipe ${keep} was removed: no recipe is selected.`);
    return;
  }
  sel.value = keep;
  const now = chosenRecipe();
  // a new version of the chosen recipe: its targets and standoff are shown afresh
  if (now && (!before || before.version !== now.version)) chooseRecipe();
}

// The selection changed (or its recipe got a new version): targets, standoff, note.
function chooseRecipe() {
  const recipe = chosenRecipe();
  const targetSel = $("recipe-target");
  const keepTarget = targetSel.value;
  if (recipe) {
    if (recipes.manualStandoff === null) recipes.manualStandoff = $("standoff").value;
    targetSel.replaceChildren(...recipe.targets.map((t) => el("option",
      { value: t.name, textContent: t.name })));
    targetSel.value = recipe.targets.some((t) => t.name === keepTarget) ? keepTarget
      : recipe.targets[0].name;
    $("recipe-target-label").hidden = recipe.targets.length < 2;
    $("standoff").value = String(recipeTarget(recipe).standoff_mm);
  } else {
    targetSel.replaceChildren();
    $("recipe-target-label").hidden = true;
    if (recipes.manualStandoff !== null) $("standoff").value = recipes.manualStandoff;
    recipes.manualStandoff = null;
  }
  showRecipeNote();
  applyRole();
}

function showRecipeNote() {
  const recipe = chosenRecipe();
  if (!recipe) { $("recipe-note").textContent = ""; return; }
  const t = recipeTarget(recipe);
  $("recipe-note").textContent = `${t.mode.replace(/_/g, "-")}, tool pose ${t.taught || "default (config)"}, `
    + `${fmt(t.speed_mm_s, 0)} mm/s, ${t.points_mm.length} dots`;
}

// Called by applyRole: with a recipe chosen, its tool pose and mode apply, not the page's.
function applyRecipeChoice() {
  if (!chosenRecipe()) return;
  $("approach-mode").disabled = true;
  $("taught").disabled = true;
}

async function approachWithRecipe(standoff) {
  const recipe = chosenRecipe();
  const body = { target: recipeTarget(recipe).name, standoff_mm: standoff };
  const job = await api("POST", `/recipes/${encodeURIComponent(recipe.name)}/approach`, body);
  state.lastJob = job;
  state.resultJobId = job.id;
  renderJob(job);
  const r = (job.params && job.params.recipe) || {};
  return `approach with recipe ${r.name || recipe.name} v${r.version || recipe.version} `
    + `started (job ${job.id})`;
}

function wireRecipes() {
  $("recipe").addEventListener("change", () => { clearError(); chooseRecipe(); });
  $("recipe-target").addEventListener("change", () => {
    const recipe = chosenRecipe();
    if (recipe) $("standoff").value = String(recipeTarget(recipe).standoff_mm);
    showRecipeNote();
  });
}

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

function main() {
  wireJogButtons();
  wireCommands();
  wireRecipes();
  applyRole();
  if (state.token) login(state.token);
  statusLoop();
  cameraLoop();
  alarmLoop();
  logsLoop();
}

main();

// The console's pages: key entry, projects, one project (upload, images, jobs, pairs, model; the
// "Locate a photo" action is locate.js, the ground control points gcp.js, the survey report
// report.js).
// Every string that comes from the server (names, messages) goes into the page as text
// (textContent, text nodes), never as HTML: a file may be named "<img src=x onerror=...>.jpg".

import * as api from "./api.js";
import { bindGcp, checkpoints, describeGcp, loadGcp } from "./gcp.js";
import { bindLocate, resetLocate, showLocate } from "./locate.js";
import { showMap } from "./map.js";
import { showReport } from "./report.js";
import { Viewer } from "./viewer.js";

const $ = (id) => document.getElementById(id);

// An element with attributes and children; string children become text nodes.
function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "dataset") Object.assign(node.dataset, v);
    else if (k.startsWith("on")) node.addEventListener(k.slice(2), v);
    else if (v !== undefined && v !== null && v !== false) node.setAttribute(k, v === true ? "" : String(v));
  }
  for (const c of children) node.append(typeof c === "string" || typeof c === "number" ? String(c) : c);
  return node;
}

function notice(message) {
  const n = $("notice");
  n.textContent = message || "";
  n.hidden = !message;
}

// A failed call: a 401 means the key is wrong or revoked, so ask for another.
function fail(error) {
  if (error instanceof api.ApiError && error.status === 401) {
    api.setKey(null);
    route();
  }
  if (error.name !== "AbortError") notice(error.message);
}

const state = {
  project: null,
  images: [],
  registered: null, // Set of registered names, null without a model
  controller: null, // aborts the current page's requests and streams
  urls: [], // object URLs of the current page, revoked when it is left
  thumbs: new Map(), // image sha256 -> object URL of its bytes, for this visit
  job: null,
  jobsPolling: false, // the project's job list is being read again while a job is open
  jobsKick: false, // a job was started meanwhile: read the list at least once more
};

function objectUrl(blob) {
  const url = URL.createObjectURL(blob);
  state.urls.push(url);
  return url;
}

function leavePage() {
  if (state.controller) state.controller.abort();
  state.controller = new AbortController();
  for (const url of state.urls) URL.revokeObjectURL(url);
  state.urls = [];
  state.thumbs = new Map();
  state.job = null;
  state.jobsPolling = false;
  state.jobsKick = false;
}

function show(view) {
  for (const id of ["key-view", "projects-view", "project-view"]) $(id).hidden = id !== view;
  const key = api.getKey();
  $("sign-out").hidden = !key;
  $("who").textContent = key ? `key ${key.slice(0, 7)}…` : "";
}

// -- routing ------------------------------------------------------------------------------------
function route() {
  leavePage();
  notice("");
  if (!api.getKey()) {
    show("key-view");
    $("key-input").focus();
    return;
  }
  const m = location.hash.match(/^#\/projects\/([^/]+)$/);
  if (m) openProject(decodeURIComponent(m[1])).catch(fail);
  else listProjects().catch(fail);
}

// -- projects -----------------------------------------------------------------------------------
async function listProjects() {
  show("projects-view");
  document.title = "Projects · geomatch";
  const projects = await api.get("/projects");
  const rows = projects.map((p) =>
    el(
      "tr",
      {},
      el("td", {}, el("a", { href: `#/projects/${api.seg(p.id)}` }, p.name)),
      el("td", {}, p.images),
      el("td", {}, p.has_model ? "yes" : "no"),
      el("td", {}, p.created_at.slice(0, 19).replace("T", " ")),
    ),
  );
  if (!rows.length) rows.push(el("tr", {}, el("td", { colspan: 4, class: "muted" }, "No projects yet.")));
  $("project-rows").replaceChildren(...rows);
}

async function createProject(e) {
  e.preventDefault();
  try {
    const p = await api.post("/projects", { name: $("project-name").value });
    $("project-name").value = "";
    location.hash = `#/projects/${api.seg(p.id)}`;
  } catch (error) {
    fail(error);
  }
}

// -- one project --------------------------------------------------------------------------------
async function openProject(id) {
  show("project-view");
  const p = await api.get(`/projects/${api.seg(id)}`);
  state.project = p;
  $("project-title").textContent = p.name;
  document.title = `${p.name} · geomatch`;
  $("upload-list").replaceChildren();
  $("job").hidden = true;
  $("job-rows").replaceChildren();
  $("match-picture").hidden = true;
  $("match-caption").textContent = "Choose a pair to see its matches (verified red, others blue).";
  $("camera-image").hidden = true;
  $("camera-caption").textContent = "Click a camera (orange) to see its image.";
  resetLocate();
  showReport(null);
  showMap(null);
  $("checkpoints").value = "";
  await refreshProject();
  await resume();
}

async function refreshProject() {
  await loadModel(); // first: the thumbnails show each image's registration
  await Promise.all([loadImages(), loadPairs(), loadGcp()]);
}

function pid() {
  return api.seg(state.project.id);
}

async function loadImages() {
  const { images } = await api.get(`/projects/${pid()}/images`);
  state.images = images;
  $("image-count").textContent = `(${images.length})`;
  const items = images.map((im) => {
    const img = el("img", { alt: "", width: 160, height: 120 });
    const registration =
      state.registered === null ? "no model yet" : state.registered.has(im.name) ? "registered" : "not registered";
    const kind = im.aerial === null ? `${im.capture} (unresolved)` : im.aerial ? "aerial" : "ground";
    const item = el(
      "li",
      { class: "thumb", dataset: { name: im.name, registration } },
      img,
      el("span", { class: "name" }, im.name),
      el("span", { class: "meta" }, `${kind} · ${im.width}×${im.height}`),
      el("span", { class: `meta reg ${registration.replace(/ /g, "-")}` }, registration),
    );
    return { item, img, im };
  });
  $("thumbs").replaceChildren(...items.map((x) => x.item));
  const signal = state.controller.signal;
  // a few at a time; each image's bytes are fetched once per visit (keyed by content)
  const queue = [...items];
  const worker = async () => {
    for (let next = queue.shift(); next; next = queue.shift()) {
      const { img, im } = next;
      try {
        if (!state.thumbs.has(im.sha256)) {
          const blob = await api.blob(`/projects/${pid()}/images/${api.seg(im.name)}`, signal);
          state.thumbs.set(im.sha256, objectUrl(blob));
        }
        img.src = state.thumbs.get(im.sha256);
      } catch (error) {
        if (error.name === "AbortError") return;
        img.replaceWith(el("span", { class: "nothumb" }, "no preview"));
      }
    }
  };
  await Promise.all([worker(), worker(), worker()]);
}

// -- uploads ------------------------------------------------------------------------------------
async function uploadFiles(files) {
  if (!state.project || !files.length) return;
  const capture = $("capture").value;
  const list = $("upload-list");
  const rows = [...files].map((file) => {
    const bar = el("progress", { max: 1, value: 0, "aria-label": `upload of ${file.name}` });
    const status = el("span", { class: "status" }, "waiting");
    const row = el("li", { dataset: { name: file.name, state: "waiting" } }, el("span", { class: "name" }, file.name), bar, status);
    list.append(row);
    return { file, bar, status, row };
  });
  for (const { file, bar, status, row } of rows) {
    row.dataset.state = "uploading";
    status.textContent = "uploading";
    try {
      const body = await api.uploadFile(state.project.id, file, capture, (f) => (bar.value = f));
      bar.value = 1;
      row.dataset.state = "done";
      status.textContent = body.images[0] && !body.images[0].created ? "already in the project" : "uploaded";
    } catch (error) {
      row.dataset.state = "error";
      row.classList.add("error");
      status.textContent = `${error.status || ""} ${error.message}`.trim();
      if (error.status === 401) fail(error);
    }
  }
  await Promise.all([loadImages(), loadGcp()]).catch(fail); // new images may make more points usable
}

function bindUpload() {
  const drop = $("drop");
  const input = $("file-input");
  drop.addEventListener("click", () => input.click());
  drop.addEventListener("keydown", (e) => {
    if (e.key === "Enter" || e.key === " ") {
      e.preventDefault();
      input.click();
    }
  });
  for (const type of ["dragenter", "dragover"]) {
    drop.addEventListener(type, (e) => {
      e.preventDefault();
      drop.classList.add("over");
    });
  }
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => {
    e.preventDefault();
    drop.classList.remove("over");
    uploadFiles(e.dataTransfer.files);
  });
  input.addEventListener("change", () => {
    const files = [...input.files];
    input.value = "";
    uploadFiles(files);
  });
}

// -- jobs ---------------------------------------------------------------------------------------
function enumOf(schema) {
  if (!schema || typeof schema !== "object") return null;
  if (Array.isArray(schema.enum)) return schema.enum;
  for (const k of ["anyOf", "oneOf", "allOf"]) {
    for (const s of schema[k] || []) {
      const found = enumOf(s);
      if (found) return found;
    }
  }
  return null;
}

// The choices come from the API's own OpenAPI schema: the console never lags behind the server.
async function loadChoices() {
  const schema = await (await fetch("/openapi.json")).json();
  const props = schema.components.schemas.MatchIn.properties;
  for (const [id, name] of [
    ["method", "method"],
    ["mapper", "mapper"],
  ]) {
    const choices = enumOf(props[name]) || [];
    const prop = props[name] || {};
    const fallback = (prop.examples || [])[0];
    $(id).replaceChildren(
      el("option", { value: "" }, `default${fallback ? ` (${fallback})` : ""}`),
      ...choices.map((c) => el("option", { value: c }, c)),
    );
  }
}

function showJob(job) {
  state.job = job;
  $("job").hidden = false;
  $("job").dataset.id = job.id;
  $("job").dataset.kind = job.kind;
  $("job").dataset.state = job.state;
  $("job-kind").textContent = job.kind === "match" ? "Matching" : "Reconstruction";
  $("job-state").textContent = job.state;
  $("job-state").dataset.state = job.state;
  const { done, total } = job.progress;
  $("job-count").textContent = total ? `${done} / ${total}` : "";
  $("job-progress").max = Math.max(total, 1);
  $("job-progress").value = job.state === "succeeded" ? Math.max(total, 1) : done;
  $("job-error").hidden = !job.error;
  $("job-error").textContent = job.error || "";
  $("cancel-job").disabled = TERMINAL.includes(job.state);
}

const TERMINAL = ["succeeded", "failed", "cancelled"];
const isOpen = (job) => !TERMINAL.includes(job.state);
const JOBS_SHOWN = 20; // the newest; the API pages through the rest
const JOBS_POLL_MS = 2000;

// The project's jobs are the server's list, not this tab's memory: a reload, a second tab or
// another device sees the running and past jobs whoever started them.
async function loadJobs(signal) {
  const { jobs } = await api.get(`/projects/${pid()}/jobs?limit=${JOBS_SHOWN}`);
  if (signal.aborted) return jobs; // the page was left meanwhile: its table is not this one's
  const rows = jobs.map((j) =>
    el(
      "tr",
      { dataset: { id: j.id, kind: j.kind, state: j.state } },
      el("td", {}, j.kind === "match" ? "Matching" : "Reconstruction"),
      el("td", { class: "job-state", dataset: { state: j.state } }, j.state),
      el("td", { class: "num" }, j.progress.total ? `${j.progress.done} / ${j.progress.total}` : ""),
      el("td", {}, j.created_at.slice(0, 19).replace("T", " ")),
    ),
  );
  if (!rows.length) rows.push(el("tr", {}, el("td", { colspan: 4, class: "muted" }, "No jobs yet.")));
  $("job-rows").replaceChildren(...rows);
  return jobs;
}

// Read the list again every few seconds while any job of it is open (queued or running).
function pollJobs() {
  if (state.jobsPolling) {
    state.jobsKick = true;
    return;
  }
  state.jobsPolling = true;
  const signal = state.controller.signal;
  const sleep = () => new Promise((resolve) => setTimeout(resolve, JOBS_POLL_MS));
  (async () => {
    for (;;) {
      state.jobsKick = false;
      const jobs = await loadJobs(signal);
      if (signal.aborted) return;
      if (!jobs.some(isOpen) && !state.jobsKick) {
        state.jobsPolling = false;
        return;
      }
      await sleep();
      if (signal.aborted) return;
    }
  })().catch((error) => {
    if (!signal.aborted) state.jobsPolling = false;
    fail(error);
  });
}

// Open jobs are followed oldest first (a match, then the reconstruct queued behind it); else the
// card shows the newest job.
async function resume() {
  const jobs = await loadJobs(state.controller.signal);
  pollJobs();
  const open = jobs.filter(isOpen).reverse();
  if (open.length) follow(open.map((j) => j.id)).catch(fail);
  else if (jobs.length) showJob(jobs[0]);
}

// Follow the jobs one after the other (a match, then the reconstruct it queued).
async function follow(jobIds) {
  const signal = state.controller.signal;
  for (const id of jobIds) {
    let last = null;
    await api.watchJob(
      id,
      (job) => {
        last = job;
        showJob(job);
      },
      signal,
    );
    if (!last) last = await api.get(`/jobs/${api.seg(id)}`);
    showJob(last);
    if (last.state !== "succeeded") break;
    if (last.kind === "match") await loadPairs();
  }
  await refreshProject();
}

async function startMatch(e) {
  e.preventDefault();
  const body = { reconstruct: $("with-reconstruct").checked };
  if ($("method").value) body.method = $("method").value;
  if ($("mapper").value) body.mapper = $("mapper").value;
  if ($("pairs").value.trim()) body.pairs = $("pairs").value.trim();
  if ($("resize").value !== "") body.resize = Number($("resize").value);
  try {
    notice("");
    const accepted = await api.post(`/projects/${pid()}/match`, body);
    const ids = [accepted.job_id, accepted.reconstruct_job_id].filter(Boolean);
    pollJobs();
    await follow(ids);
  } catch (error) {
    fail(error);
  }
}

async function startReconstruct() {
  try {
    notice("");
    const body = $("mapper").value ? { mapper: $("mapper").value } : {};
    const held = checkpoints();
    if (held !== undefined) body.checkpoints = held;
    const accepted = await api.post(`/projects/${pid()}/reconstruct`, body);
    pollJobs();
    await follow([accepted.job_id]);
  } catch (error) {
    fail(error);
  }
}

async function cancelJob() {
  if (!state.job) return;
  try {
    showJob(await api.del(`/jobs/${api.seg(state.job.id)}`));
    pollJobs();
  } catch (error) {
    fail(error);
  }
}

// -- pairs --------------------------------------------------------------------------------------
async function loadPairs() {
  const { pairs } = await api.get(`/projects/${pid()}/pairs`);
  const rows = pairs.map((p) =>
    el(
      "tr",
      { dataset: { name0: p.name0, name1: p.name1 } },
      el("td", {}, el("button", { type: "button", "aria-label": `show matches of ${p.name0} and ${p.name1}`, onclick: () => showPair(p) }, "Show")),
      el("td", {}, p.name0),
      el("td", {}, p.name1),
      el("td", { class: "num opt" }, p.matches),
      el("td", { class: "num" }, p.inliers),
    ),
  );
  if (!rows.length) rows.push(el("tr", {}, el("td", { colspan: 5, class: "muted" }, "No matched pairs yet.")));
  $("pair-rows").replaceChildren(...rows);
}

async function showPair(p) {
  const img = $("match-picture");
  const caption = $("match-caption");
  caption.textContent = `Drawing ${p.name0} × ${p.name1} …`;
  try {
    const path = `/projects/${pid()}/pairs/${api.seg(p.name0)}/${api.seg(p.name1)}/matches.png`;
    img.src = objectUrl(await api.blob(path, state.controller.signal));
    img.alt = `matches of ${p.name0} and ${p.name1}`;
    img.hidden = false;
    img.dataset.pair = `${p.name0}|${p.name1}`;
    caption.textContent = `${p.name0} × ${p.name1}: ${p.matches} matches, ${p.inliers} verified`;
  } catch (error) {
    caption.textContent = error.message;
  }
}

// -- model --------------------------------------------------------------------------------------
let viewer = null;

async function loadModel() {
  state.registered = null;
  if (!state.project.has_model) {
    const p = await api.get(`/projects/${pid()}`);
    state.project = p;
    if (!p.has_model) {
      $("model-summary").textContent = "No model yet: start a match with reconstruct.";
      viewer.clear();
      showLocate(false);
      showReport(null);
      showMap(null);
      return;
    }
  }
  showLocate(true);
  const summary = await api.get(`/projects/${pid()}/model?format=json`);
  state.registered = new Set(summary.registered_names || []);
  $("model-summary").textContent =
    `${summary.registered} of ${summary.images} images registered, ${summary.points3D} points, ` +
    `mean reprojection error ${Number(summary.mean_reprojection_error).toFixed(2)} px (${summary.mapper} mapper).` +
    describeGcp(summary);
  let report = null;
  try {
    report = await api.get(`/projects/${pid()}/report?format=json`);
  } catch (error) {
    if (error.status !== 404) throw error;
  }
  showReport(report);
  await showMap(report, async () =>
    objectUrl(await api.blob(`/projects/${pid()}/model?format=map-preview`, state.controller.signal)),
  );
  try {
    viewer.load(await api.get(`/projects/${pid()}/model?format=scene`));
  } catch (error) {
    if (error.status !== 404) throw error;
  }
}

async function showCamera(cam) {
  $("camera-caption").textContent = cam.name;
  const img = $("camera-image");
  try {
    img.src = objectUrl(await api.blob(`/projects/${pid()}/images/${api.seg(cam.name)}`, state.controller.signal));
    img.alt = cam.name;
    img.hidden = false;
  } catch (error) {
    $("camera-caption").textContent = `${cam.name}: ${error.message}`;
  }
}

async function download(e) {
  const what = e.currentTarget.dataset.download;
  const names = {
    "model?format=zip": "model.zip",
    "model?format=ply": "points.ply",
    database: "database.db",
    "report?format=md": "report.md",
    "model?format=orthophoto": "odm_orthophoto.tif",
    "model?format=dsm": "dsm.tif",
  };
  try {
    const url = objectUrl(await api.blob(`/projects/${pid()}/${what}`, state.controller.signal));
    const a = el("a", { href: url, download: `${state.project.id}-${names[what]}` });
    document.body.append(a);
    a.click();
    a.remove();
  } catch (error) {
    fail(error);
  }
}

// -- start --------------------------------------------------------------------------------------
function start() {
  viewer = new Viewer($("viewer"), showCamera);
  $("key-form").addEventListener("submit", async (e) => {
    e.preventDefault();
    api.setKey($("key-input").value.trim());
    $("key-input").value = "";
    try {
      await api.get("/projects"); // checks the key before anything else
      if (!location.hash) location.hash = "#/";
      route();
    } catch (error) {
      api.setKey(null);
      show("key-view");
      notice(error.status === 401 ? `That key was refused: ${error.message}` : error.message);
    }
  });
  $("sign-out").addEventListener("click", () => {
    api.setKey(null);
    location.hash = "#/";
    route();
  });
  $("create-form").addEventListener("submit", createProject);
  $("match-form").addEventListener("submit", startMatch);
  $("start-reconstruct").addEventListener("click", startReconstruct);
  $("cancel-job").addEventListener("click", cancelJob);
  for (const b of document.querySelectorAll("[data-download]")) b.addEventListener("click", download);
  bindUpload();
  bindGcp({ projectId: () => state.project.id, fail });
  bindLocate({ viewer, projectId: () => state.project.id, signal: () => state.controller.signal, fail });
  window.addEventListener("hashchange", route);
  loadChoices().catch(fail);
  route();
}

start();

// "Locate a photo": a new photo posed against the project's model (POST .../localize), its camera
// drawn in the viewer beside the model's and its position written out (model frame, and latitude,
// longitude, altitude and heading when the model is georeferenced). A photo the service could not
// place is shown as not localized, with the service's reason: never as a pose.
//
// Kept apart from app.js, which calls bindLocate once and showLocate with each project it shows.
// Every string from the server goes in as text.

import * as api from "./api.js";
import { $, setStatus, text } from "./dom.js";


let ctx = null; // { viewer, projectId(), signal(), fail(error) } from app.js
let located = []; // the viewer's cameras of located photos, for this project page

const status = (state, message) => setStatus("locate-status", state, message);

// The rotation world to camera of a unit quaternion (w, x, y, z), as rows: COLMAP's convention.
export function rotation([w, x, y, z]) {
  return [
    [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
    [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
    [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
  ];
}

// A localization as the viewer's camera: focal length and principal point from COLMAP's
// parameters (models with one focal length list f, cx, cy first; the others fx, fy, cx, cy).
function viewerCamera(a) {
  const { model, width, height, params } = a.camera;
  const single = model.startsWith("SIMPLE") || model.startsWith("RADIAL");
  const focal = params[0] || Math.max(width, height);
  const [cx, cy] = single ? [params[1], params[2]] : [params[2], params[3]];
  return {
    name: a.name,
    center: a.center,
    rotation: rotation(a.cam_from_world.qvec),
    width,
    height,
    focal,
    cx: cx ?? width / 2,
    cy: cy ?? height / 2,
  };
}

const fixed = (v, n) => Number(v).toFixed(n);

function describe(a) {
  const item = document.createElement("li");
  item.dataset.name = a.name;
  item.dataset.state = a.localized ? "localized" : "not-localized";
  item.append(text("span", "name", a.name));
  if (!a.localized) {
    item.append(text("span", "verdict not-localized", "not localized"), text("span", "reason", a.reason || ""));
    return item;
  }
  item.append(text("span", `verdict ${a.confidence}`, `localized (${a.confidence} confidence)`));
  const c = a.center;
  item.append(text("span", "position", `position in the model: x ${fixed(c[0], 2)}, y ${fixed(c[1], 2)}, z ${fixed(c[2], 2)}`));
  if (a.wgs84) {
    const g = a.wgs84;
    const heading = g.heading_deg === null || g.heading_deg === undefined ? "" : `, heading ${fixed(g.heading_deg, 1)}°`;
    const where = `lat ${fixed(g.lat, 7)}, lon ${fixed(g.lon, 7)}, alt ${fixed(g.alt, 1)} m${heading}`;
    const geo = text("span", "wgs84", where);
    geo.dataset.lat = String(g.lat);
    geo.dataset.lon = String(g.lon);
    item.append(geo);
  }
  const error = a.reprojection_error_px === null ? "" : `, ${fixed(a.reprojection_error_px, 2)} px error`;
  item.append(
    text("span", "meta", `${a.inliers} of ${a.matches} matches agree${error}; seen in ${a.supporting_images.join(", ")}`),
  );
  return item;
}

function show(answers) {
  $("locate-results").prepend(...answers.map(describe));
  located = [...located, ...answers.filter((a) => a.localized).map(viewerCamera)];
  ctx.viewer.setLocated(located);
}

// The job's answers once it ended: followed on its event stream when the request's wait was over.
async function finished(jobId) {
  let last = null;
  await api.watchJob(jobId, (job) => {
    last = job;
    status("waiting", `locating: ${job.state}, ${job.progress.done} of ${job.progress.total} photos`);
  }, ctx.signal());
  if (!last || last.state !== "succeeded") last = await api.get(`/jobs/${api.seg(jobId)}`);
  return last;
}

async function locate(files) {
  if (!files.length) return;
  const form = new FormData();
  for (const f of files) form.append("files", f, f.name);
  const pid = api.seg(ctx.projectId());
  status("uploading", `locating ${files.map((f) => f.name).join(", ")} …`);
  try {
    const { status: code, body } = await api.postForm(`/projects/${pid}/localize`, form, ctx.signal());
    let answers = body.localizations;
    let state = body.state;
    let error = body.error;
    if (code === 202) {
      const job = await finished(body.job_id);
      state = job.state;
      error = job.error;
      answers = job.result ? job.result.localizations : null;
    }
    if (state !== "succeeded" || !answers) {
      status("error", `locating ${state}${error ? `: ${error}` : ""}`);
      return;
    }
    show(answers);
    const n = answers.filter((a) => a.localized).length;
    status("done", `${n} of ${answers.length} located`);
  } catch (error) {
    if (error.name === "AbortError") return;
    status("error", `${error.status || ""} ${error.message}`.trim());
    if (error.status === 401) ctx.fail(error);
  }
}

export function bindLocate(context) {
  ctx = context;
  const input = $("locate-input");
  input.addEventListener("change", () => {
    const files = [...input.files];
    input.value = "";
    locate(files);
  });
}

// Each time a project is shown: the action is there only when the project has a model.
export function showLocate(hasModel) {
  $("locate-card").hidden = !hasModel;
}

// A new project page: nothing located yet.
export function resetLocate() {
  located = [];
  ctx.viewer.setLocated(located);
  $("locate-results").replaceChildren();
  status("idle", "");
}

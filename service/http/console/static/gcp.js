// "Ground control points": the project's gcp_list.txt (OpenDroneMap's format) uploaded, shown and
// removed (PUT / GET / DELETE .../gcp). The server checks the file against the project's images: a
// file it cannot use is refused with the reason (the stored one, if any, stays), and the lines and
// points it can do without are listed as problems. The next reconstruction puts the model in the
// points' coordinates; the "Check points" field of the reconstruct form holds some of them out.
//
// Kept apart from app.js, which calls bindGcp once and loadGcp with each project it shows (and
// after uploads: new images may make more points usable). Every string from the server goes in as
// text.

import * as api from "./api.js";
import { $, setStatus, text } from "./dom.js";


let ctx = null; // { projectId(), fail(error) } from app.js

const status = (state, message) => setStatus("gcp-status", state, message);

const path = () => `/projects/${api.seg(ctx.projectId())}/gcp`;

// The stored file's summary, or null for none.
export function showGcp(summary) {
  const card = $("gcp-card");
  card.dataset.state = summary === null ? "none" : summary.error ? "error" : "stored";
  $("gcp-remove").hidden = summary === null;
  $("gcp-details").hidden = summary === null;
  if (summary === null) {
    status("none", "No ground control points: a reconstruction keeps the frame the photos' GPS gives it.");
    $("gcp-points").replaceChildren();
    $("gcp-problems").replaceChildren();
    return;
  }
  const n = summary.points.length;
  if (summary.error) status("error", `The stored file no longer fits the project's images: ${summary.error}`);
  else status("stored", `${n} usable point${n === 1 ? "" : "s"} in ${summary.crs}: the next reconstruction is georeferenced by them.`);
  $("gcp-points").replaceChildren(...summary.points.map((name) => text("li", "point", name)));
  // the problems name every unusable point too ("name: why")
  const problems = summary.problems.map((p) => text("li", "problem", p));
  if (!problems.length) problems.push(text("li", "muted", "none"));
  $("gcp-problems").replaceChildren(...problems);
}

export async function loadGcp() {
  try {
    showGcp(await api.get(path()));
  } catch (error) {
    if (error.status !== 404) throw error;
    showGcp(null);
  }
}

async function upload(file) {
  status("uploading", `Checking ${file.name} against the project's images …`);
  try {
    showGcp(await api.putFile(path(), "file", file));
  } catch (error) {
    if (error.status === 401) ctx.fail(error);
    status("error", `${file.name} was refused: ${error.message}`);
  }
}

async function remove() {
  try {
    await api.del(path());
    showGcp(null);
  } catch (error) {
    if (error.status === 404) showGcp(null);
    else ctx.fail(error);
  }
}

// The reconstruct form's check points: a count ("2"), or names separated by spaces or commas;
// undefined when the field is empty.
export function checkpoints() {
  const value = $("checkpoints").value.trim();
  if (!value) return undefined;
  if (/^\d+$/.test(value)) return Number(value);
  return value.split(/[\s,]+/).filter(Boolean);
}

// The model card's line about the GCPs of a model's summary ("" when it was not georeferenced by them).
export function describeGcp(summary) {
  const g = summary.gcp;
  if (!g) return "";
  if (g.error) return ` GCPs not used: ${g.error}`;
  const used = (g.points || []).filter((p) => p.role === "control").length;
  const check = g.check_rmse_3d_m === undefined ? "" : `, check points ${Number(g.check_rmse_3d_m).toFixed(3)} m RMSE`;
  return ` Georeferenced by ${used} control points (${Number(g.control_rmse_3d_m).toFixed(3)} m RMSE${check}).`;
}

export function bindGcp(context) {
  ctx = context;
  const input = $("gcp-input");
  input.addEventListener("change", () => {
    const [file] = input.files;
    input.value = "";
    if (file) upload(file);
  });
  $("gcp-remove").addEventListener("click", remove);
}

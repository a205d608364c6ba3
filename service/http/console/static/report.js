// "Survey report": what a survey team checks before it delivers a model (GET .../report, the
// reconstruct job's report; geomatch/report.py writes it): photos registered and left out, points
// and their track lengths, reprojection error, the fit to the photos' GPS and to the ground control
// points with the check-point RMSE, pairs the view-graph checks dropped, time per stage. The
// Markdown page is downloaded by app.js's download buttons (`report?format=md`).
//
// Kept apart from app.js, which calls showReport with each model it shows (null: none). Every
// string from the server (photo and point names, reasons) goes in as text.

const $ = (id) => document.getElementById(id);

function node(tag, attrs, ...children) {
  const n = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (k === "dataset") Object.assign(n.dataset, v);
    else if (k === "className") n.className = v;
    else n.setAttribute(k, v);
  }
  for (const c of children) n.append(c instanceof Node ? c : c === null || c === undefined ? "" : String(c));
  return n;
}

const NONE = "–";
const shown = (v, unit = "") => (v === null || v === undefined ? NONE : `${v}${unit}`);
const metres = (v) => (v === null || v === undefined ? "" : Number(v).toFixed(3));

// A <dl> of [key, label, value] facts; each <dd> carries data-fact=key (tests read them).
function facts(id, rows) {
  $(id).replaceChildren(
    ...rows
      .filter((r) => r)
      .flatMap(([key, label, value]) => [node("dt", {}, label), node("dd", { dataset: { fact: key } }, value)]),
  );
}

function listOf(id, items, empty) {
  const lis = items.map((t) => node("li", {}, t));
  if (!lis.length && empty) lis.push(node("li", { className: "muted" }, empty));
  $(id).replaceChildren(...lis);
}

const FRAMES = { ENU: "ENU metres around the photos' GPS", GCP: "the GCPs' coordinate system" };

export function showReport(report) {
  const card = $("report-card");
  card.hidden = report === null;
  card.dataset.state = report === null ? "none" : "shown";
  if (report === null) return;
  const { photos: ph, model: mo, pairs: pa, georeferencing: ge } = report;

  facts("report-facts", [
    ["registered", "Photos registered", `${shown(ph.registered)} of ${shown(ph.images)}`],
    ["unregistered", "Not registered", ph.unregistered.length ? ph.unregistered.join(", ") : "none"],
    ph.left_out && ph.left_out.length
      ? ["left-out", "Left out on purpose", ph.left_out.map((o) => `${o.name}: ${o.why}`).join("; ")]
      : null,
    ["with-gps", "With GPS", ph.with_gps === null || ph.with_gps === undefined ? "none" : ph.with_gps],
    ph.aerial ? ["aerial", "Aerial", ph.aerial] : null,
    ["points", "3D points", shown(mo.points3D)],
    ["observations", "Observations", shown(mo.observations)],
    ["track", "Mean track length", shown(mo.mean_track_length)],
    ["reprojection", "Mean reprojection error", shown(mo.mean_reprojection_error_px, " px")],
    mo.models > 1 ? ["models", "Models", `${mo.models} (the largest is reported)`] : null,
  ]);

  const lengths = Object.entries(mo.track_lengths || {});
  $("report-tracks-box").hidden = !lengths.length;
  $("report-tracks").replaceChildren(
    node("tr", {}, node("th", { scope: "row" }, "photos"), ...lengths.map(([k]) => node("th", { scope: "col", className: "num" }, k))),
    node("tr", {}, node("th", { scope: "row" }, "points"), ...lengths.map(([, v]) => node("td", { className: "num" }, v))),
  );

  const gps = ge.gps;
  facts("report-geo", [
    ["frame", "Frame", ge.georeferenced ? FRAMES[ge.frame] || shown(ge.frame) : "not georeferenced"],
    gps ? ["gps", "Camera centres vs GPS", `median ${shown(gps.median_m, " m")}, RMSE ${shown(gps.rmse_m, " m")}`] : null,
    gps ? ["gps-used", "GPS fixes used", `${shown(gps.inliers)} of ${shown(gps.images)} (largest inlier ${shown(gps.max_inlier_m, " m")})`] : null,
  ]);
  const outliers = (gps ? gps.largest : []).map((r) => `${r.name}: ${r.residual_m} m${r.inlier ? "" : " (not used: outlier)"}`);
  $("report-gps-outliers-box").hidden = !gps;
  listOf("report-gps-outliers", outliers, "none beyond 3× the median");

  const g = ge.gcp;
  $("report-gcp").hidden = !g;
  if (g) {
    const rmse = (key) =>
      g[`${key}_rmse_3d_m`] === undefined ? null : `${g[`${key}_rmse_horizontal_m`]} m horizontal, ${g[`${key}_rmse_3d_m`]} m 3D`;
    facts("report-gcp-facts", [
      ["crs", "Coordinate system", shown(g.crs)],
      g.error ? ["gcp-error", "Not georeferenced by the GCPs", g.error] : null,
      rmse("check") !== null ? ["check-rmse", "Check-point RMSE", rmse("check")] : null,
      rmse("control") !== null ? ["control-rmse", "Control-point RMSE", rmse("control")] : null,
    ]);
    const rows = (g.points || []).map((p) =>
      node(
        "tr",
        { dataset: { point: p.name, role: p.role } },
        node("td", {}, p.name),
        node("td", {}, p.role),
        // a report built from an older summary may not know a point's photos: an empty cell, not "null"
        node("td", { className: "num" }, p.observations === null || p.observations === undefined ? "" : `${p.observations} (${p.observations_registered ?? 0})`),
        ...["dx_m", "dy_m", "dz_m", "3d_m"].map((k) => node("td", { className: "num" }, metres(p[k]))),
        node("td", {}, p.reason || (p.reprojection_px === null || p.reprojection_px === undefined ? "" : `reprojection ${p.reprojection_px} px`)),
      ),
    );
    if (!rows.length) rows.push(node("tr", {}, node("td", { colspan: 8, className: "muted" }, "No point placed.")));
    $("report-gcp-rows").replaceChildren(...rows);
  }

  facts("report-pairs", [
    // a reconstruct job maps what match jobs wrote: only a CLI run's report knows the plan
    pa.planned === null || pa.planned === undefined
      ? null
      : ["planned", "Planned", `${pa.planned}${pa.plan ? ` (${pa.plan})` : ""}${pa.tiled ? `, tiled ${pa.tiled}` : ""}`],
    ["verified", "Verified", shown(pa.verified)],
    ["dropped", "Dropped by the view-graph checks", pa.dropped_by_view_graph.length],
  ]);
  listOf("report-dropped", pa.dropped_by_view_graph.map((d) => `${d.pair.join(" × ")}: ${d.why}`));

  const timings = Object.entries(report.timings_s || {});
  $("report-timings").replaceChildren(
    ...timings.map(([stage, s]) => node("tr", { dataset: { stage } }, node("td", {}, stage), node("td", { className: "num" }, s))),
  );
  if (!timings.length) $("report-timings").append(node("tr", {}, node("td", { colspan: 2, className: "muted" }, "not recorded")));
}

// "Map": the orthophoto of the model (geomatch.ortho: a reconstruct job with ortho on), shown as
// the preview the job wrote (GET .../model?format=map-preview, at most 1024 px: the GeoTIFF
// itself never comes to the browser) with the registered cameras and the ground control points
// drawn where they are on it (the report's map section places them as fractions of the preview).
// The GeoTIFFs download with the buttons (model?format=orthophoto, dsm).
//
// Kept apart from app.js, which calls showMap with each report it shows (null: none) and a
// function that loads the preview as an object URL. Names go in as text (SVG <title>).

const $ = (id) => document.getElementById(id);
const SVG = "http://www.w3.org/2000/svg";
const ROLE_COLOURS = { control: "#d7263d", check: "#f4a259", unused: "#9aa0a6" };

function svg(tag, attrs, title) {
  const n = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) n.setAttribute(k, String(v));
  if (title) {
    const t = document.createElementNS(SVG, "title");
    t.textContent = title;
    n.append(t);
  }
  return n;
}

function fact(label, value, key) {
  const dt = document.createElement("dt");
  dt.textContent = label;
  const dd = document.createElement("dd");
  dd.dataset.fact = key;
  dd.textContent = value;
  return [dt, dd];
}

export async function showMap(report, loadPreview) {
  const card = $("map-card");
  const map = report && report.map && report.map.preview ? report.map : null;
  card.hidden = map === null;
  card.dataset.state = map === null ? "none" : "loading";
  if (map === null) return;
  const p = map.preview;
  const [w, h] = map.extent_m || [null, null];
  $("map-facts").replaceChildren(
    ...fact("GSD", `${map.gsd_cm} cm per pixel`, "gsd"),
    ...fact("Extent", `${w} x ${h} m (${map.area_ha} ha mapped)`, "extent"),
    ...fact("Size", `${(map.size_px || []).join(" x ")} pixels`, "size"),
    ...fact("Coordinate system", String(map.crs), "crs"),
    ...fact("Cameras / GCPs", `${p.cameras.length} / ${p.gcps.length}`, "marks"),
  );
  const marks = $("map-marks");
  marks.setAttribute("viewBox", `0 0 ${p.width} ${p.height}`);
  const r = Math.max(3, Math.round(Math.max(p.width, p.height) / 200));
  marks.replaceChildren(
    ...p.cameras.map((c) =>
      svg("circle", { cx: c.x * p.width, cy: c.y * p.height, r, class: "map-camera" }, c.name),
    ),
    ...p.gcps.map((g) => {
      const x = g.x * p.width;
      const y = g.y * p.height;
      const s = 2 * r;
      return svg(
        "polygon",
        {
          points: `${x},${y - s} ${x + s},${y + s} ${x - s},${y + s}`,
          fill: ROLE_COLOURS[g.role] || ROLE_COLOURS.unused,
          class: "map-gcp",
          "data-role": g.role,
        },
        `${g.name} (${g.role})`,
      );
    }),
  );
  try {
    $("map-image").src = await loadPreview();
    card.dataset.state = "shown";
  } catch (error) {
    $("map-facts").append(...fact("Preview", error.message, "error"));
    card.dataset.state = "failed";
  }
}

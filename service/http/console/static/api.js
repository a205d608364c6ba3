// The public /v1 REST API, as any client calls it: Bearer key, JSON bodies, {"detail": ...} errors.
// The key lives in sessionStorage (this tab only) and never appears in a URL.

const KEY = "geomatch.key";

export function getKey() {
  return sessionStorage.getItem(KEY);
}

export function setKey(key) {
  if (key) sessionStorage.setItem(KEY, key);
  else sessionStorage.removeItem(KEY);
}

export class ApiError extends Error {
  constructor(status, detail) {
    super(detail);
    this.status = status;
  }
}

function auth() {
  return { Authorization: `Bearer ${getKey()}` };
}

// The message a person should read: the API's own "detail" when it sent one.
async function failure(response) {
  let detail = `${response.status} ${response.statusText}`;
  try {
    const body = await response.json();
    if (typeof body.detail === "string") detail = body.detail;
  } catch {
    // not JSON: the status line says enough
  }
  return new ApiError(response.status, detail);
}

export async function request(method, path, body) {
  const headers = auth();
  const init = { method, headers };
  if (body !== undefined) {
    headers["Content-Type"] = "application/json";
    init.body = JSON.stringify(body);
  }
  const response = await fetch(`/v1${path}`, init);
  if (!response.ok) throw await failure(response);
  return response.status === 204 ? null : response.json();
}

export const get = (path) => request("GET", path);
export const post = (path, body) => request("POST", path, body);
export const del = (path) => request("DELETE", path);

// Bytes behind the key (images, pictures, downloads): an <img src> cannot send the header.
export async function blob(path, signal) {
  const response = await fetch(`/v1${path}`, { headers: auth(), signal });
  if (!response.ok) throw await failure(response);
  return response.blob();
}

export const seg = (s) => encodeURIComponent(s);

// One file per request, so each file gets its own progress and its own error. XMLHttpRequest
// because fetch() reports no upload progress.
export function uploadFile(projectId, file, capture, onProgress) {
  return new Promise((resolve, reject) => {
    const xhr = new XMLHttpRequest();
    xhr.open("POST", `/v1/projects/${seg(projectId)}/images`);
    xhr.setRequestHeader("Authorization", `Bearer ${getKey()}`);
    xhr.responseType = "json";
    xhr.upload.onprogress = (e) => {
      if (e.lengthComputable) onProgress(e.loaded / e.total);
    };
    xhr.onload = () => {
      const body = xhr.response;
      if (xhr.status >= 200 && xhr.status < 300) resolve(body);
      else {
        const detail = body && typeof body.detail === "string" ? body.detail : `${xhr.status} ${xhr.statusText}`;
        reject(new ApiError(xhr.status, detail));
      }
    };
    xhr.onerror = () => reject(new ApiError(0, "network error: the upload did not reach the server"));
    const form = new FormData();
    form.append("capture", capture);
    form.append("files", file, file.name);
    xhr.send(form);
  });
}

// The job's server-sent events, read with fetch(): EventSource cannot send the Authorization
// header, and the key must not go into the URL. Calls onJob for each `event: job`; resolves when
// the stream ends (the job ended) or `signal` aborts it.
export async function watchJob(jobId, onJob, signal) {
  const response = await fetch(`/v1/jobs/${seg(jobId)}/events`, {
    headers: { ...auth(), Accept: "text/event-stream" },
    signal,
  });
  if (!response.ok) throw await failure(response);
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += value.replace(/\r\n?/g, "\n");
    let end;
    while ((end = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      let event = "message";
      const data = [];
      for (const line of block.split("\n")) {
        if (line.startsWith("event:")) event = line.slice(6).trim();
        else if (line.startsWith("data:")) data.push(line.slice(5).trimStart());
      }
      if (!data.length) continue;
      const payload = JSON.parse(data.join("\n"));
      if (event === "job") onJob(payload);
      else if (event === "error") throw new ApiError(404, payload.detail);
    }
  }
}

// One file as a multipart field, replacing what the path holds (PUT): the ground control points.
export async function putFile(path, field, file) {
  const form = new FormData();
  form.append(field, file, file.name);
  const response = await fetch(`/v1${path}`, { method: "PUT", headers: auth(), body: form });
  if (!response.ok) throw await failure(response);
  return response.json();
}

// A multipart form (photos): the response's status too, since 200 and 202 mean different things.
export async function postForm(path, form, signal) {
  const response = await fetch(`/v1${path}`, { method: "POST", headers: auth(), body: form, signal });
  if (!response.ok) throw await failure(response);
  return { status: response.status, body: await response.json() };
}

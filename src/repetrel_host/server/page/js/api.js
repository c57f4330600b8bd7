// The server's public API as the page uses it: the key (asked once, kept in this
// browser), JSON calls whose refusals come back as the server's sentence, uploads with
// progress, and the event stream, reconnected by itself after a server restart.

const KEY_STORAGE = "hyrel-api-key";

export function apiKey() {
  return localStorage.getItem(KEY_STORAGE) || "";
}

export function setApiKey(key) {
  localStorage.setItem(KEY_STORAGE, key);
}

/** A refusal: the HTTP status and the server's sentence. */
export class ApiError extends Error {
  constructor(status, message, body) {
    super(message);
    this.status = status;
    this.body = body;
  }
}

export const NO_KEY =
  "Enter the server's API key (hyrel-server printed it at its first start; it is kept in the " +
  "data folder's api-key file), open a one-time link (hyrel-server link), or ask for access.";

function sentence(status, body, fallback) {
  if (status === 403) return NO_KEY;
  if (body && typeof body.error === "string") return body.error;
  if (body && typeof body.detail === "string") return body.detail;
  return fallback;
}

/** ``path`` with the key in its query: for what cannot send a header (images, videos,
 * EventSource). */
export function keyed(path) {
  const key = apiKey();
  if (!key) return path;
  return `${path}${path.includes("?") ? "&" : "?"}apikey=${encodeURIComponent(key)}`;
}

/** One call; resolves to the JSON answer (``{}`` for 204), rejects with an ApiError. */
export async function call(method, path, body) {
  const headers = { "X-Api-Key": apiKey() };
  let payload;
  if (body !== undefined) {
    headers["Content-Type"] = "application/json";
    payload = JSON.stringify(body);
  }
  let response;
  try {
    response = await fetch(path, { method, headers, body: payload });
  } catch (error) {
    throw new ApiError(0, "the server does not answer (reconnecting)", null);
  }
  let data = null;
  try {
    data = response.status === 204 ? {} : await response.json();
  } catch (error) {
    data = null;
  }
  if (!response.ok) {
    throw new ApiError(response.status, sentence(response.status, data, response.statusText), data);
  }
  return data;
}

export const get = (path) => call("GET", path);
export const post = (path, body) => call("POST", path, body);
export const del = (path) => call("DELETE", path);

/** A multipart upload with its progress (``onProgress(fraction)``); resolves to the JSON
 * answer, rejects with an ApiError (a refused file's findings in ``error.body``). */
export function upload(path, form, onProgress) {
  return new Promise((resolve, reject) => {
    const request = new XMLHttpRequest();
    request.open("POST", path);
    request.setRequestHeader("X-Api-Key", apiKey());
    request.upload.addEventListener("progress", (event) => {
      if (event.lengthComputable && onProgress) onProgress(event.loaded / event.total);
    });
    request.addEventListener("load", () => {
      let data = null;
      try {
        data = JSON.parse(request.responseText);
      } catch (error) {
        data = null;
      }
      if (request.status >= 200 && request.status < 300) resolve(data);
      else reject(new ApiError(request.status, sentence(request.status, data, request.statusText), data));
    });
    request.addEventListener("error", () => reject(new ApiError(0, "the upload was cut off", null)));
    request.send(form);
  });
}

/** The server's event stream (``/v1/events``), one for the page. Listeners by event type
 * (``on("progress", fn)``; ``"*"`` for all); ``onLink(fn)`` hears "live", "reconnecting"
 * and "no key". After a reconnection the server sends each printer as it stands again, and
 * ``onReconnect`` listeners fetch what they show again (what happened meanwhile). */
export class EventStream {
  constructor(printer) {
    this.printer = printer;
    this.listeners = new Map();
    this.linkListeners = [];
    this.reconnectListeners = [];
    this.link = "connecting";
    this.source = null;
    this.retry = 500;
    this.everOpen = false;
  }

  on(type, listener) {
    if (!this.listeners.has(type)) this.listeners.set(type, []);
    this.listeners.get(type).push(listener);
  }

  onLink(listener) {
    this.linkListeners.push(listener);
    listener(this.link);
  }

  onReconnect(listener) {
    this.reconnectListeners.push(listener);
  }

  setLink(link) {
    if (link === this.link) return;
    this.link = link;
    for (const listener of this.linkListeners) listener(link);
  }

  start() {
    if (this.source) this.source.close();
    const query = this.printer ? `?printer=${encodeURIComponent(this.printer)}` : "";
    const source = new EventSource(keyed(`/v1/events${query}`));
    this.source = source;
    const types = ["printer", "job", "progress", "temperatures", "message", "snapshot", "file", "z", "appkey"];
    for (const type of types) {
      source.addEventListener(type, (event) => this.dispatch(type, JSON.parse(event.data)));
    }
    source.addEventListener("open", () => {
      this.retry = 500;
      const again = this.everOpen;
      this.everOpen = true;
      this.setLink("live");
      if (again) for (const listener of this.reconnectListeners) listener();
    });
    source.addEventListener("error", () => {
      source.close();
      if (this.source !== source) return;
      this.setLink("reconnecting");
      // Why it failed (a restart, or the key) is asked of the API: EventSource cannot say.
      get("/v1/printers").then(
        () => this.later(),
        (error) => (error.status === 403 ? this.setLink("no key") : this.later()),
      );
    });
  }

  later() {
    setTimeout(() => this.start(), this.retry);
    this.retry = Math.min(this.retry * 2, 5000);
  }

  dispatch(type, data) {
    for (const listener of this.listeners.get(type) || []) listener(data);
    for (const listener of this.listeners.get("*") || []) listener(data);
  }
}

// Every time the page writes goes through these two, in the browser's locale: a clock time
// ("19:48", "07:48 PM"; the charts' axes too) and a duration ("4 min 10 s", "about 38 min").

const TODAY = () => new Date().toDateString();
const number = (n, digits = 1) => n.toLocaleString(undefined, { minimumIntegerDigits: digits, useGrouping: false });

/** When something happens, in the browser's locale and time zone: "10:42" (or "10:42 AM")
 * today, "2 Dec 10:42" another day; ``seconds`` adds them ("10:42:05", for a chart's axis).
 * ``when``: seconds since the epoch, or the server's ISO 8601 time; "" for none. */
export function clock(when, { seconds = false } = {}) {
  if (when == null || when === "") return "";
  const at = new Date(typeof when === "string" ? Date.parse(when) : when * 1000);
  if (isNaN(at)) return "";
  const time = at.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit", second: seconds ? "2-digit" : undefined });
  if (at.toDateString() === TODAY()) return time;
  return `${at.toLocaleDateString([], { day: "numeric", month: "short" })} ${time}`;
}

/** How long: "1 h 05 min", "4 min 10 s", "12 s"; ``rough`` for an estimate, which is not
 * to the second: "about 40 s", "about 38 min", "about 2 h 05 min". "" for none. */
export function duration(seconds, { rough = false } = {}) {
  if (seconds == null || !isFinite(seconds)) return "";
  const s = Math.max(0, Math.round(seconds));
  if (rough) {
    if (s < 60) return `about ${number(s)} s`;
    const minutes = Math.round(s / 60);
    if (minutes < 60) return `about ${number(minutes)} min`;
    return `about ${number(Math.floor(minutes / 60))} h ${number(minutes % 60, 2)} min`;
  }
  const hours = Math.floor(s / 3600);
  const minutes = Math.floor((s % 3600) / 60);
  if (hours) return `${number(hours)} h ${number(minutes, 2)} min`;
  if (minutes) return `${number(minutes)} min ${number(s % 60, 2)} s`;
  return `${number(s)} s`;
}

/** An element: ``h("button", {class: "x", onclick}, "text", child...)``. */
export function h(tag, attributes = {}, ...children) {
  const element = document.createElement(tag);
  for (const [name, value] of Object.entries(attributes)) {
    if (value === undefined || value === null || value === false) continue;
    if (name.startsWith("on")) element.addEventListener(name.slice(2), value);
    else if (name === "dataset") Object.assign(element.dataset, value);
    else if (value === true) element.setAttribute(name, "");
    else element.setAttribute(name, value);
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined || child === false) continue;
    element.append(child instanceof Node ? child : String(child));
  }
  return element;
}

/** Enable ``button`` when ``why`` is empty; else disable it and say why on hover. */
export function allow(button, why) {
  button.disabled = Boolean(why);
  if (why) button.title = why;
  else button.removeAttribute("title");
}

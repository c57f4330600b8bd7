// The page: the farm view at "/", a printer in full at "/printers/NAME". The header holds
// the key (typed, asked for, or from a one-time link), the stream's link state ("live",
// "reconnecting…") and the Access panel.

import { apiKey, setApiKey, EventStream, NO_KEY, post } from "./api.js";

const notice = document.getElementById("notice");
const link = document.getElementById("link");
const keyForm = document.getElementById("key-form");
const keyInput = document.getElementById("key");

// What the page says for "no key": a refused link's sentence instead, which says more.
let noKeyWhy = NO_KEY;

/** A sentence for the person at the top of the page ("" clears it). */
export function say(text, kind = "error") {
  if (text === NO_KEY) text = noKeyWhy;
  notice.textContent = text || "";
  notice.className = text ? kind : "";
}

function showKeyForm(show) {
  keyForm.hidden = !show;
  if (show) keyInput.focus();
}

document.getElementById("key-button").addEventListener("click", () => showKeyForm(keyForm.hidden));
keyForm.addEventListener("submit", (event) => {
  event.preventDefault();
  setApiKey(keyInput.value.trim());
  location.reload();
});

// Without the key: ask for an app key, as an OctoPrint app does, and wait for a person
// to allow it on a page that has one (OctoPrint's appkeys plugin).
document.getElementById("ask-access").addEventListener("click", async () => {
  const app = `Status page (${navigator.platform || "a browser"})`;
  let token;
  try {
    token = (await post("/plugin/appkeys/request", { app })).app_token;
  } catch (error) {
    say(`the server did not take the request: ${error.message}`);
    return;
  }
  say(`"${app}" asks for access: allow it on a page that has the key.`, "info");
  for (;;) {
    await new Promise((resolve) => setTimeout(resolve, 1000));
    const answer = await fetch(`/plugin/appkeys/request/${token}`);
    if (answer.status === 202) continue;
    if (answer.ok) {
      setApiKey((await answer.json()).api_key);
      location.reload();
    } else say("The request was denied, or it expired: ask again.");
    return;
  }
});

// A one-time link (hyrel-server link, "/#token=..."): its token leaves the address at once,
// so that a reload or a bookmark does not offer it again, and is traded for an app key of
// this browser's own, kept as a typed key is. A key in the address (?apikey=) is not taken:
// the browser's history kept the address before the page could read it. Resolves to what
// to say about it ([sentence, kind]), or null.
async function takeLink() {
  const token = new URLSearchParams(location.hash.slice(1)).get("token");
  const query = new URLSearchParams(location.search);
  const keyInAddress = query.has("apikey");
  if (!token && !keyInAddress) return null;
  query.delete("apikey");
  const rest = query.toString();
  history.replaceState(null, "", location.pathname + (rest ? `?${rest}` : ""));
  if (!token) return [KEY_IN_ADDRESS, apiKey() ? "info" : "error"];
  let answer;
  try {
    answer = await fetch("/v1/links/redeem", {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ token }),
    });
  } catch (error) {
    return ["The server did not answer the link: open it again.", "error"];
  }
  const body = await answer.json().catch(() => ({}));
  if (!answer.ok) {
    const why = typeof body.error === "string" ? body.error : `the server refused it (${answer.status})`;
    return [`${why[0].toUpperCase()}${why.slice(1)}.`, "error"];
  }
  setApiKey(body.api_key);
  return [`This browser has a key of its own now, "${body.app_id}" (Access lists it, and revokes it).`, "info"];
}

const KEY_IN_ADDRESS =
  "A key in the page's address is not taken: the browser's history keeps the address. " +
  "Enter the key with the API key button, or open a one-time link (hyrel-server link).";

const LINK_WORDS = { live: "live", reconnecting: "reconnecting…", connecting: "connecting…", "no key": "no key" };

// A link opened in a page already open changes only the address's hash: no new load, so
// the page loads again to take it.
window.addEventListener("hashchange", () => {
  if (new URLSearchParams(location.hash.slice(1)).has("token")) location.reload();
});

async function main() {
  const told = await takeLink();
  if (told && !apiKey()) noKeyWhy = told[0];
  const match = location.pathname.match(/^\/printers\/([^/]+)\/?$/);
  const printer = match ? decodeURIComponent(match[1]) : null;
  const stream = new EventStream(printer);
  stream.onLink((state) => {
    link.textContent = LINK_WORDS[state] || state;
    link.className = `link ${state.replace(" ", "-")}`;
    if (state === "no key") {
      say(NO_KEY);
      showKeyForm(true);
    } else if (state === "live" && notice.textContent === noKeyWhy) say("");
  });
  if (!apiKey()) {
    say(NO_KEY);
    showKeyForm(true);
  }
  const main = document.getElementById("main");
  const view = printer ? await import("./printer.js") : await import("./farm.js");
  await view.mount(main, { name: printer, stream, say });
  if (told) {
    // Said once the view is up: its first load clears the top of the page.
    say(...told);
    if (told[1] === "info") setTimeout(() => notice.textContent === told[0] && say(""), 15000);
  }
  import("./panels/access.js")
    .then((access) => access.mount(document.getElementById("access-panel"), { stream, say }))
    .catch((error) => console.error("the Access panel did not load", error));
  stream.start();
}

main();

// The page: the farm view at "/", a printer in full at "/printers/NAME". The header holds
// the key, the stream's link state ("live", "reconnecting…") and the Access panel.

import { apiKey, setApiKey, EventStream, NO_KEY, post } from "./api.js";

const notice = document.getElementById("notice");
const link = document.getElementById("link");
const keyForm = document.getElementById("key-form");
const keyInput = document.getElementById("key");

/** A sentence for the person at the top of the page ("" clears it). */
export function say(text, kind = "error") {
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

const LINK_WORDS = { live: "live", reconnecting: "reconnecting…", connecting: "connecting…", "no key": "no key" };

async function main() {
  const match = location.pathname.match(/^\/printers\/([^/]+)\/?$/);
  const printer = match ? decodeURIComponent(match[1]) : null;
  const stream = new EventStream(printer);
  stream.onLink((state) => {
    link.textContent = LINK_WORDS[state] || state;
    link.className = `link ${state.replace(" ", "-")}`;
    if (state === "no key") {
      say(NO_KEY);
      showKeyForm(true);
    } else if (state === "live" && notice.textContent === NO_KEY) say("");
  });
  if (!apiKey()) {
    say(NO_KEY);
    showKeyForm(true);
  }
  const main = document.getElementById("main");
  const view = printer ? await import("./printer.js") : await import("./farm.js");
  await view.mount(main, { name: printer, stream, say });
  import("./panels/access.js")
    .then((access) => access.mount(document.getElementById("access-panel"), { stream, say }))
    .catch((error) => console.error("the Access panel did not load", error));
  stream.start();
}

main();

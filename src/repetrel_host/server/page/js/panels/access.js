// Access: applications asking for a key (OctoPrint's appkeys flow: a slicer, a phone app)
// allowed or denied here, the keys granted, revocable, and one-time links for other screens.
// Page-wide, below the view.

import { get, post, del, h, clock } from "../api.js";

export async function mount(section, { stream, say }) {
  const requests = h("div", { id: "requests" });
  const keys = h("ul", { id: "appkeys" });
  const made = h("div", { id: "one-time-link" });
  section.replaceChildren(
    h("h2", {}, "Access"),
    requests,
    h("h3", {}, "App keys"),
    h("p", { class: "muted hint" }, "Applications that were allowed a key. Revoking one refuses its next request."),
    keys,
    h("h3", {}, "One-time link"),
    h(
      "p",
      { class: "muted hint" },
      "For another screen (a kiosk, a wall display): the link opens this page there once, until the time it shows, " +
        "and that browser gets a key of its own, listed above. No key goes into its address or history.",
    ),
    h("button", { type: "button", id: "make-link", onclick: () => makeLink() }, "Make a link"),
    made,
  );

  async function makeLink() {
    let answer;
    try {
      answer = await post("/v1/links", {});
    } catch (error) {
      say(error.message);
      return;
    }
    const field = h("input", { type: "text", readonly: true, size: 48, value: answer.url, "aria-label": "the one-time link" });
    made.replaceChildren(
      field,
      h("span", { class: "muted" }, ` once, until ${clock(answer.expires)}; it gives "${answer.app_id}".`),
    );
    field.select();
  }

  async function decide(token, allow) {
    try {
      await post(`/v1/appkeys/requests/${encodeURIComponent(token)}`, { allow });
    } catch (error) {
      say(error.message);
    }
    load();
  }

  async function revoke(app) {
    if (!confirm(`Revoke the key of "${app}"? It is refused from its next request on.`)) return;
    try {
      await del(`/v1/appkeys/${encodeURIComponent(app)}`);
    } catch (error) {
      say(error.message);
    }
    load();
  }

  async function load() {
    let answer;
    try {
      answer = await get("/v1/appkeys");
    } catch (error) {
      section.hidden = true; // without the key there is nothing to decide here
      return;
    }
    section.hidden = false;
    requests.replaceChildren(
      ...answer.pending.map((pending) =>
        h(
          "div",
          { class: "request" },
          h("strong", {}, pending.app_id),
          ` asks for access${pending.remote_address ? ` from ${pending.remote_address}` : ""}. `,
          h("button", { type: "button", class: "primary", onclick: () => decide(pending.user_token, true) }, "Allow"),
          " ",
          h("button", { type: "button", onclick: () => decide(pending.user_token, false) }, "Deny"),
        ),
      ),
    );
    keys.replaceChildren(
      ...(answer.keys.length
        ? answer.keys.map((key) =>
            h(
              "li",
              {},
              h("strong", {}, key.app_id),
              h("span", { class: "muted" }, ` for ${key.user_id}, since ${clock(key.created)} `),
              h("button", { type: "button", class: "danger", onclick: () => revoke(key.app_id) }, "Revoke"),
            ),
          )
        : [h("li", { class: "muted" }, "none yet")]),
    );
  }

  stream.on("appkey", load);
  stream.onReconnect(load);
  await load();
}

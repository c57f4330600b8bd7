// The terminal: typed commands (with their history on the up arrow) and their replies,
// the controller's messages, and the wire itself ("Send: ...", "Recv: ..."), read from
// the printer's OctoPrint-compatible push socket as any OctoPrint client reads it. The
// session's own polls (M105 and its reports) can be hidden.

import { post, h } from "../api.js";

const KEPT = 500; // lines shown
// The session's polls on the wire: M105 sent (numbered or not) and temperature reports.
const POLL = /^(Send: (N\d+ )?M105\b|Recv:\s+(ok\s+)?(T\d*|B|C):\s*-?\d|Recv: ok$|Send: \x05|Recv: >ST:)/;

export function mount(body, ctx) {
  const historyKey = `terminal-history-${ctx.name}`;
  const typed = JSON.parse(localStorage.getItem(historyKey) || "[]");
  let recall = typed.length;
  const output = h("div", { class: "terminal-output", role: "log", "aria-live": "polite" });
  const showWire = h("input", { type: "checkbox", id: "terminal-wire", checked: true, onchange: refilter });
  const hidePolls = h("input", { type: "checkbox", id: "terminal-polls", checked: true, onchange: refilter });
  const input = h("input", { type: "text", id: "terminal-input", placeholder: "G-code, e.g. M105", autocomplete: "off", spellcheck: "false", "aria-label": "command" });
  const send = h("button", { type: "submit", class: "primary", id: "terminal-send" }, "Send");
  const why = h("div", { class: "terminal-why muted" });
  const form = h("form", { class: "terminal-form", onsubmit: submit }, input, send);
  body.append(
    h("div", { class: "row terminal-options" },
      h("label", {}, showWire, " the wire"),
      h("label", {}, hidePolls, " hide the polls (M105, temperature reports)"),
      h("button", { type: "button", onclick: () => output.replaceChildren() }, "Clear")),
    output, form, why,
  );

  // Lines wait for the next frame and go in together: the wire of a print is hundreds of
  // lines a second, and a layout for each would stall the page.
  let waiting = [];

  function add(kind, text) {
    const line = h("div", { class: `line ${kind}`, dataset: { poll: String(kind === "wire" && POLL.test(text)) } }, text);
    line.hidden = hiddenLine(line);
    if (waiting.push(line) === 1) requestAnimationFrame(flush);
    else if (waiting.length > 2 * KEPT) waiting = waiting.slice(-KEPT); // a hidden tab: no frames
  }

  function flush() {
    const lines = waiting.slice(-KEPT);
    waiting = [];
    const atBottom = output.scrollTop + output.clientHeight >= output.scrollHeight - 4;
    output.append(...lines);
    const extra = output.childElementCount - KEPT;
    for (let i = 0; i < extra; i += 1) output.firstElementChild.remove();
    if (atBottom) output.scrollTop = output.scrollHeight;
  }

  function hiddenLine(line) {
    if (!line.classList.contains("wire")) return false;
    return !showWire.checked || (hidePolls.checked && line.dataset.poll === "true");
  }

  function refilter() {
    for (const line of output.children) line.hidden = hiddenLine(line);
    output.scrollTop = output.scrollHeight;
  }

  async function submit(event) {
    event.preventDefault();
    const command = input.value.trim();
    if (!command) return;
    if (typed[typed.length - 1] !== command) typed.push(command);
    typed.splice(0, Math.max(0, typed.length - 100));
    localStorage.setItem(historyKey, JSON.stringify(typed));
    recall = typed.length;
    input.value = "";
    add("typed", `> ${command}`);
    try {
      const reply = await post(`${ctx.path}/command`, { command });
      for (const line of reply.lines) add("reply", line);
      if (!reply.lines.length) add("reply", reply.ok ? "ok" : "(no reply)");
    } catch (error) {
      add("refused", `not sent: ${error.message}`);
    }
  }

  input.addEventListener("keydown", (event) => {
    if (event.key === "ArrowUp" && recall > 0) {
      recall -= 1;
      input.value = typed[recall];
      event.preventDefault();
    } else if (event.key === "ArrowDown" && recall < typed.length) {
      recall += 1;
      input.value = typed[recall] || "";
      event.preventDefault();
    }
  });

  ctx.onChange(() => {
    const reason = ctx.whyNot("command");
    ctx.allow(send, "command");
    why.textContent = reason ? `Commands wait: ${reason}.` : "";
  });
  ctx.stream.on("message", (event) => add("message", event.text));

  // The wire, from the push socket (OctoPrint's terminal feed): a passive login gives the
  // session the socket's auth takes.
  let socket = null;
  let retry = 1000;
  async function openWire() {
    let user;
    try {
      user = await post(`/printers/${encodeURIComponent(ctx.name)}/api/login`, { passive: true });
    } catch (error) {
      setTimeout(openWire, retry);
      retry = Math.min(retry * 2, 10000);
      return;
    }
    const scheme = location.protocol === "https:" ? "wss" : "ws";
    socket = new WebSocket(`${scheme}://${location.host}/printers/${encodeURIComponent(ctx.name)}/sockjs/websocket`);
    socket.addEventListener("open", () => {
      retry = 1000;
      socket.send(JSON.stringify({ auth: `${user.name}:${user.session}` }));
      socket.send(JSON.stringify({ subscribe: { state: { logs: true, messages: false }, events: false, plugins: false } }));
    });
    socket.addEventListener("message", (event) => {
      const message = JSON.parse(event.data);
      const state = message.current || message.history;
      for (const line of (state && state.logs) || []) add("wire", line);
    });
    socket.addEventListener("close", () => setTimeout(openWire, retry));
  }
  openWire();
}

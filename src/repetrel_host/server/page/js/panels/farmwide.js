// The farm across machines (hyrel-server --farm): every node and its printers, each linking
// to the page of the node that drives it; the shared queue in claim order, with cancel; a
// form that submits a file with its requirements. Each job shows its planned time (filled
// in once the node that received its file has planned it) and the queue its total; a
// printing printer, when it should be free. Kept fresh by the farm's event stream
// (PostgreSQL's notifications). On a server that is not in a farm, nothing is shown.

import { call, get, del, upload, keyed, h, clock, duration } from "../api.js";

const STATE_CLASS = { ready: "ok", printing: "busy", paused: "paused", offline: "offline", error: "error" };
const ENDED_SHOWN = 10; // the last jobs that ended, under the queue

export async function mount(section, { say }) {
  let farm;
  try {
    farm = await get("/v1/farm");
  } catch (error) {
    if (error.status !== 404 && error.status !== 403) say(error.message);
    return; // not in a farm (404), or no key yet: the page says so at the top
  }
  section.hidden = false;
  const nodes = h("div", { id: "farm-nodes" });
  const queue = h("div", { id: "farm-queue" });
  const heading = h("h2", {}, "The farm");
  section.append(heading, nodes, submitForm(say, () => refresh()), queue);

  function draw() {
    const printers = farm.printers;
    const queued = farm.jobs.filter((job) => job.state === "queued").length;
    const lost = farm.nodes.filter((node) => node.lost).length;
    heading.replaceChildren(
      "The farm ",
      h(
        "span",
        { class: "muted summary" },
        `${farm.nodes.length} nodes${lost ? ` (${lost} lost)` : ""} · ${printers.length} printers · ${queued} queued`,
      ),
    );
    nodes.replaceChildren(
      ...farm.nodes.map((node) => {
        const here = node.id === farm.node.id;
        const own = printers.filter((printer) => printer.node === node.id);
        return h(
          "section",
          { class: `farm-node ${node.lost ? "lost" : ""}`, dataset: { node: node.name } },
          h(
            "header",
            {},
            h("h3", {}, node.url ? h("a", { href: here ? "/" : node.url }, node.name) : node.name),
            h(
              "span",
              { class: `badge ${node.lost ? "offline" : "ok"}` },
              node.lost ? `lost since ${clock(node.lost_at)}` : here ? "this server" : "alive",
            ),
          ),
          h("div", { class: "farm-printers" }, own.map(printerCard)),
        );
      }),
    );
    queue.replaceChildren(jobsTable());
  }

  function printerCard(printer) {
    const job = printer.job ? farm.jobs.find((j) => j.id === printer.job) : null;
    const state = printer.state === "ready" && printer.held ? "held" : printer.state;
    const has = printer.capabilities;
    const tools = Object.entries(has.tools || {}).map(
      ([tool, head]) => `${tool} ${head.head}${head.material ? ` ${head.material}` : ""}${head.nozzle ? ` ${head.nozzle} mm` : ""}`,
    );
    return h(
      "a",
      { class: "farm-printer", href: printer.url, dataset: { printer: printer.name, state } },
      h("span", { class: "name" }, printer.name),
      h("span", { class: `badge ${state === "held" ? "wait" : STATE_CLASS[state] || "offline"}` }, state),
      h("span", { class: "what muted" }, [has.machine, ...tools, ...(has.tags || []).map((tag) => `#${tag}`)].filter(Boolean).join(" · ")),
      job ? h("span", { class: "job" }, `${job.name} · ${job.lines}/${job.total_lines} lines`) : null,
      printer.free_at ? h("span", { class: "free-at muted" }, `free at ${clock(printer.free_at)}`) : null,
    );
  }

  function jobsTable() {
    const active = farm.jobs.filter((job) => ["queued", "claimed", "printing", "paused"].includes(job.state));
    const ended = farm.jobs.filter((job) => !active.includes(job)).slice(0, ENDED_SHOWN);
    const rows = [...active, ...ended].map((job) => {
      const where = job.printer ? `${job.printer} at ${job.node_name}` : "";
      let action = null;
      if (["queued", "claimed", "printing", "paused"].includes(job.state)) {
        action = h("button", { type: "button", class: "danger", onclick: () => cancelJob(job) }, "Cancel");
      } else if (job.state === "resumed") {
        // Resumed once: its rest is that job (the farm refuses a second resume).
        action = h("span", { class: "resumed-as muted" }, `rest: job ${job.resumed_by}`);
      } else if (job.resume_from_line) {
        action = h(
          "button",
          { type: "button", class: "resume", title: `queue the rest, from line ${job.resume_from_line}, for ${job.printer} at ${job.node_name} (its part is on that bed)`, onclick: () => resumeJob(job) },
          `Resume on ${job.printer}`,
        );
      }
      return h(
        "tr",
        { dataset: { job: job.id, state: job.state } },
        h("td", {}, job.id),
        h("td", { class: "file", title: job.name }, job.name, job.from_line ? h("span", { class: "muted" }, ` from line ${job.from_line}`) : null),
        h("td", {}, h("span", { class: `badge ${badge(job.state)}` }, job.state)),
        h("td", {}, job.requires, job.priority ? ` · priority ${job.priority}` : ""),
        h("td", {}, where),
        h("td", { class: "numbers" }, job.total_lines ? `${job.lines}/${job.total_lines}` : ""),
        h("td", { class: "estimate numbers" }, estimate(job)),
        h("td", { class: "error" }, job.error || ""),
        h("td", {}, action),
      );
    });
    if (!rows.length) return h("p", { class: "empty" }, "No farm jobs yet: submit a file above, or use hyrel-send --server URL --farm.");
    return h(
      "div",
      { class: "farm-jobs-scroll" },
      h(
        "table",
        { class: "farm-jobs" },
      h("thead", {}, h("tr", {}, ["job", "file", "state", "needs", "printer", "lines", "time", "", ""].map((name) => h("th", {}, name)))),
        h("tbody", {}, rows),
      ),
      queueTotal(),
    );
  }

  function queueTotal() {
    const queued = farm.jobs.filter((job) => job.state === "queued");
    if (!queued.length) return null;
    const planned = queued.filter((job) => job.estimated_time != null);
    const seconds = planned.reduce((sum, job) => sum + job.estimated_time, 0);
    const waiting = queued.length - planned.length;
    const parts = [`${queued.length} queued`];
    if (planned.length) parts.push(duration(seconds, { rough: true }));
    if (waiting) parts.push(`${waiting} without an estimate`);
    return h("p", { class: "farm-queue-total muted" }, parts.join(" · "));
  }

  async function cancelJob(job) {
    if (job.state !== "queued" && !confirm(`Cancel farm job ${job.id} (${job.name})? Its printer stops it with the safe stop.`)) return;
    try {
      await del(`/v1/farm/jobs/${job.id}`);
      await refresh();
    } catch (error) {
      say(error.message);
    }
  }

  async function resumeJob(job) {
    try {
      await call("POST", `/v1/farm/jobs/${job.id}/resume`, {});
      await refresh();
    } catch (error) {
      say(error.message);
    }
  }

  let pending = null;
  async function refresh() {
    try {
      farm = await get("/v1/farm");
      draw();
    } catch (error) {
      say(error.message);
    }
  }

  function later() {
    // Progress reports come about once a second from every printing job: one reload a
    // second at most.
    if (pending) return;
    pending = setTimeout(() => {
      pending = null;
      refresh();
    }, 1000);
  }

  function listen() {
    const source = new EventSource(keyed("/v1/farm/events"));
    source.addEventListener("message", later);
    source.addEventListener("error", () => {
      source.close();
      setTimeout(() => {
        refresh();
        listen();
      }, 2000);
    });
  }

  draw();
  listen();
  // Progress is not notified (only changes of state are): while a job streams, the lines
  // shown are read again every few seconds.
  setInterval(() => {
    if (farm.jobs.some((job) => job.state === "printing")) later();
  }, 4000);
}

// A job's planned time: "about 42 min"; the whole file's for a job from a line whose rest
// was not planned; nothing until its node planned it (or for a file without moves).
function estimate(job) {
  if (job.estimated_time == null) return "";
  const whole = job.from_line && job.estimate_of === "file";
  return h("span", { title: whole ? "the whole file's: the rest from its line was not planned" : "planned from the file's moves" }, duration(job.estimated_time, { rough: true }), whole ? " (whole file)" : "");
}

function badge(state) {
  return { queued: "wait", claimed: "busy", printing: "busy", paused: "paused", completed: "ok", cancelled: "offline", resumed: "offline" }[state] || "error";
}

function submitForm(say, done) {
  const file = h("input", { type: "file", name: "file", accept: ".gcode,.gco,.g", required: true });
  const needs = h("input", { type: "text", name: "require", size: 28, placeholder: "material=PLA tag=abs T1.head=MK1-250" });
  const copies = h("input", { type: "number", name: "copies", min: 1, max: 100, value: 1 });
  const priority = h("input", { type: "number", name: "priority", value: 0 });
  const state = h("span", { class: "muted", role: "status" });
  const form = h(
    "form",
    { class: "farm-submit" },
    h("label", {}, "File ", file),
    h("label", {}, "Needs ", needs),
    h("label", {}, "Copies ", copies),
    h("label", {}, "Priority ", priority),
    h("button", { type: "submit", class: "primary" }, "Send to the farm"),
    state,
  );
  form.addEventListener("submit", async (event) => {
    event.preventDefault();
    if (!file.files.length) return;
    const data = new FormData();
    data.append("file", file.files[0]);
    for (const need of needs.value.split(/[\s,]+/).filter(Boolean)) data.append("require", need);
    data.append("copies", copies.value || "1");
    data.append("priority", priority.value || "0");
    try {
      const queued = await upload("/v1/farm/jobs", data, (fraction) => {
        state.textContent = `sending… ${Math.round(fraction * 100)} %`;
      });
      state.textContent = `queued as farm job ${queued.jobs.join(", ")} (${queued.requires}); can print it: ${queued.eligible.join(", ")}`;
      form.reset();
      done();
    } catch (error) {
      state.textContent = "";
      say(error.message);
    }
  });
  return form;
}

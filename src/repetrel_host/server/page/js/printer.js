// One printer in full: its state line, then a panel per file of ./panels/ (each exports
// ``mount(body, ctx)``). The printer's JSON is kept here, up to date from the event stream,
// and handed to the panels through ``ctx``.

import { get, post, del, upload, keyed, h, allow, clock } from "./api.js";
import { stateWords, stateClass, whyNot, isOffline } from "./state.js";

// Where each panel goes: the job and the machine on the left, what a person reads on the
// right, the lists across the bottom.
const PANELS = [
  ["job", "The job", "left"],
  ["temperatures", "Temperatures", "left"],
  ["control", "Control", "left"],
  ["terminal", "Terminal", "right"],
  ["camera", "Camera", "right"],
  ["files", "Files", "wide"],
  ["queue", "Queue and history", "wide"],
];

export async function mount(main, { name, stream, say }) {
  const path = `/v1/printers/${encodeURIComponent(name)}`;
  const changeListeners = [];
  const ctx = {
    name,
    path, // the printer's API: /v1/printers/NAME
    printer: null, // its JSON, as /v1/printers/NAME gives it, kept up to date
    lastJob: null, // the job that ended last (its record), while no other runs
    stream,
    say,
    api: { get, post, del, upload, keyed },
    /** ``fn(printer)`` at every change of the printer (state, job, progress). */
    onChange(listener) {
      changeListeners.push(listener);
      if (ctx.printer) listener(ctx.printer);
    },
    /** Why ``action`` cannot be done now ("" when it can): see state.js. */
    whyNot: (action) => whyNot(ctx.printer, action),
    allow: (button, action) => allow(button, whyNot(ctx.printer, action)),
  };

  document.getElementById("crumbs").replaceChildren(h("a", { href: "/" }, "all printers"), " › ", name);
  document.title = `${name} · Hyrel print server`;
  const badge = h("span", { class: "badge" });
  const since = h("span", { class: "since" });
  const free = h("span", { class: "free-at" });
  const release = h("button", { type: "button", id: "release", onclick: () => act("release") }, "Release the queue");
  const held = h("div", { class: "held", hidden: true }, "The queue is held after the last job: clear the bed, then ", release);
  const head = h("section", { class: "printer-head", dataset: { printer: name } }, h("h1", {}, name), badge, since, free, held);
  const columns = { left: h("div", { class: "column" }), right: h("div", { class: "column" }), wide: h("div", { class: "wide" }) };
  main.append(head, h("div", { class: "columns" }, columns.left, columns.right), columns.wide);

  async function act(action) {
    try {
      await post(`${path}/${action}`);
    } catch (error) {
      say(error.message);
    }
  }

  function changed() {
    const printer = ctx.printer;
    badge.textContent = stateWords(printer);
    badge.className = `badge ${stateClass(printer)}`;
    // Offline: the badge says since when, this says why; else since when it is so.
    since.textContent = isOffline(printer) ? printer.reason || "" : printer.since ? `since ${clock(printer.since)}` : "";
    // When it should be free, its queue counted: while a job runs (a paused one has no end).
    const freeAt = printer.job && printer.state !== "paused" ? clock(printer.free_at) : "";
    free.textContent = freeAt ? `free at ${freeAt}` : "";
    held.hidden = !printer.held;
    allow(release, whyNot(printer, "release"));
    for (const listener of changeListeners) {
      try {
        listener(printer);
      } catch (error) {
        console.error(error);
      }
    }
  }

  async function load() {
    try {
      ctx.printer = await get(path);
    } catch (error) {
      if (error.status === 404) say(`There is no printer ${name} on this server.`);
      else if (error.status !== 403) say(error.message);
      return false;
    }
    changed();
    return true;
  }

  stream.on("printer", (event) => {
    const { type, printer: _, ...fields } = event;
    ctx.printer = { ...(ctx.printer || { name }), ...fields };
    changed();
  });
  stream.on("progress", (event) => {
    const job = ctx.printer && ctx.printer.job;
    if (!job || job.id !== event.job) return;
    const replanned = event.time_left_from !== job.time_left_from;
    Object.assign(job, event, { id: event.job });
    if ("free_at" in event) ctx.printer.free_at = event.free_at;
    if (replanned) refreshFree(); // the job planned: its whole time, which progress omits
    changed();
  });
  stream.on("job", (event) => {
    if (!ctx.printer) return;
    const job = event.job;
    if (job.state === "printing" || job.state === "paused") {
      ctx.printer.job = { ...(ctx.printer.job || {}), ...job };
    } else if (ctx.printer.job && ctx.printer.job.id === job.id) {
      ctx.printer.job = null;
      ctx.lastJob = job;
    } else if (job.state !== "queued") {
      ctx.lastJob = job;
    }
    refreshFree();
    changed();
  });
  stream.onReconnect(load);

  let freeTimer = null;
  function refreshFree() {
    // A job queued, started or ended moves the printer's free time: asked again (once for
    // several events in a row), and the running job's whole time with it.
    clearTimeout(freeTimer);
    freeTimer = setTimeout(async () => {
      try {
        const printer = await get(path);
        if (!ctx.printer) return;
        ctx.printer.free_at = printer.free_at;
        const job = ctx.printer.job;
        if (job && printer.job && printer.job.id === job.id) job.estimated_time = printer.job.estimated_time;
        changed();
      } catch (error) {
        /* the next event or the reconnection tries again */
      }
    }, 300);
  }

  if (!(await load())) ctx.printer = { name, state: "connecting" };
  for (const [panel, title, where] of PANELS) {
    const body = h("div", { class: "panel-body" });
    const section = h("section", { class: "panel", id: `panel-${panel}` }, h("h2", {}, title), body);
    columns[where].append(section);
    import(`./panels/${panel}.js`)
      .then((module) => module.mount(body, ctx))
      .catch((error) => {
        body.replaceChildren(h("p", { class: "error" }, `This panel did not load: ${error.message}`));
        console.error(error);
      });
  }
}

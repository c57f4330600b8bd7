// The printer's queue (reordered by dragging, or by its arrows; each queued job can be
// cancelled), the history of its ended jobs (outcome, who, how long, its report; print it
// again, or resume it from the layer where it stopped) and what its jobs add up to.

import { h, clock, duration } from "../api.js";
import { metres } from "./files.js";

const SHOWN = 20; // ended jobs in the history
const OUTCOME = { completed: "ok", cancelled: "offline", failed: "error", interrupted: "held" };

export function mount(body, ctx) {
  const api = ctx.api;
  let jobs = [];
  let paths = null; // the stored files' paths (null: not known)
  let dragged = null; // the id of the queued job being dragged
  const reports = new Set(); // the jobs whose report is shown
  const resumes = new Map(); // job id -> its resume box
  let timer = null;

  const running = h("div", { class: "queue-running" });
  const queued = h("ol", { class: "queue-list", "aria-label": "queued jobs" });
  const queueHint = h("p", { class: "muted queue-hint" });
  const history = h("div", { class: "history-list" });
  const totals = h("div", { class: "queue-totals" });
  body.append(
    running,
    h("h3", {}, "Queued"), queueHint, queued,
    h("h3", {}, "History"), history,
    h("h3", {}, "Totals"), totals,
  );

  let loads = 0;
  async function load() {
    const mine = ++loads;
    try {
      const [found, sums, files] = await Promise.all([
        api.get(`${ctx.path}/jobs`),
        api.get(`${ctx.path}/totals`),
        api.get("/v1/files").catch(() => null),
      ]);
      if (mine !== loads) return; // a later listing was asked for: it shows
      jobs = found;
      paths = files ? new Set(files.map((f) => f.path)) : null;
      render();
      showTotals(sums);
    } catch (error) {
      history.replaceChildren(h("p", { class: "error" }, `The jobs could not be listed: ${error.message}`));
    }
  }

  /** Loads again soon (several events in a row make one listing); not during a drag,
   * which new rows would cut off: once it ends. */
  function later() {
    clearTimeout(timer);
    timer = setTimeout(() => (dragged === null ? load() : later()), 150);
  }

  function render() {
    const active = jobs.filter((j) => j.state === "printing" || j.state === "paused");
    running.replaceChildren(...active.map((j) =>
      h("p", { class: "queue-now" }, h("span", { class: `badge ${j.state === "paused" ? "paused" : "busy"}` }, j.state), " ", h("strong", {}, j.name), h("span", { class: "muted" }, ` · job ${j.id}, since ${clock(j.started)}${j.user ? `, by ${j.user}` : ""}`))));
    const waiting = jobs.filter((j) => j.state === "queued");
    queued.replaceChildren(...waiting.map((job, i) => queuedRow(job, i, waiting)));
    queueHint.textContent = waiting.length
      ? (waiting.length > 1 ? "Drag a job onto another to take its place (or use its arrows). " : "") + (ctx.printer && ctx.printer.held ? "The queue is held: release it (above) to start the next job." : "")
      : "Nothing queued.";
    queueHint.hidden = !queueHint.textContent;
    const ended = jobs.filter((j) => !["queued", "printing", "paused"].includes(j.state)).slice(0, SHOWN);
    history.replaceChildren(...(ended.length ? ended.map(historyRow) : [h("p", { class: "empty" }, "No job has ended on this printer yet.")]));
  }

  function queuedRow(job, index, waiting) {
    const up = h("button", { type: "button", class: "move", "aria-label": "move up", title: "move up", disabled: index === 0, onclick: () => move(job.id, waiting[index - 1].id) }, "↑");
    const down = h("button", { type: "button", class: "move", "aria-label": "move down", title: "move down", disabled: index === waiting.length - 1, onclick: () => move(job.id, waiting[index + 2] ? waiting[index + 2].id : null) }, "↓");
    const cancel = h("button", { type: "button", class: "danger cancel", onclick: () => cancelJob(job) }, "Cancel");
    const row = h("li", { class: "queue-row", draggable: "true", dataset: { job: String(job.id) } },
      h("span", { class: "grip", "aria-hidden": "true", title: "drag to reorder" }, "⠿"),
      h("div", { class: "queue-main" },
        h("div", { class: "queue-name" }, job.name),
        h("div", { class: "muted queue-meta" }, [`job ${job.id}`, `queued ${clock(job.submitted)}`, job.user ? `by ${job.user}` : "", job.total_lines ? `${job.total_lines} lines` : "", job.from_line ? `from line ${job.from_line}` : ""].filter(Boolean).join(" · ")),
        h("div", { class: "queue-estimate" }, estimate(job))),
      h("div", { class: "queue-actions" }, up, down, cancel));
    // Whether the dragged job comes from below this one.
    const upward = (id) => waiting.findIndex((j) => j.id === id) > index;
    row.addEventListener("dragstart", (event) => {
      dragged = job.id;
      event.dataTransfer.effectAllowed = "move";
      event.dataTransfer.setData("text/plain", String(job.id));
      row.classList.add("dragging");
    });
    row.addEventListener("dragend", () => {
      dragged = null;
      clearMarks();
    });
    row.addEventListener("dragover", (event) => {
      if (dragged === null) return;
      event.preventDefault();
      event.dataTransfer.dropEffect = "move";
      clearMarks();
      if (dragged !== job.id) row.classList.add(upward(dragged) ? "drop-before" : "drop-after");
    });
    row.addEventListener("drop", (event) => {
      if (dragged === null) return;
      event.preventDefault();
      const id = dragged;
      dragged = null;
      clearMarks();
      // The dropped job takes this one's place: before it when it came from below, after
      // it when it came from above.
      if (id === job.id) return;
      const next = upward(id) ? job : waiting[index + 1];
      move(id, next ? next.id : null);
    });
    return row;
  }

  /** "about 42 min · ends ~15:10", "about 42 min" (its start not known), "no estimate yet". */
  function estimate(job) {
    if (job.estimated_time == null) return "no estimate yet";
    const whole = job.estimated_time_whole_file ? " (the whole file's)" : "";
    const ends = job.estimated_end ? ` · ends ~${clock(job.estimated_end)}` : "";
    return `${duration(job.estimated_time, { rough: true })}${whole}${ends}`;
  }

  function clearMarks() {
    for (const row of queued.children) row.classList.remove("drop-before", "drop-after", "dragging");
  }

  async function move(id, before) {
    try {
      jobs = await api.post(`/v1/jobs/${id}/move`, { before });
      render();
    } catch (error) {
      ctx.say(`Job ${id} was not moved: ${error.message}`);
      load();
    }
  }

  async function cancelJob(job) {
    try {
      await api.del(`/v1/jobs/${job.id}`);
      ctx.say("");
    } catch (error) {
      ctx.say(`Job ${job.id} was not cancelled: ${error.message}`);
    }
    load();
  }

  function historyRow(job) {
    const lasted = job.started && job.ended ? duration(job.ended - job.started) : "";
    const lines = job.total_lines ? `${job.lines} of ${job.total_lines} lines` : `${job.lines} lines`;
    const facts = [job.started ? `started ${clock(job.started)}` : "never started", lasted, lines, job.from_line ? `from line ${job.from_line}` : "", job.user ? `by ${job.user}` : ""];
    const again = h("button", { type: "button", class: "again", onclick: () => queueFile(job, {}, again) }, "Print again");
    if (paths && !paths.has(job.path)) {
      again.disabled = true;
      again.title = `the file ${job.path} is no longer on the server`;
    }
    const actions = [again];
    if (job.report && job.report.text) {
      actions.push(h("button", { type: "button", class: "report-toggle", "aria-expanded": String(reports.has(job.id)), onclick: () => { reports.has(job.id) ? reports.delete(job.id) : reports.add(job.id); render(); } }, reports.has(job.id) ? "Hide report" : "Report"));
    }
    if (job.state !== "completed" && job.last_line > 0) {
      const resume = h("button", { type: "button", class: "resume", onclick: () => showResume(job, resume) }, "Resume…");
      if (paths && !paths.has(job.path)) {
        resume.disabled = true;
        resume.title = again.title;
      }
      actions.push(resume);
    }
    return h("div", { class: "history-row", dataset: { job: String(job.id), state: job.state } },
      h("div", { class: "history-info" },
        h("div", { class: "history-head" },
          h("span", { class: `badge ${OUTCOME[job.state] || "offline"}` }, job.state),
          h("strong", { class: "history-name", title: job.path }, job.name),
          h("span", { class: "muted" }, `job ${job.id}`)),
        h("div", { class: "muted history-meta" }, facts.filter(Boolean).join(" · ")),
        job.error ? h("div", { class: "error history-error" }, job.error) : null),
      h("div", { class: "history-actions" }, actions),
      reports.has(job.id) && job.report ? h("pre", { class: "report" }, job.report.text) : null,
      resumes.get(job.id) || null);
  }

  async function showResume(job, button) {
    if (resumes.has(job.id)) {
      resumes.delete(job.id);
      render();
      return;
    }
    button.disabled = true;
    let box;
    try {
      const where = await api.get(`/v1/jobs/${job.id}/resume`);
      const layer = where.from_layer;
      const queueIt = layer != null
        ? h("button", { type: "button", class: "primary queue-from", onclick: (event) => queueFile(job, { from_layer: layer }, event.target) }, `Queue from layer ${layer}`)
        : h("button", { type: "button", class: "primary queue-from", onclick: (event) => queueFile(job, { from_line: where.from_line }, event.target) }, `Queue from line ${where.from_line}`);
      box = h("div", { class: "resume-box" },
        h("p", {}, `It stopped before line ${where.from_line}${layer != null ? `, in layer ${layer}` : ""}. Check the part and the nozzle first. From a terminal:`),
        h("code", {}, where.layer_command || where.command),
        h("div", { class: "row" }, queueIt, h("button", { type: "button", onclick: () => { resumes.delete(job.id); render(); } }, "Close")));
    } catch (error) {
      box = h("div", { class: "resume-box" }, h("p", { class: "error" }, error.message));
    }
    resumes.set(job.id, box);
    render();
  }

  async function queueFile(job, where, button) {
    if (button) button.disabled = true;
    try {
      const made = await api.post(`${ctx.path}/queue`, { file: job.path, ...where });
      resumes.delete(job.id);
      const shown = made.findings && made.findings.length ? ` (the check warns: ${made.findings.length})` : "";
      ctx.say(`${job.name} queued again as job ${made.id}${shown}.`, "info");
      setTimeout(() => ctx.say(""), 4000);
    } catch (error) {
      const found = (error.body && error.body.detail && error.body.detail.findings) || [];
      ctx.say(error.status === 404 ? `${job.name} cannot be printed again: ${error.message} (it was deleted)` : `${error.message}${found.length ? `: ${found.join("; ")}` : ""}`);
      if (button) button.disabled = false;
    }
    load();
  }

  function showTotals(sums) {
    const counts = Object.entries(sums.jobs || {}).filter(([, n]) => n);
    const tools = Object.entries(sums.filament || {});
    totals.replaceChildren(h("dl", {},
      h("dt", {}, "printing"), h("dd", {}, duration(sums.print_seconds || 0)),
      h("dt", {}, "jobs"), h("dd", {}, counts.length ? counts.map(([state, n]) => h("span", { class: `badge ${OUTCOME[state] || "offline"}` }, `${n} ${state}`)) : "none ended yet"),
      h("dt", {}, "filament"), h("dd", {}, tools.length ? tools.map(([tool, used]) => `${tool}: ${metres(used.length)}`).join(" · ") : "none"),
      h("dt", {}, "lines"), h("dd", {}, String(sums.lines || 0))));
  }

  ctx.stream.on("job", later);
  ctx.stream.on("file", later);
  ctx.stream.onReconnect(load);
  let held = null;
  let shownFree = ""; // the printer's free time ("15:10") when the queue was last listed
  let listedAt = 0;
  ctx.onChange((printer) => {
    // The queued jobs' ends move with the running job's time left: listed again when the
    // printer's free time shows another minute, so that the last end and the header agree
    // (every 10 s at most, not every progress: a drag would be cut off).
    const free = clock(printer.free_at);
    if (free && free !== shownFree && jobs.some((j) => j.state === "queued") && Date.now() - listedAt > 10000) {
      shownFree = free;
      listedAt = Date.now();
      later();
    }
    // The "held" hint follows the printer.
    if (printer.held === held) return;
    held = printer.held;
    if (jobs.length) {
      render();
      later(); // held, the queued jobs have no start: released, they have again
    }
  });
  load();
}

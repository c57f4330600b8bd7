// The job: the running one (or, when none runs, the last one), its progress, Pause, Resume
// and Cancel, and a layer view that draws a layer's moves from the file, the ones the
// controller acknowledged in blue, and marks when the running job prints the layer shown.
// After a job stopped part-way, the offer to resume it.

import { h, clock, duration } from "../api.js";

const ENDED = new Set(["completed", "failed", "interrupted", "cancelled"]);
const RESUMABLE = new Set(["failed", "interrupted", "cancelled"]);
const STATE_CLASS = { printing: "busy", paused: "paused", completed: "ok", cancelled: "offline", interrupted: "held", failed: "error" };
const LEFT_FROM = { estimate: "(planned, at this printer's pace)", plan: "(planned)", slicer: "(slicer's estimate)", linear: "(at the rate so far)" };
const CACHED_LAYERS = 8;
const MARK_REFRESH = 5000; // ms: the layer's times are asked again at most this often
const COLOURS = { done: "#1d63c9", todo: "#a9b1bd", travelDone: "rgba(29, 99, 201, 0.35)", travelTodo: "rgba(120, 130, 145, 0.3)", area: "#dde1e7" };

/** A path below the uploads, as a URL path ("parts/a b.gcode" -> "parts/a%20b.gcode"). */
const urlPath = (path) => path.split("/").map(encodeURIComponent).join("/");
const count = (n) => (n == null ? "?" : Number(n).toLocaleString());

export async function mount(body, ctx) {
  const api = ctx.api;
  let fetchedLast = null; // the newest ended job, asked of the server at mount
  let shownId = null; // the job shown
  let shownPhase = null; // and whether it runs, or how it ended
  const resumes = new Map(); // job id -> its resume offer (null: none), once answered
  const asked = new Set(); // job ids whose resume offer is asked for
  const layers = new Map(); // "path\nN" -> the layer's moves (a promise), the last few
  const layerCounts = new Map(); // path -> its layer count, as the layers answer says
  let view = { path: null, layer: 0, data: null }; // the layer drawn
  let follow = true; // the view follows the printed layer until the person moves the slider
  let drawing = 0;
  let times = { key: null, answer: null, asked: 0, pending: false }; // the shown layer's

  // The summary.
  const title = h("div", { class: "job-title" });
  const name = h("strong", { class: "job-file" });
  const state = h("span", { class: "badge job-state" });
  const bar = h("div");
  const percent = h("span", { class: "job-percent" });
  const facts = h("dl", { class: "job-facts" });
  const failure = h("p", { class: "error job-error", hidden: true });
  const pause = h("button", { type: "button", id: "job-pause", onclick: () => act("pause") }, "Pause");
  const resume = h("button", { type: "button", id: "job-resume", class: "primary", onclick: () => act("resume") }, "Resume");
  const cancel = h("button", { type: "button", id: "job-cancel", class: "danger", onclick: () => act("cancel") }, "Cancel");
  const offer = h("div", { class: "job-resume-offer", hidden: true });
  const summary = h("div", { class: "job-summary" },
    title, h("div", { class: "row job-head" }, name, state),
    h("div", { class: "job-progress" }, h("div", { class: "bar" }, bar), percent),
    facts, failure, h("div", { class: "row job-buttons" }, pause, resume, cancel), offer);

  // The layer view.
  const canvas = h("canvas", { class: "layer-canvas", dataset: { layer: "0", moves: "0", acked: "0" } });
  const slider = h("input", { type: "range", min: 1, max: 1, value: 1, class: "layer-slider", "aria-label": "layer shown", oninput: () => { follow = false; followBox.checked = false; show(Number(slider.value)); } });
  const followBox = h("input", { type: "checkbox", checked: true, onchange: () => { follow = followBox.checked; sync(); } });
  const layerWords = h("span", { class: "layer-words" });
  const layerNote = h("p", { class: "muted layer-note", hidden: true });
  const layerMark = h("p", { class: "layer-mark", hidden: true });
  const viewer = h("div", { class: "layer-view" }, canvas,
    h("div", { class: "row layer-tools" }, slider, layerWords,
      h("label", { class: "layer-follow", title: "show the layer being printed" }, followBox, " follow the print")),
    layerMark, layerNote);

  const empty = h("p", { class: "empty" }, "no job: upload a file in Files below and print it");
  body.append(empty, summary, viewer);

  /** The job shown: the running one, else the one that ended last. */
  function shownJob() {
    const printer = ctx.printer || {};
    if (printer.job) return { job: printer.job, running: true };
    const last = ctx.lastJob || fetchedLast;
    return { job: last, running: false };
  }

  async function act(action) {
    const { job } = shownJob();
    if (action === "cancel" && !window.confirm(`Cancel job ${job ? `${job.id} (${job.name})` : ""}? The safe stop runs first.`)) return;
    try {
      await api.post(`${ctx.path}/${action}`);
    } catch (error) {
      ctx.say(error.message);
    }
  }

  function fact(label, value, note) {
    return h("div", {}, h("dt", {}, label), h("dd", {}, value, note ? h("span", { class: "muted" }, ` ${note}`) : null));
  }

  function render() {
    const { job, running } = shownJob();
    empty.hidden = Boolean(job);
    summary.hidden = viewer.hidden = !job;
    for (const [button, action] of [[pause, "pause"], [resume, "resume"], [cancel, "cancel"]]) ctx.allow(button, action);
    if (!job) return;
    const printer = ctx.printer;
    const jobState = running ? (printer.phase ? `${printer.phase}…` : printer.state === "paused" ? "paused" : "printing") : job.state;
    title.textContent = running ? "" : "No job is running. The last one:";
    title.hidden = running;
    name.textContent = job.name;
    name.title = job.path || job.name;
    state.textContent = jobState;
    state.className = `badge job-state ${STATE_CLASS[running ? (printer.state === "paused" ? "paused" : "printing") : job.state] || ""}`;
    const done = running ? job.completion ?? 0 : job.state === "completed" ? 100 : job.total_lines ? (100 * job.lines) / job.total_lines : 0;
    bar.style.width = `${Math.min(100, done)}%`;
    percent.textContent = `${done.toFixed(done < 10 ? 1 : 0)} %`;

    const rows = [];
    const total = layersOf(job);
    if (running && total) rows.push(fact("Layer", `${Math.max(job.layer, 1)} of ${total}`));
    rows.push(fact("Lines acknowledged", `${count(job.lines)} of ${count(job.total_lines)}`, job.from_line ? `(resumed from line ${count(job.from_line)})` : ""));
    if (running) {
      // The server's figures as it gives them: the whole job's, the time left, the end.
      const whole = job.estimated_time != null ? `of ${duration(job.estimated_time, { rough: true })}` : "";
      if (job.started) rows.push(fact("Elapsed", duration(Date.now() / 1000 - job.started), whole));
      if (job.time_left != null) rows.push(fact("Time left", duration(job.time_left), LEFT_FROM[job.time_left_from] || ""));
      else rows.push(fact("Time left", "being planned"));
      if (job.ends && printer.state !== "paused") rows.push(fact("Ends", clock(job.ends)));
    } else {
      if (job.started && job.ended) rows.push(fact("Ran", duration(job.ended - job.started)));
      if (job.ended) rows.push(fact("Ended", clock(job.ended)));
    }
    facts.replaceChildren(...rows);
    failure.textContent = running ? "" : job.error || "";
    failure.hidden = !failure.textContent;

    if (shownId !== job.id) { // another job: the view follows it
      shownId = job.id;
      follow = true;
      followBox.checked = true;
    }
    const phase = `${job.id} ${running ? "running" : job.state}`;
    if (shownPhase !== phase) { // it ended (or another is shown): resumable?
      shownPhase = phase;
      offer.hidden = true;
      offer.replaceChildren();
      if (!running && RESUMABLE.has(job.state) && job.last_line > 0) offerResume(job);
    }
    sync();
  }

  // The resume offer: the command hyrel-send runs, and a button that queues the same.
  async function offerResume(job) {
    if (!resumes.has(job.id) && !asked.has(job.id)) {
      asked.add(job.id);
      try {
        resumes.set(job.id, await api.get(`/v1/jobs/${job.id}/resume`));
      } catch (error) {
        resumes.set(job.id, null); // completed, or none of it ran: nothing to resume
      }
      asked.delete(job.id);
    }
    const answer = resumes.get(job.id);
    if (!answer || shownPhase !== `${job.id} ${job.state}`) return;
    const byLayer = answer.from_layer != null && answer.layer_command;
    const where = byLayer ? `layer ${answer.from_layer}` : `line ${count(answer.from_line)}`;
    const status = h("span", { class: "muted job-queued" });
    const queue = h("button", { type: "button", class: "primary", id: "job-queue-resumed" }, `Queue the resumed job (from ${where})`);
    queue.addEventListener("click", async () => {
      const wanted = byLayer ? { file: answer.file, from_layer: answer.from_layer } : { file: answer.file, from_line: answer.from_line };
      queue.disabled = true;
      try {
        const queued = await api.post(`${ctx.path}/queue`, wanted);
        queue.title = `queued already as job ${queued.id}`;
        status.textContent = `Queued as job ${queued.id}.${ctx.printer && ctx.printer.held ? " The queue is held: release it (above) to start it." : ""}`;
      } catch (error) {
        queue.disabled = false;
        ctx.say(error.message);
      }
    });
    offer.replaceChildren(
      h("p", {}, `Job ${job.id} stopped after line ${count(answer.from_line - 1)} of its file${answer.from_layer ? `, in layer ${answer.from_layer}` : ""}. `,
        `Resume it from the start of ${where}, here or from a shell:`),
      h("code", { class: "job-resume-command" }, byLayer ? answer.layer_command : answer.command),
      h("div", { class: "row" }, queue, status));
    offer.hidden = false;
    if (follow) sync();
  }

  // Layers: fetched once each (the last few kept), drawn again at each progress.
  function layersOf(job) {
    return job.layers || layerCounts.get(job.path) || 0;
  }

  function fetchLayer(path, number) {
    const key = `${path}\n${number}`;
    let found = layers.get(key);
    if (found) {
      layers.delete(key); // the newest at the end
    } else {
      found = api.get(`/v1/files/${urlPath(path)}/layers/${number}`).then((data) => {
        layerCounts.set(path, data.layers);
        return data;
      });
      found.catch(() => layers.delete(key));
    }
    layers.set(key, found);
    while (layers.size > CACHED_LAYERS) layers.delete(layers.keys().next().value);
    return found;
  }

  /** The layer being printed (or where the last job stopped). */
  function currentLayer(job, running) {
    if (running) return Math.max(1, job.layer || 1);
    const total = layersOf(job);
    if (job.state === "completed") return total || 1;
    const answer = resumes.get(job.id);
    if (answer && answer.from_layer) return answer.from_layer;
    return view.path === job.path && view.layer ? view.layer : total || 1; // where it was
  }

  function sync() {
    const { job, running } = shownJob();
    if (!job) return;
    if (!job.layers && !layerCounts.has(job.path)) {
      fetchLayer(job.path, 1).then(sync, (error) => {
        if (error.status === 404) layerCounts.set(job.path, 0); // no layers: asked once
        noLayers(error.status === 404 ? "" : error.message);
      });
      return;
    }
    const total = layersOf(job);
    if (!total) return noLayers("");
    layerNote.hidden = true;
    canvas.hidden = false;
    slider.max = total;
    slider.disabled = total < 2;
    const wanted = follow ? currentLayer(job, running) : Math.min(Number(slider.value), total);
    if (follow && running && job.layer < total) fetchLayer(job.path, job.layer + 1); // ready for the next
    show(wanted);
  }

  function noLayers(why) {
    canvas.hidden = true;
    layerMark.hidden = true;
    layerNote.hidden = false;
    layerNote.textContent = why ? `No layer view: ${why}` : "No layer view: this file marks no layers.";
    slider.disabled = true;
  }

  function show(number) {
    const { job } = shownJob();
    if (!job) return;
    slider.value = number;
    if (view.path === job.path && view.layer === number && view.data) return redraw();
    fetchLayer(job.path, number).then(
      (data) => {
        const now = shownJob().job;
        if (!now || now.path !== job.path || Number(slider.value) !== number) return;
        view = { path: job.path, layer: number, data };
        redraw();
      },
      (error) => ctx.say(`layer ${number}: ${error.message}`),
    );
  }

  function redraw() {
    if (!drawing) drawing = requestAnimationFrame(() => { drawing = 0; draw(); });
  }

  function draw() {
    const { job, running } = shownJob();
    const data = view.data;
    if (!job || !data) return;
    const lastLine = running || job.state !== "completed" ? job.last_line || 0 : Infinity;
    const width = canvas.clientWidth;
    const height = canvas.clientHeight;
    if (!width || !height) return;
    const ratio = window.devicePixelRatio || 1;
    canvas.width = Math.round(width * ratio);
    canvas.height = Math.round(height * ratio);
    const pen = canvas.getContext("2d");
    pen.setTransform(ratio, 0, 0, ratio, 0, 0);
    pen.clearRect(0, 0, width, height);

    const moves = data.moves;
    let box = data.area;
    if (!box) {
      box = { minX: Infinity, maxX: -Infinity, minY: Infinity, maxY: -Infinity };
      for (const [, x0, y0, x1, y1] of moves) {
        box.minX = Math.min(box.minX, x0, x1); box.maxX = Math.max(box.maxX, x0, x1);
        box.minY = Math.min(box.minY, y0, y1); box.maxY = Math.max(box.maxY, y0, y1);
      }
    }
    const margin = 10;
    const spanX = Math.max(box.maxX - box.minX, 1e-3);
    const spanY = Math.max(box.maxY - box.minY, 1e-3);
    const scale = Math.min((width - 2 * margin) / spanX, (height - 2 * margin) / spanY);
    const left = (width - spanX * scale) / 2;
    const top = (height - spanY * scale) / 2;
    const x = (value) => left + (value - box.minX) * scale;
    const y = (value) => top + (box.maxY - value) * scale; // Y up
    if (moves.length) {
      pen.strokeStyle = COLOURS.area;
      pen.setLineDash([4, 4]);
      pen.lineWidth = 1;
      pen.strokeRect(x(box.minX), y(box.maxY), spanX * scale, spanY * scale);
    }

    const paths = { done: new Path2D(), todo: new Path2D(), travelDone: new Path2D(), travelTodo: new Path2D() };
    let acked = 0;
    let head = null;
    for (const [line, x0, y0, x1, y1, extrudes] of moves) {
      const isDone = line <= lastLine;
      if (isDone) {
        acked += 1;
        head = [x1, y1];
      }
      const path = paths[extrudes ? (isDone ? "done" : "todo") : isDone ? "travelDone" : "travelTodo"];
      path.moveTo(x(x0), y(y0));
      path.lineTo(x(x1), y(y1));
    }
    pen.lineCap = "round";
    pen.setLineDash([3, 4]);
    pen.lineWidth = 1;
    pen.strokeStyle = COLOURS.travelTodo;
    pen.stroke(paths.travelTodo);
    pen.strokeStyle = COLOURS.travelDone;
    pen.stroke(paths.travelDone);
    pen.setLineDash([]);
    pen.lineWidth = 1.6;
    pen.strokeStyle = COLOURS.todo;
    pen.stroke(paths.todo);
    pen.strokeStyle = COLOURS.done;
    pen.stroke(paths.done);
    if (running && head && acked < moves.length) {
      pen.fillStyle = "#e0552b"; // where the nozzle is
      pen.beginPath();
      pen.arc(x(head[0]), y(head[1]), 4, 0, 2 * Math.PI);
      pen.fill();
    }
    canvas.dataset.layer = String(data.layer);
    canvas.dataset.moves = String(moves.length);
    canvas.dataset.acked = String(acked);
    const total = layersOf(job);
    const z = data.z != null ? ` · Z ${data.z} mm` : "";
    layerWords.textContent = `Layer ${data.layer} of ${total}${z}`;
    markLayer(job, running, data.layer);
  }

  // The layer's mark while a job runs: the layers below the one it prints are printed, the
  // one it prints is printing (done when its plan says), the ones above start when its plan
  // says (the layer's times asked of the server, again as progress comes, at most every
  // MARK_REFRESH ms). Which layer is which follows the job's own layer, as "Layer" above.
  function markLayer(job, running, number) {
    if (!running) return showMark(null);
    const key = `${job.id}\n${job.path}\n${number}`;
    if (times.key !== key) times = { key, answer: null, asked: 0, pending: false }; // asked at once
    const printed = number < (job.layer || 0);
    // Asked again sooner once the layer's planned end has passed (the job runs late).
    const late = times.answer && times.answer.ends_at && Date.parse(times.answer.ends_at) < Date.now();
    const wait = late ? MARK_REFRESH / 5 : MARK_REFRESH;
    if (!printed && !times.pending && Date.now() - times.asked >= wait) askTimes(job.path, number, key);
    showMark(printed ? "printed" : number === job.layer ? "printing" : "ahead", times.answer);
  }

  async function askTimes(path, number, key) {
    times.asked = Date.now();
    times.pending = true;
    const printer = encodeURIComponent(ctx.name);
    try {
      const answer = await api.get(`/v1/files/${urlPath(path)}/layers/${number}?printer=${printer}&moves=false`);
      if (times.key === key) {
        times.answer = answer;
        redraw(); // marked again, as the job stands now
      }
    } catch (error) {
      // The mark stays as it was: asked again at the next progress.
    } finally {
      if (times.key === key) times.pending = false;
    }
  }

  /** The mark of a layer ``where`` the job is (printed, printing, ahead; null: none):
   * "printed", "printing now · done ~14:32", "starts ~15:10 (in about 38 min)". */
  function showMark(where, answer) {
    const words = where ? markWords(where, answer) : "";
    layerMark.textContent = words;
    layerMark.hidden = !words;
    layerMark.dataset.mark = words ? where : "";
    layerMark.classList.toggle("now", where === "printing");
    layerMark.classList.toggle("done", where === "printed");
  }

  function markWords(where, answer) {
    if (where === "printed") return "printed";
    const planned = answer && answer.starts_at && answer.ends_at;
    if (where === "printing") {
      // Done when the plan says, unless that time has passed (the job runs slower).
      const ends = planned ? Date.parse(answer.ends_at) / 1000 : null;
      return ends && ends > Date.now() / 1000 ? `printing now · done ~${clock(ends)}` : "printing now";
    }
    if (!planned) return "";
    const starts = Date.parse(answer.starts_at) / 1000;
    return `starts ~${clock(starts)} (in ${duration(Math.max(0, starts - Date.now() / 1000), { rough: true })})`;
  }

  ctx.onChange(render);
  setInterval(() => {
    if (ctx.printer && ctx.printer.job) render(); // the elapsed time
  }, 1000);
  new ResizeObserver(redraw).observe(canvas);
  ctx.stream.onReconnect(() => {
    resumes.clear(); // what happened meanwhile
    shownPhase = null;
    loadLast();
  });

  /** With no job running and none ended on this page: the newest that ended. */
  async function loadLast() {
    if ((ctx.printer && ctx.printer.job) || ctx.lastJob) return render();
    try {
      const jobs = await api.get(`${ctx.path}/jobs`);
      fetchedLast = jobs.find((job) => ENDED.has(job.state)) || null;
    } catch (error) {
      if (error.status !== 403) ctx.say(error.message);
    }
    render();
  }
  await loadLast();
}

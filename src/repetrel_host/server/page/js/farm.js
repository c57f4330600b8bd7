// The farm at a glance: every printer as a tile (state, the job's thumbnail, progress,
// temperatures, the held queue's Release), sorted and filtered; a tile opens the printer.

import { get, post, keyed, h, allow, clock, duration } from "./api.js";
import { category, stateWords, stateClass, whyNot } from "./state.js";

const FILTERS = ["all", "printing", "idle", "held", "offline", "error"];
const SORTS = { name: "name", state: "state", left: "time left" };
const STATE_ORDER = { error: 0, offline: 1, held: 2, printing: 3, idle: 4 };

export async function mount(main, { stream, say }) {
  const printers = new Map(); // name -> the printer's JSON, kept up to date by the stream
  const thumbnails = new Map(); // file path -> its thumbnail's URL
  let filter = localStorage.getItem("farm-filter") || "all";
  let sort = localStorage.getItem("farm-sort") || "name";

  const chips = h("div", { class: "chips", role: "group", "aria-label": "show" });
  const sortSelect = h(
    "select",
    { id: "farm-sort", "aria-label": "sort by", onchange: () => { sort = sortSelect.value; localStorage.setItem("farm-sort", sort); draw(); } },
    Object.entries(SORTS).map(([value, words]) => h("option", { value, selected: value === sort }, `sort by ${words}`)),
  );
  const grid = h("div", { id: "farm", class: "tiles" });
  const empty = h("p", { class: "empty", hidden: true }, "No printer in this group.");
  const farmWide = h("section", { id: "farm-wide", hidden: true });
  main.append(h("div", { class: "toolbar" }, chips, sortSelect), grid, empty, farmWide);
  document.getElementById("crumbs").textContent = "all printers";

  async function loadFiles() {
    try {
      for (const file of await get("/v1/files")) if (file.thumbnail) thumbnails.set(file.path, file.thumbnail);
    } catch (error) {
      /* no key yet: the header says so */
    }
  }

  async function load() {
    try {
      for (const printer of await get("/v1/printers")) printers.set(printer.name, printer);
      say("");
    } catch (error) {
      if (error.status !== 403) say(error.message);
    }
    await loadFiles();
    draw();
  }

  function drawChips() {
    const counts = Object.fromEntries(FILTERS.map((name) => [name, 0]));
    for (const printer of printers.values()) {
      counts.all += 1;
      counts[category(printer)] += 1;
    }
    chips.replaceChildren(
      ...FILTERS.map((name) =>
        h(
          "button",
          {
            type: "button",
            class: `chip ${name === filter ? "on" : ""}`,
            "aria-pressed": String(name === filter),
            dataset: { filter: name },
            onclick: () => { filter = name; localStorage.setItem("farm-filter", filter); draw(); },
          },
          `${name} `,
          h("span", { class: "count" }, counts[name]),
        ),
      ),
    );
  }

  function order(a, b) {
    if (sort === "state") {
      const difference = STATE_ORDER[category(a)] - STATE_ORDER[category(b)];
      if (difference) return difference;
    } else if (sort === "left") {
      const left = (p) => (p.job && p.job.time_left != null ? p.job.time_left : Infinity);
      if (left(a) !== left(b)) return left(a) - left(b);
    }
    return a.name.localeCompare(b.name);
  }

  const images = new Map(); // a thumbnail's element, kept: a redraw does not load it again

  function image(url, name) {
    if (!images.has(url)) images.set(url, h("img", { class: "thumb", src: keyed(url), alt: `${name}, as the slicer drew it` }));
    return images.get(url);
  }

  let drawing = false;
  const refreshing = new Map(); // printer name -> its timer

  function refresh(name) {
    // A job queued, started or ended moves the printer's free time: asked again (once for
    // several events in a row).
    clearTimeout(refreshing.get(name));
    refreshing.set(name, setTimeout(async () => {
      refreshing.delete(name);
      try {
        const printer = await get(`/v1/printers/${encodeURIComponent(name)}`);
        printers.set(name, { ...(printers.get(name) || {}), free_at: printer.free_at });
        schedule();
      } catch (error) {
        /* the next event or the reconnection tries again */
      }
    }, 300));
  }

  function schedule() {
    // Temperatures come every second from every printer: one redraw a frame at most.
    if (drawing) return;
    drawing = true;
    requestAnimationFrame(() => {
      drawing = false;
      draw();
    });
  }

  function draw() {
    drawChips();
    const shown = [...printers.values()].filter((p) => filter === "all" || category(p) === filter).sort(order);
    grid.replaceChildren(...shown.map(tile));
    empty.hidden = shown.length > 0 || printers.size === 0;
  }

  function temperatures(printer) {
    // The heaters as the server names them (a "T" beside T0, T1... is the active one: left
    // out), else every sensor reported.
    const readings = printer.temperatures || {};
    const heaters = printer.heaters && printer.heaters.length ? printer.heaters : Object.keys(readings).map((sensor) => ({ sensor, label: sensor }));
    return heaters
      .filter((heater) => readings[heater.sensor])
      .map((heater) => {
        const reading = readings[heater.sensor];
        const target = reading.target ? ` / ${Math.round(reading.target)}` : "";
        return h("span", { class: "reading", title: heater.label }, `${shortLabel(heater.sensor)} ${reading.actual.toFixed(0)}${target}°`);
      });
  }

  function tile(printer) {
    const job = printer.job;
    const href = `/printers/${encodeURIComponent(printer.name)}`;
    const thumbnail = job && thumbnails.get(job.path);
    const release = h("button", { type: "button", class: "release", onclick: async (event) => {
      event.preventDefault();
      try {
        await post(`/v1/printers/${encodeURIComponent(printer.name)}/release`);
      } catch (error) {
        say(error.message);
      }
    } }, "Release");
    allow(release, whyNot(printer, "release"));
    const percent = job && job.completion != null ? job.completion : null;
    return h(
      "article",
      { class: `tile is-${stateClass(printer)}`, dataset: { printer: printer.name, category: category(printer) } },
      h("a", { class: "open", href, "aria-label": `open printer ${printer.name}` }),
      h("header", {}, h("h2", {}, printer.name), h("span", { class: `badge ${stateClass(printer)}` }, stateWords(printer))),
      h(
        "div",
        { class: "body" },
        thumbnail ? image(thumbnail, job.name) : h("div", { class: "thumb none" }, job ? "no preview" : category(printer)),
        h(
          "div",
          { class: "facts" },
          job
            ? [
                h("div", { class: "file", title: job.name }, job.name),
                h("div", { class: "bar", role: "progressbar", "aria-valuenow": percent ?? 0 }, h("div", { style: `width:${percent ?? 0}%` })),
                h(
                  "div",
                  { class: "numbers" },
                  percent != null ? `${percent.toFixed(1)} %` : "",
                  job.layers ? ` · layer ${job.layer} of ${job.layers}` : "",
                  job.time_left != null ? ` · ${duration(job.time_left)} left${job.time_left_from === "slicer" ? " (slicer's estimate)" : ""}` : "",
                  // Its queue counted; a paused job has no end (the badge says why).
                  printer.free_at && printer.state !== "paused" ? ` · free at ${clock(printer.free_at)}` : "",
                ),
              ]
            : h("div", { class: "file idle" }, printer.error && category(printer) !== "offline" ? printer.error : "no job"),
          h("div", { class: "temps" }, temperatures(printer)),
          category(printer) === "offline" && printer.reason ? h("div", { class: "reason" }, printer.reason) : null,
        ),
      ),
      printer.held ? h("div", { class: "held" }, "The queue is held: clear the bed, then ", release) : null,
    );
  }

  stream.on("printer", (event) => {
    const known = printers.get(event.printer) || { name: event.printer };
    const { type, printer: _, ...fields } = event;
    printers.set(event.printer, { ...known, ...fields });
    schedule();
  });
  stream.on("progress", (event) => {
    const printer = printers.get(event.printer);
    if (!printer || !printer.job || printer.job.id !== event.job) return;
    Object.assign(printer.job, event);
    if ("free_at" in event) printer.free_at = event.free_at;
    schedule();
  });
  stream.on("job", (event) => {
    const printer = printers.get(event.printer);
    if (!printer) return;
    const job = event.job;
    if (job.state === "printing" || job.state === "paused") printer.job = { ...(printer.job || {}), ...job };
    else if (printer.job && printer.job.id === job.id) printer.job = null;
    refresh(event.printer);
    schedule();
  });
  stream.on("temperatures", (event) => {
    const printer = printers.get(event.printer);
    if (!printer) return;
    printer.temperatures = Object.fromEntries(Object.entries(event.readings).map(([sensor, [actual, target]]) => [sensor, { actual, target }]));
    schedule();
  });
  stream.on("file", () => {
    loadFiles().then(draw);
    for (const name of printers.keys()) refresh(name); // a queued job's file planned: its estimate
  });
  stream.onReconnect(load);
  await load();
  // A server in a farm shows the whole farm under its own printers.
  import("./panels/farmwide.js")
    .then((farmwide) => farmwide.mount(farmWide, { say }))
    .catch((error) => console.error("the farm's panel did not load", error));
}

function shortLabel(sensor) {
  return sensor === "B" ? "bed" : sensor === "C" ? "chamber" : sensor;
}

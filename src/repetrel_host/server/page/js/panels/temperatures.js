// Every heater of the printer: a live chart of the last half hour (each heater's actual
// temperature as a solid line, its target dashed in the same colour), then a table to set
// the targets, by hand, off, or from a material preset.

import uPlot from "../../vendor/uPlot.esm.js";
import { h, clock } from "../api.js";

const KEPT = 1800; // seconds the chart shows
const COLOURS = ["#d9480f", "#1d63c9", "#2b8a3e", "#9c36b5", "#c2255c", "#0b7285", "#e67700", "#5c940d"];
const KINDS = { head: 0, bed: 1, chamber: 2 };
const TICKS = [1, 2, 5, 10, 15, 30, 60, 120, 300, 600, 900, 1800, 3600]; // s between ticks

export async function mount(body, ctx) {
  let samples = []; // [{time, readings: {sensor: [actual, target]}}], oldest first
  let presets = {};
  let chart = null;
  let chartKey = "";
  const colours = new Map(); // sensor -> colour, in the order they appeared
  const buttons = [];
  const rows = new Map(); // sensor -> {actual, target} cells

  const plot = h("div", { class: "temps-chart" });
  const table = h("table", { class: "temps-table" });
  const legend = h("p", { class: "temps-key muted" }, "solid: actual · dashed: target");
  const why = h("p", { class: "panel-why muted", hidden: true });
  body.append(plot, legend, table, why);

  const colour = (sensor) => {
    if (!colours.has(sensor)) colours.set(sensor, COLOURS[colours.size % COLOURS.length]);
    return colours.get(sensor);
  };
  let known = []; // the heaters: the printer's, or asked again when a report names a new one
  const heaters = () => [...known].sort((a, b) => (KINDS[a.kind] ?? 3) - (KINDS[b.kind] ?? 3));
  const label = (sensor) => (heaters().find((heater) => heater.sensor === sensor) || {}).label || sensor;

  /** The sensors charted: the heaters', then any other the reports name ("T" beside T0,
   * T1... is the active one again, left out). */
  function sensors() {
    const found = heaters().map((heater) => heater.sensor);
    for (const sample of samples) for (const sensor of Object.keys(sample.readings)) if (!found.includes(sensor)) found.push(sensor);
    return charted(found);
  }
  const charted = (found) => found.filter((sensor) => !(sensor === "T" && found.some((other) => /^T\d+$/.test(other))));

  /** A report names a heater the printer's JSON has not (it was read before the first
   * report): the printer is asked again, once for each such set. */
  const asked = new Set();
  async function unknown(readings) {
    const missing = charted(Object.keys(readings)).filter((sensor) => !known.some((heater) => heater.sensor === sensor));
    if (!missing.length || asked.has(missing.join())) return;
    asked.add(missing.join());
    try {
      const printer = await ctx.api.get(ctx.path);
      if (ctx.printer) ctx.printer.heaters = printer.heaters; // for the other panels too
      changed(printer.heaters || []);
    } catch (error) {
      asked.delete(missing.join());
    }
  }

  function data(charted) {
    const columns = [samples.map((sample) => sample.time)];
    for (const sensor of charted) {
      const readings = samples.map((sample) => sample.readings[sensor]);
      columns.push(readings.map((reading) => (reading ? reading[0] : null)));
      // A target of 0 is a heater off: no line.
      columns.push(readings.map((reading) => (reading && reading[1] ? reading[1] : null)));
    }
    return columns;
  }

  function draw() {
    const charted = sensors();
    const key = charted.map((sensor) => `${sensor}=${label(sensor)}`).join("|");
    if (chart && key === chartKey) {
      chart.setData(data(charted));
      return;
    }
    if (chart) chart.destroy();
    chartKey = key;
    const series = [{}];
    for (const sensor of charted) {
      const stroke = colour(sensor);
      series.push({ label: label(sensor), stroke, width: 2, spanGaps: true, value: (u, v) => (v == null ? "–" : `${v.toFixed(1)} °C`) });
      series.push({ label: `${label(sensor)} target`, stroke, width: 1.5, dash: [6, 4], points: { show: false }, value: (u, v) => (v == null ? "off" : `${v} °C`) });
    }
    chart = new uPlot(
      {
        width: plot.clientWidth || 600,
        height: size().height,
        series,
        legend: { show: false },
        cursor: { drag: { x: false, y: false } },
        scales: { y: { range: (u, min, max) => [0, Math.max(60, Math.ceil(((max ?? 0) + 15) / 20) * 20)] } },
        axes: [
          // Times as the page writes them all (the browser's locale), a tick a second at most.
          { stroke: "#5d6778", grid: { stroke: "#eceff3" }, ticks: { stroke: "#eceff3" }, incrs: TICKS, values: (u, ticks, axis, space, step) => ticks.map((t) => clock(t, { seconds: step < 60 })) },
          { stroke: "#5d6778", grid: { stroke: "#eceff3" }, ticks: { stroke: "#eceff3" }, size: 44, values: (u, ticks) => ticks.map((t) => `${t}°`) },
        ],
      },
      data(charted),
      plot,
    );
    plot.uplot = chart; // for the page's tests: the series and data drawn
    for (const [sensor, row] of rows) row.swatch.style.background = colour(sensor);
  }

  const size = () => ({ width: plot.clientWidth || 600, height: plot.clientWidth < 500 ? 170 : 220 });
  new ResizeObserver(() => chart && plot.clientWidth && chart.setSize(size())).observe(plot);

  function add(time, readings) {
    samples.push({ time, readings });
    const oldest = time - KEPT;
    while (samples.length && samples[0].time < oldest) samples.shift();
  }

  async function load() {
    try {
      const answer = await ctx.api.get(`${ctx.path}/temperatures`);
      const history = answer.samples.map((sample) => ({
        time: sample.time,
        readings: Object.fromEntries(Object.entries(sample.readings).map(([s, r]) => [s, [r.actual, r.target]])),
      }));
      const last = history.length ? history[history.length - 1].time : -Infinity;
      samples = history.concat(samples.filter((sample) => sample.time > last));
      if (history.length) unknown(history[history.length - 1].readings);
    } catch (error) {
      ctx.say(error.message);
    }
    draw();
  }

  async function send(heater, target) {
    if (!Number.isFinite(target) || target < 0) {
      ctx.say(`${heater.label}: give a temperature in °C (0 turns it off)`);
      return;
    }
    try {
      await ctx.api.post(`${ctx.path}/command`, { command: heater.command.replace("{target}", String(target)) });
    } catch (error) {
      ctx.say(error.message);
    }
  }

  function button(text, attributes, onclick) {
    const made = h("button", { type: "button", ...attributes, onclick }, text);
    buttons.push(made);
    return made;
  }

  function fill() {
    rows.clear();
    buttons.length = 0;
    const head = h("tr", {}, h("th", {}, "Heater"), h("th", { class: "num" }, "Actual"), h("th", { class: "num" }, "Target"), h("th", {}, "Set"));
    const lines = heaters().map((heater) => {
      const actual = h("td", { class: "num actual" });
      const target = h("td", { class: "num target" });
      const swatch = h("span", { class: "swatch" });
      const input = h("input", { type: "number", min: 0, max: 500, step: 1, placeholder: "°C", "aria-label": `${heater.label} target` });
      const set = button("Set", { type: "submit", class: "set" });
      const form = h("form", { class: "set-target", onsubmit: (event) => (event.preventDefault(), send(heater, input.valueAsNumber)) }, input, set);
      const picks = Object.entries(presets)
        .map(([name, preset]) => [name, preset[heater.kind]])
        .filter(([, value]) => value != null)
        .map(([name, value]) => button(`${name} ${value}°`, { class: "preset", dataset: { preset: name, value } }, () => send(heater, value)));
      const off = button("Off", { class: "off" }, () => send(heater, 0));
      rows.set(heater.sensor, { actual, target, swatch });
      return h(
        "tr",
        { dataset: { sensor: heater.sensor } },
        h("td", { class: "label" }, swatch, heater.label),
        actual,
        target,
        h("td", { class: "controls" }, h("div", {}, form, off, picks.length ? h("span", { class: "presets" }, picks) : null)),
      );
    });
    table.replaceChildren(h("thead", {}, head), h("tbody", {}, lines));
    if (!lines.length) table.replaceChildren(h("tr", {}, h("td", { class: "empty" }, "No heater reported yet.")));
    for (const [sensor, row] of rows) row.swatch.style.background = colour(sensor);
    show();
    enable();
  }

  /** The latest reading of each heater in its row. */
  function show() {
    const latest = {};
    for (const sample of samples) Object.assign(latest, sample.readings);
    for (const [sensor, [actual, target]] of Object.entries((ctx.printer && ctx.printer.temperatures) || {}).map(([s, r]) => [s, [r.actual, r.target]])) {
      if (!(sensor in latest)) latest[sensor] = [actual, target];
    }
    for (const [sensor, row] of rows) {
      const [actual, target] = latest[sensor] || [null, null];
      row.actual.textContent = actual == null ? "–" : `${actual.toFixed(1)} °C`;
      row.target.textContent = target ? `${Math.round(target * 10) / 10} °C` : "off";
    }
  }

  function enable() {
    for (const made of buttons) ctx.allow(made, "command");
    why.hidden = !ctx.whyNot("command");
    why.textContent = `Targets wait: ${ctx.whyNot("command")}.`;
  }

  let heatersKey = null;
  function changed(list) {
    const key = JSON.stringify(list);
    if (key === heatersKey) return enable();
    heatersKey = key;
    known = list;
    fill();
    if (chart) draw();
  }

  ctx.stream.on("temperatures", (event) => {
    unknown(event.readings);
    add(event.time, event.readings);
    draw();
    show();
  });
  ctx.stream.onReconnect(load);

  try {
    presets = await ctx.api.get("/v1/presets");
  } catch (error) {
    presets = {};
  }
  heatersKey = null; // the table again, with the presets
  ctx.onChange((printer) => changed(printer.heaters || []));
  await load();
  show();
}

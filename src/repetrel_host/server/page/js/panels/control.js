// Moving the machine by hand: jog and home the axes, motors off, the part fan, extrude and
// retract, the feed and flow factors. Every button sends G-code through the command API,
// so all of it waits while a job streams (pause it first); the last reply shows below.

import { h } from "../api.js";

const STEPS = [0.1, 1, 10, 100];
const FEED = { X: 3000, Y: 3000, Z: 600 }; // mm/min

export function mount(body, ctx) {
  const buttons = [];
  const status = h("p", { class: "control-status muted", role: "status" }, "The controller's replies show here.");
  const why = h("p", { class: "panel-why muted", hidden: true });
  let step = 10;
  let queue = Promise.resolve();

  /** Send ``commands`` one after another (after what was sent before), stopping at the
   * first refusal; the last reply (or the refusal) goes in the status line. */
  function send(...commands) {
    queue = queue.then(async () => {
      status.className = "control-status muted";
      status.textContent = `${commands.join(" · ")} …`;
      let reply = null;
      for (const [index, command] of commands.entries()) {
        try {
          reply = await ctx.api.post(`${ctx.path}/command`, { command });
        } catch (error) {
          status.className = "control-status error";
          status.textContent = `${command}: ${error.message}`;
          // A jog cut short after G91 leaves the machine relative: back to absolute.
          if (index > 0 && commands.includes("G90")) ctx.api.post(`${ctx.path}/command`, { command: "G90" }).catch(() => {});
          return;
        }
      }
      const said = [...(reply.lines || []), reply.ok_line].filter(Boolean).join(" · ");
      status.className = "control-status";
      status.textContent = `${commands.join(" · ")} → ${said || "sent"}`;
    });
    return queue;
  }

  function button(text, attributes, onclick) {
    const made = h("button", { type: "button", ...attributes, onclick }, text);
    buttons.push(made);
    return made;
  }

  // Jog: the step, then X/Y as a cross and Z beside it.
  const steps = h(
    "div",
    { class: "segmented", role: "radiogroup", "aria-label": "jog step" },
    STEPS.map((size) =>
      h(
        "label",
        {},
        h("input", { type: "radio", name: `jog-step-${ctx.name}`, value: size, checked: size === step, onchange: () => (step = size) }),
        h("span", {}, `${size}`),
      ),
    ),
  );
  const jog = (axis, sign, text) =>
    button(text, { class: `jog jog-${axis.toLowerCase()}${sign > 0 ? "plus" : "minus"}`, dataset: { axis, sign } }, () =>
      send("G91", `G1 ${axis}${sign < 0 ? "-" : ""}${step} F${FEED[axis]}`, "G90"),
    );
  const pad = h(
    "div",
    { class: "jog-pad" },
    jog("Y", 1, "Y+"),
    jog("X", -1, "X−"),
    jog("X", 1, "X+"),
    jog("Y", -1, "Y−"),
    jog("Z", 1, "Z+"),
    jog("Z", -1, "Z−"),
  );
  const homeZ = () => {
    if (window.confirm("Home Z? The head goes down to the bed: make sure nothing is on it.")) send("G28 Z");
  };
  const line = (what, ...controls) => h("div", { class: "line" }, h("span", { class: "what" }, what), h("div", { class: "row" }, controls));
  const homes = line(
    "Home",
    button("Home X Y", { class: "home-xy" }, () => send("G28 X Y")),
    button("Home Z", { class: "home-z" }, homeZ),
    button("Home all", { class: "home-all" }, () => send("G28")),
    button("Motors off", { class: "motors-off" }, () => send("M84")),
  );

  // The part fan, in percent.
  const fan = h("input", { type: "range", min: 0, max: 100, step: 5, value: 100, class: "fan", "aria-label": "fan speed" });
  const fanShown = h("output", { class: "fan-shown" }, "100 %");
  fan.addEventListener("input", () => (fanShown.textContent = `${fan.value} %`));
  const fanRow = line(
    "Fan",
    h("span", { class: "group fan-group" }, fan, fanShown),
    h(
      "span",
      { class: "group" },
      button("Fan on", { class: "fan-on" }, () => send(`M106 S${Math.round((fan.valueAsNumber * 255) / 100)}`)),
      button("Fan off", { class: "fan-off" }, () => send("M107")),
    ),
  );

  // Extrude and retract with a head.
  const head = h("select", { class: "head", "aria-label": "head" });
  const amount = h("input", { type: "number", min: 0.1, max: 500, step: 0.1, value: 5, class: "amount", "aria-label": "length in mm" });
  const speed = h("input", { type: "number", min: 1, max: 6000, step: 1, value: 100, class: "speed", "aria-label": "feed in mm/min" });
  const extrude = (sign) => {
    const length = amount.valueAsNumber;
    const feed = speed.valueAsNumber;
    if (!(length > 0) || !(feed > 0) || head.value === "") {
      status.className = "control-status error";
      status.textContent = head.value === "" ? "no head to extrude with" : "give a length and a feed above 0";
      return;
    }
    send(`T${head.value}`, "M83", `G1 E${sign < 0 ? "-" : ""}${length} F${feed}`);
  };
  const extrusion = line(
    "Extrude",
    h("span", { class: "group" }, head, h("label", {}, amount, " mm"), h("label", {}, "at ", speed, " mm/min")),
    h("span", { class: "group" }, button("Extrude", { class: "extrude" }, () => extrude(1)), button("Retract", { class: "retract" }, () => extrude(-1))),
  );

  // Feed and flow factors, in percent.
  const factor = (name, code, what) => {
    const input = h("input", { type: "number", min: 10, max: 500, step: 1, value: 100, class: name, "aria-label": `${what} in percent` });
    return h(
      "label",
      { class: "factor" },
      `${what} `,
      input,
      " % ",
      button("Set", { class: `set-${name}` }, () =>
        input.valueAsNumber > 0 ? send(`${code} S${Math.round(input.valueAsNumber)}`) : (status.textContent = `give the ${what.toLowerCase()} in percent`),
      ),
    );
  };
  const factors = line("Factors", factor("feed", "M220", "Feed"), factor("flow", "M221", "Flow"));

  body.append(
    line("Jog", h("div", { class: "control-jog" }, h("div", { class: "step" }, h("span", { class: "muted" }, "step (mm)"), steps), pad)),
    homes,
    fanRow,
    extrusion,
    factors,
    why,
    status,
  );
  body.classList.add("control");

  let headsKey = null;
  function heads(heaters) {
    const found = heaters.filter((heater) => heater.kind === "head");
    const key = JSON.stringify(found.map((heater) => [heater.tool, heater.label]));
    if (key === headsKey) return;
    headsKey = key;
    const chosen = head.value;
    head.replaceChildren(...found.map((heater) => h("option", { value: heater.tool }, heater.label)));
    if (found.some((heater) => String(heater.tool) === chosen)) head.value = chosen;
  }
  ctx.onChange((printer) => {
    for (const made of buttons) ctx.allow(made, "command");
    why.hidden = !ctx.whyNot("command");
    why.textContent = `The controls wait: ${ctx.whyNot("command")}.`;
    heads(printer.heaters || []);
  });

  // The printer's JSON read before its first report has no heads yet: a report naming a
  // head the list has not asks the printer again (once for each such set).
  const asked = new Set();
  ctx.stream.on("temperatures", async (event) => {
    const known = ((ctx.printer && ctx.printer.heaters) || []).map((heater) => heater.sensor);
    const reported = Object.keys(event.readings).filter((sensor) => /^T\d*$/.test(sensor));
    const numbered = reported.filter((sensor) => sensor !== "T"); // "T" beside them: the active one
    const missing = (numbered.length ? numbered : reported).filter((sensor) => !known.includes(sensor));
    if (!missing.length || asked.has(missing.join())) return;
    asked.add(missing.join());
    try {
      const printer = await ctx.api.get(ctx.path);
      if (ctx.printer) ctx.printer.heaters = printer.heaters;
      heads(printer.heaters || []);
    } catch (error) {
      asked.delete(missing.join());
    }
  });
}

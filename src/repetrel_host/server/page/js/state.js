// A printer's state in words and colour, and what can be done now (and why not): every
// button of the page asks here, so none is enabled when its action cannot work.

import { clock } from "./api.js";

const OFFLINE = new Set(["disconnected", "connecting", "closed", "offline"]);

export function isOffline(printer) {
  return OFFLINE.has(printer.state);
}

/** The farm view's groups: printing, idle, held, offline, error. */
export function category(printer) {
  if (isOffline(printer)) return "offline";
  if (printer.state === "printing" || printer.state === "paused") return "printing";
  if (printer.error) return "error";
  if (printer.held) return "held";
  return "idle";
}

/** The state as a person reads it: "printing", "paused", "ready", "offline since 10:42". */
export function stateWords(printer) {
  if (printer.phase === "pausing") return "pausing…";
  if (printer.phase === "resuming") return "resuming…";
  if (isOffline(printer)) {
    const since = printer.since ? ` since ${clock(printer.since)}` : "";
    return printer.state === "closed" ? `disconnected${since}` : `offline${since}`;
  }
  if (printer.state === "ready" && printer.held) return "ready · bed not cleared";
  return printer.state;
}

/** The colour class of the state: ok, busy, paused, held, offline, error. */
export function stateClass(printer) {
  if (isOffline(printer)) return "offline";
  if (printer.state === "paused") return "paused";
  if (printer.state === "printing") return "busy";
  if (printer.error) return "error";
  if (printer.held) return "held";
  return "ok";
}

/** Why ``action`` cannot be done on ``printer`` now; "" when it can. Actions: command (a
 * typed command, a jog, a temperature), pause, resume, cancel, release, queue, snapshot. */
export function whyNot(printer, action) {
  if (!printer) return "the printer is not known yet";
  const offline = isOffline(printer);
  const offlineWhy = `printer ${printer.name} is offline${printer.reason ? ` (${printer.reason})` : ""}`;
  switch (action) {
    case "command":
      if (offline) return offlineWhy;
      if (printer.phase) return `wait: the printer is ${printer.phase}`;
      if (printer.state === "printing") return "a job is streaming: pause it first";
      if (printer.state === "paused" && printer.protocol === "hyrel") {
        // Hyrel's controller holds the paused job's lines: a command would wait behind them.
        return "the controller holds the paused job (Hyrel's link): commands go after resume or cancel";
      }
      return "";
    case "pause":
      if (printer.state === "paused") return "the job is paused already";
      if (printer.state !== "printing") return "no job is printing";
      if (printer.phase) return `wait: the printer is ${printer.phase}`;
      return "";
    case "resume":
      if (printer.state !== "paused") return printer.state === "printing" ? "the job is printing" : "no job is paused";
      if (printer.phase) return `wait: the printer is ${printer.phase}`;
      return "";
    case "cancel":
      if (printer.state !== "printing" && printer.state !== "paused") return "no job is running";
      return "";
    case "release":
      if (!printer.held) return "the queue is not held";
      return "";
    case "snapshot":
      if (!printer.camera) return `printer ${printer.name} has no camera (camera = ... in its settings)`;
      return "";
    default:
      return "";
  }
}

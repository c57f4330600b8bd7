// The server's uploaded files: upload (a drop zone and a file input, each upload with its
// progress), folders (a breadcrumb, new, delete), a search across folders, sorting, and
// each file's analysis (the print time from its moves beside the slicer's estimate,
// filament, layers, size, thumbnail). "Print" asks the lint first: warnings are shown
// before the job is queued, errors refuse it.

import { h, clock, duration } from "../api.js";

const SORTS = {
  date: { label: "date", key: (f) => f.date, down: true },
  name: { label: "name", key: (f) => f.name.toLowerCase(), down: false },
  size: { label: "size", key: (f) => f.size, down: true },
  time: { label: "estimated time", key: (f) => estimate(f) ?? -1, down: true },
};

/** A path below the uploads, as a URL path ("parts/a b.gcode" -> "parts/a%20b.gcode"). */
export const urlPath = (path) => path.split("/").map(encodeURIComponent).join("/");
const folderOf = (path) => (path.includes("/") ? path.slice(0, path.lastIndexOf("/")) : "");
/** The file's print time: ours (from its moves), else the slicer's; null when neither. */
const estimate = (file) => {
  const a = file.analysis;
  return a ? a.estimatedPrintTime ?? a.slicerEstimatedPrintTime ?? null : null;
};
/** The row's time: ours, with the slicer's beside it when they differ by over a minute
 * ("52 min 53 s (slicer: 54 min 10 s)"); the slicer's alone for a file without moves. */
function shownTime(a) {
  const ours = a.estimatedPrintTime, slicer = a.slicerEstimatedPrintTime;
  if (ours == null) return slicer == null ? null : `${duration(slicer)} (slicer)`;
  if (slicer == null || Math.abs(ours - slicer) <= 60) return duration(ours);
  return `${duration(ours)} (slicer: ${duration(slicer)})`;
}
/** The details' sentence, worded as hyrel-send --check says it. */
function timeSentence(a) {
  const slicer = a.slicerEstimatedPrintTime != null ? `; the slicer's: ${duration(a.slicerEstimatedPrintTime)}` : "";
  if (a.estimatedPrintTime == null) return `no moves: no print time${slicer}`;
  return `${duration(a.estimatedPrintTime)}, limits from ${a.estimatedPrintTimeLimitsFrom}${slicer}`;
}
/** A finding without its repeated severity: "warning: a.gcode:3: warning: G10 ..." ->
 * "a.gcode:3: warning: G10 ...". */
const finding = (text) => text.replace(/^(error|warning): (?=.*: (error|warning): )/, "");

/** Filament length (mm) as metres ("1.24 m"), or mm when it is under a centimetre. */
export function metres(mm) {
  return mm < 10 ? `${mm.toFixed(1)} mm` : `${(mm / 1000).toFixed(2)} m`;
}

export function bytes(size) {
  if (size < 1024) return `${size} B`;
  if (size < 1024 * 1024) return `${(size / 1024).toFixed(1)} kB`;
  return `${(size / 1024 / 1024).toFixed(1)} MB`;
}

export function mount(body, ctx) {
  const api = ctx.api;
  let files = [];
  let folders = [];
  let current = ""; // the folder shown ("" = the top)
  let sort = "date";
  let reversed = false;
  const open = new Set(); // the paths whose details are shown
  const notes = new Map(); // path -> element shown under its row (a check, a refusal)
  let retry = null;
  let tries = 0; // listings while some file's analysis was still missing
  const pending = (file) => !file.analysis && /\.(gcode|gco|g)$/i.test(file.name);

  const input = h("input", { type: "file", id: "files-input", class: "visually-hidden", multiple: true, accept: ".gcode,.gco,.g", onchange: () => { uploadAll(input.files); input.value = ""; } });
  const pick = h("label", { class: "button primary", for: "files-input" }, "Upload…");
  const folderName = h("input", { type: "text", id: "files-folder-name", placeholder: "folder name", "aria-label": "new folder name" });
  const folderForm = h("form", { class: "row files-new-folder", hidden: true, onsubmit: makeFolder },
    folderName, h("button", { type: "submit", class: "primary" }, "Create"),
    h("button", { type: "button", onclick: () => (folderForm.hidden = true) }, "Cancel"));
  const newFolder = h("button", { type: "button", id: "files-new-folder", onclick: () => { folderForm.hidden = false; folderName.focus(); } }, "New folder");
  const uploads = h("div", { class: "files-uploads" });
  const crumbs = h("nav", { class: "files-crumbs", "aria-label": "folder" });
  const search = h("input", { type: "search", id: "files-search", placeholder: "search all folders", "aria-label": "search files by name", oninput: render });
  const sortSelect = h("select", { id: "files-sort", "aria-label": "sort by", onchange: () => { sort = sortSelect.value; reversed = false; render(); } },
    Object.entries(SORTS).map(([value, s]) => h("option", { value }, s.label)));
  const direction = h("button", { type: "button", id: "files-direction", title: "reverse the order", onclick: () => { reversed = !reversed; render(); } });
  const list = h("div", { class: "files-list" });
  const drop = h("div", { class: "files-drop" },
    h("span", { class: "muted" }, "Drop G-code files here, or"), pick, input, newFolder);
  body.append(drop, folderForm, uploads,
    h("div", { class: "files-tools" }, crumbs, h("div", { class: "row" }, search, h("label", { class: "muted" }, "sort ", sortSelect), direction)),
    list);

  // The whole panel takes dropped files.
  const isFiles = (event) => event.dataTransfer && Array.from(event.dataTransfer.types).includes("Files");
  body.addEventListener("dragover", (event) => {
    if (!isFiles(event)) return;
    event.preventDefault();
    event.dataTransfer.dropEffect = "copy";
    body.classList.add("files-dragging");
  });
  body.addEventListener("dragleave", (event) => {
    if (!body.contains(event.relatedTarget)) body.classList.remove("files-dragging");
  });
  body.addEventListener("drop", (event) => {
    if (!isFiles(event)) return;
    event.preventDefault();
    body.classList.remove("files-dragging");
    uploadAll(event.dataTransfer.files);
  });

  let loads = 0;
  async function load() {
    const mine = ++loads;
    try {
      const found = await Promise.all([api.get("/v1/files"), api.get("/v1/folders")]);
      if (mine !== loads) return; // a later listing was asked for: it shows
      [files, folders] = found;
    } catch (error) {
      if (mine !== loads) return;
      list.replaceChildren(h("p", { class: "error" }, `The files could not be listed: ${error.message}`));
      return;
    }
    if (current && !folders.includes(current)) current = "";
    render();
    // Files analysed in the background have no analysis yet: ask again soon (for a minute).
    clearTimeout(retry);
    if (!files.some(pending)) tries = 0;
    else if (++tries < 30) retry = setTimeout(load, 2000);
  }

  function render() {
    const query = search.value.trim().toLowerCase();
    direction.textContent = (SORTS[sort].down !== reversed) ? "↓" : "↑";
    // The breadcrumb: each folder above opens it.
    const parts = current ? current.split("/") : [];
    crumbs.replaceChildren(
      crumb("All files", ""),
      ...parts.flatMap((name, i) => [h("span", { class: "muted" }, " › "), crumb(name, parts.slice(0, i + 1).join("/"), i === parts.length - 1)]),
    );
    if (query) crumbs.append(h("span", { class: "muted" }, ` · searching all folders for “${search.value.trim()}”`));
    const shown = query ? files.filter((f) => f.name.toLowerCase().includes(query)) : files.filter((f) => folderOf(f.path) === current);
    const { key, down } = SORTS[sort];
    const sign = down !== reversed ? -1 : 1;
    shown.sort((a, b) => (key(a) < key(b) ? -sign : key(a) > key(b) ? sign : a.name.localeCompare(b.name)));
    const below = query ? [] : folders.filter((f) => folderOf(f) === current).sort();
    const rows = [...below.map(folderRow), ...shown.map(fileRow)];
    if (!rows.length) rows.push(h("p", { class: "empty" }, query ? "No file's name matches." : current ? "This folder is empty: drop files here." : "No files yet: drop G-code files here or upload them."));
    list.replaceChildren(...rows);
  }

  function crumb(name, path, here = false) {
    if (here || (path === current && !search.value.trim())) return h("strong", {}, name);
    return h("a", { href: "#", dataset: { folder: path }, onclick: (event) => { event.preventDefault(); go(path); } }, name);
  }

  function go(folder) {
    current = folder;
    search.value = "";
    render();
  }

  function folderRow(path) {
    const name = path.slice(path.lastIndexOf("/") + 1);
    const inside = files.filter((f) => f.path.startsWith(`${path}/`)).length;
    const remove = h("button", { type: "button", class: "danger", onclick: () => deleteFolder(path, inside) }, "Delete");
    return h("div", { class: "file-row folder", dataset: { folder: path } },
      h("div", { class: "file-thumb folder-icon", "aria-hidden": "true" }),
      h("div", { class: "file-main" },
        h("a", { href: "#", class: "file-name", onclick: (event) => { event.preventDefault(); go(path); } }, name),
        h("div", { class: "file-meta muted" }, inside ? `${inside} file${inside === 1 ? "" : "s"}` : "empty")),
      h("div", { class: "file-actions" }, remove));
  }

  function fileRow(file) {
    const analysis = file.analysis;
    const meta = [bytes(file.size), clock(file.date)];
    if (!analysis) meta.push(!pending(file) ? "no analysis (not G-code)" : tries < 30 ? "analysing…" : "not analysed (yet)");
    else {
      const time = shownTime(analysis);
      if (time != null) meta.push(time);
      if (analysis.layers) meta.push(`${analysis.layers} layers`);
    }
    const thumb = file.thumbnail
      ? h("img", { class: "file-thumb", alt: "", loading: "lazy", src: api.keyed(`${file.thumbnail}?v=${file.date}`) })
      : h("div", { class: "file-thumb none", "aria-hidden": "true" }, "G");
    const details = h("button", { type: "button", class: "details", "aria-expanded": String(open.has(file.path)), onclick: () => { open.has(file.path) ? open.delete(file.path) : open.add(file.path); render(); } }, open.has(file.path) ? "Hide details" : "Details");
    const print = h("button", { type: "button", class: "primary print", onclick: () => printFile(file, print) }, "Print");
    const remove = h("button", { type: "button", class: "danger delete", onclick: () => deleteFile(file) }, "Delete");
    const folder = search.value.trim() && folderOf(file.path) ? h("span", { class: "muted" }, `${folderOf(file.path)}/`) : null;
    return h("div", { class: "file-row", dataset: { path: file.path } },
      thumb,
      h("div", { class: "file-main" },
        h("div", { class: "file-name", title: file.path }, folder, file.name),
        h("div", { class: "file-meta muted" }, meta.join(" · "))),
      h("div", { class: "file-actions" }, details, print, remove),
      open.has(file.path) ? detailsOf(file) : null,
      notes.get(file.path) || null);
  }

  function detailsOf(file) {
    const a = file.analysis;
    if (!a) return h("div", { class: "file-details muted" }, "The file is being analysed: its details come with the next listing.");
    const facts = [];
    const fact = (term, ...value) => facts.push(h("dt", {}, term), h("dd", {}, ...value));
    fact("slicer", a.slicer || "not said");
    fact("estimated time", timeSentence(a));
    const tools = Object.entries(a.filament || {});
    fact("filament", tools.length ? tools.map(([tool, used]) => h("div", {}, `${tool}: ${metres(used.length)}, ${used.volume.toFixed(2)} cm³`)) : "none extruded");
    fact("layers", String(a.layers || 0));
    const d = a.dimensions;
    if (d && !a._empty) fact("dimensions", `${d.width.toFixed(1)} × ${d.depth.toFixed(1)} × ${d.height.toFixed(1)} mm (W × D × H)`);
    fact("file", `${file.path}, ${bytes(file.size)}, ${clock(file.date)}`);
    return h("div", { class: "file-details" },
      file.thumbnail ? h("img", { class: "file-preview", alt: `preview of ${file.name}`, src: api.keyed(`${file.thumbnail}?v=${file.date}`) }) : null,
      h("dl", {}, ...facts));
  }

  function note(path, element) {
    if (element) notes.set(path, element);
    else notes.delete(path);
    render();
  }

  const findingList = (findings) => h("ul", { class: "findings" }, findings.map((f) => h("li", { class: f.startsWith("error") ? "error" : "" }, finding(f))));

  async function printFile(file, button) {
    button.disabled = true;
    try {
      const check = await api.get(`/v1/files/${urlPath(file.path)}/check?printer=${encodeURIComponent(ctx.name)}`);
      if (check.errors) {
        note(file.path, h("div", { class: "file-check refused" },
          h("p", { class: "error" }, `Not printed: the check found ${check.errors} error${check.errors === 1 ? "" : "s"} for printer ${ctx.name}. Fix the file (or the printer's heads) and upload it again.`),
          findingList(check.findings),
          h("button", { type: "button", onclick: () => note(file.path, null) }, "Close")));
      } else if (check.findings.length) {
        note(file.path, h("div", { class: "file-check" },
          h("p", {}, `The check for printer ${ctx.name} warns:`),
          findingList(check.findings),
          h("div", { class: "row" },
            h("button", { type: "button", class: "primary anyway", onclick: () => queue(file) }, "Print anyway"),
            h("button", { type: "button", onclick: () => note(file.path, null) }, "Cancel"))));
      } else await queue(file);
    } catch (error) {
      note(file.path, refusal(file.path, error));
    } finally {
      button.disabled = false;
    }
  }

  async function queue(file) {
    try {
      const job = await api.post(`${ctx.path}/queue`, { file: file.path });
      const done = h("div", { class: "file-check queued" }, `Queued as job ${job.id} on ${ctx.name}.`);
      note(file.path, done);
      setTimeout(() => notes.get(file.path) === done && note(file.path, null), 4000);
    } catch (error) {
      note(file.path, refusal(file.path, error));
    }
  }

  function refusal(path, error) {
    const found = (error.body && error.body.detail && error.body.detail.findings) || [];
    return h("div", { class: "file-check refused" },
      h("p", { class: "error" }, error.message), found.length ? findingList(found) : null,
      h("button", { type: "button", onclick: () => note(path, null) }, "Close"));
  }

  async function deleteFile(file) {
    if (!confirm(`Delete ${file.path} from the server?`)) return;
    try {
      await api.del(`/v1/files/${urlPath(file.path)}`);
      notes.delete(file.path);
      open.delete(file.path);
      await load();
    } catch (error) {
      note(file.path, refusal(file.path, error)); // 409: the job using it
    }
  }

  async function deleteFolder(path, inside) {
    const what = inside ? ` and the ${inside} file${inside === 1 ? "" : "s"} in it` : "";
    if (!confirm(`Delete the folder ${path}${what}?`)) return;
    try {
      await api.del(`/v1/folders/${urlPath(path)}`);
      ctx.say("");
      await load();
    } catch (error) {
      ctx.say(`The folder ${path} was not deleted: ${error.message}`);
    }
  }

  async function makeFolder(event) {
    event.preventDefault();
    const name = folderName.value.trim().replace(/^\/+|\/+$/g, "");
    if (!name) return;
    try {
      const made = await api.post("/v1/folders", { path: current ? `${current}/${name}` : name });
      folderName.value = "";
      folderForm.hidden = true;
      ctx.say("");
      current = made.path;
      await load();
    } catch (error) {
      ctx.say(`The folder was not made: ${error.message}`);
    }
  }

  function uploadAll(chosen) {
    for (const file of Array.from(chosen)) uploadOne(file);
  }

  async function uploadOne(file) {
    const folder = current;
    const bar = h("div", {});
    const status = h("span", { class: "muted" }, "0 %");
    const close = h("button", { type: "button", class: "close", "aria-label": "dismiss", onclick: () => row.remove() }, "×");
    close.hidden = true;
    const row = h("div", { class: "upload", dataset: { name: file.name } },
      h("div", { class: "upload-head" }, h("strong", {}, file.name), folder ? h("span", { class: "muted" }, ` → ${folder}/`) : null, status, close),
      h("div", { class: "bar" }, bar));
    uploads.append(row);
    const form = new FormData();
    form.append("file", file);
    form.append("folder", folder);
    try {
      const entry = await api.upload(`/v1/files?printer=${encodeURIComponent(ctx.name)}`, form, (fraction) => {
        bar.style.width = `${Math.round(fraction * 100)}%`;
        status.textContent = fraction < 1 ? `${Math.round(fraction * 100)} %` : "checking…";
      });
      bar.style.width = "100%";
      row.classList.add("done");
      status.textContent = `uploaded as ${entry.path}`;
      if (entry.note) row.append(h("p", { class: "muted" }, entry.note));
      if (entry.findings && entry.findings.length) {
        row.append(findingList(entry.findings));
        close.hidden = false;
      } else setTimeout(() => row.remove(), 4000);
      await load();
    } catch (error) {
      row.classList.add("failed");
      status.textContent = "";
      close.hidden = false;
      const found = (error.body && error.body.detail && error.body.detail.findings) || [];
      row.append(h("p", { class: "error" }, error.message), found.length ? findingList(found) : "");
    }
  }

  ctx.stream.on("file", () => load());
  ctx.stream.onReconnect(load);
  load();
}

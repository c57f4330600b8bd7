// The printer's camera: the latest snapshot (and "Snapshot now"), the layer snapshots of
// the current or last job as a strip (one clicked is shown large), and the time-lapse
// videos made of them by ffmpeg on the server.

import { h, allow, clock } from "../api.js";

const NAME = /^(\d{4})(\d{2})(\d{2})-(\d{2})(\d{2})(\d{2})-\d+(?:-job(\d+)-layer(\d+))?\./;

/** What a snapshot's file name says: its time (the server's clock, written as the page
 * writes every time: "10:15:00"), its job and layer if any. */
function described(file) {
  const found = NAME.exec(file) || [];
  const [year, month, day, hour, minute, second] = found.slice(1, 7).map(Number);
  return {
    time: found[1] ? clock(new Date(year, month - 1, day, hour, minute, second) / 1000, { seconds: true }) : "",
    job: found[7] ? Number(found[7]) : null,
    layer: found[8] ? Number(found[8]) : null,
  };
}

export async function mount(body, ctx) {
  const api = ctx.api;
  let snapshots = []; // {file, url}, newest first
  let latest = null; // {file, url}
  let chosen = null; // a layer snapshot clicked, shown instead of the latest
  let lapses = { missing: null, videos: [] };
  let making = false;
  let taking = false;
  let built = null; // whether the camera's UI (true) or the no-camera sentence (false) is up

  const image = h("img", { class: "camera-image", alt: "the camera's latest snapshot" });
  const none = h("p", { class: "empty camera-none" }, "No snapshot yet.");
  const caption = h("span", { class: "camera-caption muted" });
  const backToLatest = h("button", { type: "button", class: "camera-latest", hidden: true, onclick: () => { chosen = null; render(); } }, "Show the latest");
  const snap = h("button", { type: "button", id: "camera-snapshot", onclick: snapshotNow }, "Snapshot now");
  const stripTitle = h("h3", {}, "Layer snapshots");
  const strip = h("div", { class: "camera-strip" });
  const make = h("button", { type: "button", id: "camera-timelapse", onclick: makeTimelapse }, "Make time-lapse");
  const missing = h("p", { class: "camera-missing muted", hidden: true });
  const videos = h("div", { class: "camera-videos" });
  const camera = h("div", { class: "camera" },
    h("figure", { class: "camera-figure" }, image, none),
    h("div", { class: "row" }, snap, caption, backToLatest),
    stripTitle, strip,
    h("h3", {}, "Time-lapse"), missing, h("div", { class: "row" }, make), videos);
  const noCamera = h("p", { class: "empty camera-absent" }, "No camera: add camera = ... to this printer's settings.");

  /** The job whose layer snapshots are shown: the running one, the last one, else the
   * newest that has some. */
  function jobId() {
    const printer = ctx.printer || {};
    if (printer.job) return printer.job.id;
    if (ctx.lastJob) return ctx.lastJob.id;
    const found = snapshots.find((s) => described(s.file).job != null);
    return found ? described(found.file).job : null;
  }

  function layerShots(job) {
    return snapshots.filter((s) => s.file.includes(`-job${job}-layer`)).reverse(); // oldest first
  }

  function render() {
    const printer = ctx.printer || {};
    if (printer.camera == null) return; // not known yet
    if (!printer.camera) {
      if (built !== false) body.replaceChildren(noCamera);
      built = false;
      return;
    }
    if (built !== true) body.replaceChildren(camera);
    built = true;

    const shown = chosen || latest;
    none.hidden = Boolean(shown);
    image.hidden = !shown;
    if (shown && image.dataset.file !== shown.file) {
      image.src = api.keyed(shown.url);
      image.dataset.file = shown.file;
    }
    const said = shown ? described(shown.file) : null;
    caption.textContent = !shown ? "" : chosen ? `layer ${said.layer} of job ${said.job} · ${said.time}` : `latest · ${said.time}`;
    backToLatest.hidden = !chosen;
    if (taking) allow(snap, "taking a snapshot…");
    else ctx.allow(snap, "snapshot");

    const job = jobId();
    const shots = job != null ? layerShots(job) : [];
    stripTitle.textContent = job != null ? `Layer snapshots of job ${job}` : "Layer snapshots";
    if (strip.dataset.shown !== shots.map((s) => s.file).join()) {
      strip.dataset.shown = shots.map((s) => s.file).join();
      strip.replaceChildren(...shots.map((shot) => {
        const layer = described(shot.file).layer;
        return h("button", { type: "button", class: "camera-thumb", title: `layer ${layer}`, dataset: { file: shot.file }, onclick: () => { chosen = shot; render(); } },
          h("img", { src: api.keyed(shot.url), alt: `layer ${layer}`, loading: "lazy" }), h("span", {}, layer));
      }));
      if (!shots.length) strip.append(h("span", { class: "empty" }, "None yet: a job takes one at each layer (M790)."));
      strip.scrollLeft = strip.scrollWidth; // the newest in sight
    }
    for (const thumb of strip.querySelectorAll(".camera-thumb")) thumb.classList.toggle("on", Boolean(chosen) && thumb.dataset.file === chosen.file);

    missing.hidden = !lapses.missing;
    missing.textContent = lapses.missing || "";
    make.textContent = making ? "Making the time-lapse…" : job != null ? `Make time-lapse of job ${job}` : "Make time-lapse";
    let why = "";
    if (lapses.missing) why = lapses.missing;
    else if (making) why = "a time-lapse is being made";
    else if (job == null) why = "no job has layer snapshots yet";
    else if (shots.length < 2) why = `job ${job} has ${shots.length} layer snapshot${shots.length === 1 ? "" : "s"}: a video needs two`;
    allow(make, why);

    const [newest, ...older] = lapses.videos;
    if (videos.dataset.shown !== lapses.videos.map((v) => v.file).join()) {
      videos.dataset.shown = lapses.videos.map((v) => v.file).join();
      videos.replaceChildren();
      if (newest) {
        videos.append(h("video", { class: "camera-video", controls: true, preload: "metadata", src: api.keyed(newest.url) }),
          h("p", { class: "muted" }, newest.file));
      }
      if (older.length) videos.append(h("ul", { class: "camera-older" }, older.map((v) => h("li", {}, h("a", { href: api.keyed(v.url), target: "_blank" }, v.file)))));
    }
  }

  async function snapshotNow() {
    taking = true;
    render();
    try {
      latest = await api.post(`${ctx.path}/snapshots`);
      chosen = null;
    } catch (error) {
      ctx.say(error.message);
    }
    taking = false;
    render();
  }

  async function makeTimelapse() {
    const job = jobId();
    making = true;
    render();
    try {
      await api.post(`${ctx.path}/timelapses`, { job });
      lapses = await api.get(`${ctx.path}/timelapses`);
    } catch (error) {
      ctx.say(error.message);
    }
    making = false;
    render();
  }

  async function load() {
    if (!(ctx.printer && ctx.printer.camera)) return render();
    try {
      const [listed, made] = await Promise.all([api.get(`${ctx.path}/snapshots`), api.get(`${ctx.path}/timelapses`)]);
      // With those the stream told meanwhile; the names start with the time taken.
      const known = new Set(listed.map((s) => s.file));
      snapshots = [...listed, ...snapshots.filter((s) => !known.has(s.file))];
      snapshots.sort((a, b) => (a.file < b.file ? 1 : a.file > b.file ? -1 : 0));
      latest = snapshots[0] || null;
      lapses = made;
    } catch (error) {
      if (error.status !== 403) ctx.say(error.message);
    }
    render();
  }

  ctx.stream.on("snapshot", (event) => {
    if (event.printer && event.printer !== ctx.name) return;
    const shot = { file: event.file, url: event.url };
    if (!snapshots.some((s) => s.file === shot.file)) snapshots.unshift(shot);
    latest = shot;
    render();
  });
  let hadCamera = null;
  ctx.onChange((printer) => {
    if (printer.camera !== hadCamera) {
      hadCamera = printer.camera;
      if (printer.camera) load();
    }
    render();
  });
  ctx.stream.onReconnect(load);
  if (hadCamera === null) render();
}

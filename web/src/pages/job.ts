// Job page: the image refining live over Server-Sent Events, the error-against-time plot,
// settings, tile stop records, the event log, cancel, job control (pause, resume, retry,
// continue, priority and name) and downloads. An animation's page adds its frame strip
// (framestrip.ts): the image, its layers, the tile grid, the stop records and the downloads
// then show the chosen frame, which the URL carries (#/jobs/ID?frame=N).

import {
  ApiError,
  FINISHED,
  type Frame,
  type Job,
  type JobDetail,
  type JobEvent,
  cancelJob,
  continueJob,
  convergence,
  frameImageUrl,
  getJob,
  imageUrl,
  jobEvents,
  listFrames,
  MOVIE_PATH,
  pauseJob,
  resumeJob,
  retryJob,
  serverHas,
  updateJob,
  watchUrl,
} from "../api";
import { type ErrorPoint, convergencePlot } from "../chart";
import { h, replace, setText } from "../dom";
import { dateTime, duration, label, percent, si, spp } from "../format";
import { frameIndex, frameTiles, tileLabel } from "../frames";
import { noiseTargetShortfall } from "../outputs";
import { jobHash } from "../router";
import { taskLog } from "../tasklog";
import { Throttled } from "../throttle";
import { TileProgress, card, errorVsTarget, setConnection, stat, stateBadge, updateBadge } from "../ui";
import { FrameStrip, MoviePanel } from "./framestrip";
import { Viewer } from "./viewer";

const CONVERGENCE_PATH = "/api/v1/jobs/{job_id}/convergence";
const MAX_ROWS = 500;

/** A finished frame's image is final (until the job is continued, which raises its spp). */
const finalKey = (f: Frame) => (f.state === "done" ? `done-${f.mean_spp}` : null);

/** tileName: how a tile_stopped event's tile is named (of an animation: frame and its own tile). */
function eventSummary(e: JobEvent, tileName: (d: Record<string, unknown>) => string): string {
  const d = e.data ?? {};
  if (e.kind === "tile_stopped") {
    return `${tileName(d)} at ${d.spp} spp, error ${percent(Number(d.error))} (${d.reason})`;
  }
  if (e.kind === "frame_finished") {
    return `frame ${d.frame} at ${spp(Number(d.spp))} spp, error ${percent(d.error === null ? null : Number(d.error))}`;
  }
  if (e.kind === "convergence" && Array.isArray(d.points)) {
    return `${d.points.length} error samples recorded for the plot`;
  }
  return Object.entries(d)
    .filter(([, v]) => v !== "" && v !== null && v !== undefined)
    .map(([k, v]) => `${k}: ${typeof v === "object" ? JSON.stringify(v) : String(v)}`)
    .join(", ");
}

/** frame: the frame of an animation the URL asks for (null: its first). */
export function mountJob(root: HTMLElement, jobId: string, frame: number | null = null): () => void {
  let disposed = false;
  let source: EventSource | null = null;
  const cleanups: (() => void)[] = [];
  document.title = `Job ${jobId} · renderfarm`;
  replace(root, h("p", { class: "muted" }, "Loading job…"));

  const start = async () => {
    let detail: JobDetail;
    try {
      detail = await getJob(jobId);
    } catch (e) {
      const text = e instanceof ApiError && e.status === 404 ? `There is no job ${jobId}.` : `Cannot load job ${jobId}: ${(e as Error).message}`;
      replace(root, h("div", { class: "card empty" }, h("p", {}, text), h("a", { href: "#/jobs" }, "Back to the jobs")));
      return;
    }
    // An animation's frames, for the strip (a still's page is the same as ever).
    let frames: Frame[] | null = null;
    if ((detail.progress.frames_total ?? 1) > 1) {
      try {
        frames = await listFrames(jobId);
      } catch (e) {
        setConnection(false, `Cannot load the frames of job ${jobId}: ${(e as Error).message}`);
      }
    }
    if (disposed) return;
    build(detail, frames && frames.length > 1 ? frames : null);
  };

  const build = (initial: JobDetail, initialFrames: Frame[] | null) => {
    let job: Job = initial;
    const st = initial.settings;
    document.title = `${initial.name || initial.id} · renderfarm`;

    // Header and actions.
    const badge = stateBadge(job.state);
    const cancelButton = h("button", { type: "button", class: "button danger", "data-action": "cancel" }, "Cancel job");
    const confirmBox = h(
      "div",
      { class: "confirm", hidden: true, role: "group", "aria-label": "Confirm cancel" },
      h("span", {}, "Stop rendering this job?"),
      h("button", { type: "button", class: "button danger", "data-action": "confirm-cancel" }, "Yes, cancel"),
      h("button", { type: "button", class: "button secondary", "data-action": "keep" }, "Keep rendering"),
    );
    // Job control: each button shows in the states where the server allows it.
    const controlButton = (action: string, text: string) =>
      h("button", { type: "button", class: "button secondary", "data-action": action }, text);
    const pauseButton = controlButton("pause", "Pause");
    const resumeButton = controlButton("resume", "Resume");
    const retryButton = controlButton("retry", "Retry");
    const controlMessage = h("p", { class: "control-message small", role: "status", "data-field": "" });
    const numberInput = (id: string, step: string) => h("input", { id, type: "number", step, min: "0", class: "input" }) as HTMLInputElement;
    const maxSppInput = numberInput("continue-max-spp", "1");
    const thresholdInput = numberInput("continue-noise-threshold", "any");
    const continueForm = h(
      "form",
      { class: "control-form", "data-form": "continue", "aria-label": "Continue with more samples" },
      h("label", { for: "continue-max-spp" }, "Max spp"),
      maxSppInput,
      h("label", { for: "continue-noise-threshold" }, "Noise threshold"),
      thresholdInput,
      h("button", { type: "submit", class: "button", "data-action": "continue" }, "Continue"),
    ) as HTMLFormElement;
    const priorityInput = h("input", { id: "edit-priority", type: "number", step: "1", min: "-1000", max: "1000", class: "input" }) as HTMLInputElement;
    const nameInput = h("input", { id: "edit-name", type: "text", maxlength: "200", class: "input" }) as HTMLInputElement;
    const editForm = h(
      "form",
      { class: "control-form", "data-form": "edit", "aria-label": "Priority and name" },
      h("label", { for: "edit-priority" }, "Priority"),
      priorityInput,
      h("label", { for: "edit-name" }, "Name"),
      nameInput,
      h("button", { type: "submit", class: "button secondary", "data-action": "save" }, "Save"),
    ) as HTMLFormElement;
    const title = h("h1", {}, initial.name || "(unnamed)");
    // The forms show the job's values, except in a field the user has typed into since: a
    // control's answer (a Resume's, say) arriving meanwhile must not undo what they typed.
    const formInputs = [maxSppInput, thresholdInput, priorityInput, nameInput];
    for (const input of formInputs) input.addEventListener("input", () => (input.dataset.edited = "1"));
    const fillForms = (j: Job) => {
      const values: [HTMLInputElement, string][] = [
        [maxSppInput, String(j.settings.max_spp * 2)],
        [thresholdInput, String(j.settings.noise_threshold)],
        [priorityInput, String(j.settings.priority)],
        [nameInput, j.name],
      ];
      for (const [input, value] of values) if (!input.dataset.edited) input.value = value;
    };
    /** A form was sent: its fields show the job's values again once the answer comes. */
    const sent = (...inputs: HTMLInputElement[]) => {
      for (const input of inputs) delete input.dataset.edited;
    };

    const safeName = (job.name || job.id).replace(/[^\w.-]+/g, "_");
    const pngLink = h("a", { class: "button secondary", href: imageUrl(jobId, "png"), download: `${safeName}.png` }, "Download PNG");
    const exrLink = h("a", { class: "button secondary", href: imageUrl(jobId, "exr"), download: `${safeName}.exr` }, "Download EXR");
    const denoisedLink =
      st.denoise === true
        ? h("a", { class: "button secondary", href: imageUrl(jobId, "png", "denoised"), download: `${safeName}-denoised.png` }, "Download denoised PNG")
        : null;
    /** Of an animation the downloads are the frame shown. */
    const frameDownloads = (n: number) => {
      const links: [HTMLAnchorElement | null, "png" | "exr", string, string][] = [
        [pngLink, "png", "rgb", "PNG"],
        [exrLink, "exr", "rgb", "EXR"],
        [denoisedLink, "png", "denoised", "denoised PNG"],
      ];
      for (const [a, fmt, layer, what] of links) {
        if (!a) continue;
        a.href = frameImageUrl(jobId, n, fmt, layer);
        a.download = `${safeName}-frame${n}${layer === "denoised" ? "-denoised" : ""}.${fmt}`;
        a.dataset.frame = String(n);
        setText(a, `Download ${what} (frame ${n})`);
      }
    };
    const actions = h(
      "div",
      { class: "actions" },
      pngLink,
      exrLink,
      denoisedLink,
      pauseButton,
      resumeButton,
      retryButton,
      cancelButton,
      confirmBox,
    );
    const failure = h("div", { class: "alert", role: "alert", hidden: true });
    // A completed job whose tiles stopped at max_spp or the time limit, not on noise.
    const shortfall = h("div", { class: "alert warn", role: "status", hidden: true, "data-field": "shortfall" });

    // Live figures.
    const bar = new TileProgress("Tiles converged");
    const meanSpp = h("span");
    const error = h("span", { class: "error-vs-target" });
    const elapsed = h("span");
    const eta = h("span");
    const merged = h("span");
    const framesDoneText = h("span");
    const stats = h(
      "div",
      { class: "stats" },
      initialFrames ? stat("Frames done", framesDoneText, "frames") : null,
      stat("Tiles converged", bar.el, "progress"),
      stat("Mean spp", meanSpp, "spp"),
      stat("Error / target", error, "error"),
      stat("Elapsed", elapsed, "elapsed"),
      stat("ETA", eta, "eta"),
      stat("Samples merged", merged, "samples"),
    );

    const viewer = new Viewer(jobId, st.width, st.height, st.tile_size, {
      denoise: st.denoise === true,
      aovs: typeof st.aovs === "string" ? st.aovs : "",
      light_groups: typeof st.light_groups === "string" ? st.light_groups : "",
    });
    cleanups.push(() => viewer.stop());

    // An animation: the strip of its frames, the frame shown, the preview movie.
    const cols = Math.ceil(st.width / st.tile_size);
    const perFrame = cols * Math.ceil(st.height / st.tile_size);
    let lastDetail: JobDetail = initial;
    let strip: FrameStrip | null = null;
    let movie: MoviePanel | null = null;
    let movieServed = false;
    let frameSlots = new Map<number, number>(); // frame number -> its place in the frame list
    // The address follows the frame a moment after the last change: dragging the slider over
    // many frames would otherwise replace the history entry faster than browsers allow.
    let addressTimer: number | undefined;
    const frameToAddress = (n: number) => {
      window.clearTimeout(addressTimer);
      addressTimer = window.setTimeout(() => {
        if (!disposed) history.replaceState(history.state, "", jobHash(jobId, n));
      }, 150);
    };
    cleanups.push(() => window.clearTimeout(addressTimer));
    if (initialFrames) {
      const wanted = frameIndex(initialFrames, frame);
      if (frame !== null && initialFrames[wanted].frame !== frame) history.replaceState(history.state, "", jobHash(jobId));
      frameSlots = new Map(initialFrames.map((f, i) => [f.frame, i]));
      movie = new MoviePanel(jobId, safeName, Number(st.fps));
      cleanups.push(() => movie?.stop());
      strip = new FrameStrip(
        initialFrames,
        wanted,
        st.noise_threshold,
        (f) => {
          viewer.setFrame(f.frame, finalKey(f));
          frameDownloads(f.frame);
          renderStops(lastDetail);
          frameToAddress(f.frame);
        },
        movie.el,
      );
      viewer.setFrame(strip.current.frame, finalKey(strip.current));
      frameDownloads(strip.current.frame);
      void serverHas(MOVIE_PATH).then((has) => {
        movieServed = has && Boolean(st.frames); // a job of every variant has no movie
        if (has && !disposed) movie?.update(job.progress.frames_done ?? 0, job.progress.frames_total ?? 1);
      });
    }
    const framesLoader = new Throttled(async () => {
      if (!strip) return;
      try {
        const list = await listFrames(jobId);
        if (disposed || list.length < 1) return;
        frameSlots = new Map(list.map((f, i) => [f.frame, i]));
        strip.update(list);
        viewer.setFrame(strip.current.frame, finalKey(strip.current));
      } catch (e) {
        setConnection(false, (e as Error).message);
      }
    }, 1500);
    cleanups.push(() => framesLoader.stop());

    // Convergence plot: from the server's history when it has the endpoint, else from the stream.
    let points: ErrorPoint[] = [];
    let historyNote = "";
    const plotBox = h("div", { class: "plot-box" });
    const plotNote = h("p", { class: "muted small" });
    const drawPlot = () => {
      plotBox.replaceChildren(convergencePlot(points, st.noise_threshold > 0 ? st.noise_threshold : null));
      setText(plotNote, historyNote);
    };
    const addPoint = (t: number, e: number | null) => {
      if (e === null || !(t > 0)) return;
      const last = points[points.length - 1];
      if (last && t <= last.t) return;
      points.push({ t, error: e });
      if (points.length > 4000) points = points.filter((_, i) => i % 2 === 0 || i === points.length - 1);
    };
    const plotThrottle = new Throttled(async () => drawPlot(), 1000);
    cleanups.push(() => plotThrottle.stop());
    const loadHistory = async () => {
      if (!(await serverHas(CONVERGENCE_PATH))) {
        historyNote = FINISHED.has(job.state)
          ? "This server keeps no convergence history: the plot holds what this page saw while the job rendered."
          : "Plotted from the live stream since this page opened.";
        return;
      }
      try {
        const history = await convergence(jobId);
        const seen = points;
        points = [];
        for (const p of history) addPoint(p.t, p.error);
        for (const p of seen) addPoint(p.t, p.error);
        historyNote = "";
      } catch {
        historyNote = "Plotted from the live stream since this page opened.";
      }
    };

    // Settings.
    const settingsList = h(
      "dl",
      { class: "settings-list" },
      Object.entries(st).map(([k, v]) => [h("dt", { title: k }, label(k)), h("dd", { class: "mono", "data-setting": k }, v === "" ? "-" : String(v))]),
      h("dt", {}, "Scene"),
      h("dd", { class: "mono", title: initial.scene_sha256 }, initial.scene_sha256.slice(0, 16) + "…"),
      h("dt", {}, "Created"),
      h("dd", {}, dateTime(initial.created_unix_s)),
      h("dt", {}, "Finished"),
      h("dd", { "data-field": "finished" }, dateTime(initial.finished_unix_s)),
    );
    const finishedCell = settingsList.querySelector<HTMLElement>('[data-field="finished"]')!;

    // Stop records and events (of an animation: the frame shown).
    const stopsBody = h("tbody");
    const stopsNote = h("p", { class: "muted small" });
    const stopsTable = h(
      "div",
      { class: "table-scroll tall" },
      h(
        "table",
        { class: "table compact" },
        h("caption", { class: "visually-hidden" }, "Tile stop records"),
        h("thead", {}, h("tr", {}, ["Tile", "Row, col", "Batch", "spp", "Error", "Reason"].map((t) => h("th", { scope: "col" }, t)))),
        stopsBody,
      ),
    );
    const eventsList = h("ol", { class: "event-log", reversed: true });
    // What workers reported about the job's tasks (tasklog.ts); hidden while there is none.
    const taskLogBody = h("tbody", {});
    const taskLogCard = card(
      "Task log",
      h(
        "div",
        { class: "table-scroll" },
        h(
          "table",
          { class: "table compact task-log" },
          h("caption", { class: "visually-hidden" }, "Task log"),
          h("thead", {}, h("tr", {}, ["Time", "Worker", "Where", "Message"].map((t) => h("th", { scope: "col" }, t)))),
          taskLogBody,
        ),
      ),
    );
    taskLogCard.hidden = true;
    const renderStops = (d: JobDetail) => {
      lastDetail = d;
      // A still's tiles are numbered in its grid; an animation's across frames (frameTiles).
      const stops = (strip ? frameTiles(d.stops, strip.currentIndex, perFrame) : d.stops.map((r) => ({ ...r, local: r.tile }))).sort(
        (a, b) => a.tile - b.tile,
      );
      const of = strip ? `${perFrame} tiles of frame ${strip.current.frame}` : `${d.progress.tiles_total} tiles`;
      setText(stopsNote, `${stops.length} of ${of} stopped` + (stops.length > MAX_ROWS ? ` (first ${MAX_ROWS} shown)` : ""));
      stopsBody.replaceChildren(
        ...stops.slice(0, MAX_ROWS).map((r) =>
          h(
            "tr",
            {},
            h("td", { class: "num" }, r.local),
            h("td", { class: "num" }, `${Math.floor(r.local / cols)}, ${r.local % cols}`),
            h("td", { class: "num" }, r.batch),
            h("td", { class: "num" }, r.spp),
            h("td", { class: "num" }, percent(r.error)),
            h("td", {}, h("span", { class: `reason reason-${r.reason ?? "none"}` }, (r.reason ?? "").replace(/_/g, " "))),
          ),
        ),
      );
      viewer.setConverged(stops.map((r) => r.local));
      const short = noiseTargetShortfall(d, d.stops);
      shortfall.hidden = short === null;
      setText(shortfall, short ?? "");
    };
    const tileName = (d: Record<string, unknown>) => tileLabel(d, perFrame, frameSlots);
    let finishLogged = false;
    const renderEvents = (events: JobEvent[]) => {
      finishLogged = events.some((e) => e.kind === "job_finished");
      const t0 = initial.created_unix_s;
      const entries = taskLog(events, perFrame, frameSlots).slice(-MAX_ROWS).reverse();
      taskLogCard.hidden = entries.length === 0;
      taskLogBody.replaceChildren(
        ...entries.map((t) =>
          h(
            "tr",
            { class: `task-log-${t.level}` },
            h("td", { class: "mono muted", title: dateTime(t.at) }, `+${(t.at - t0).toFixed(1)} s`),
            h("td", { class: "mono" }, t.worker),
            h("td", {}, t.place),
            h("td", { class: `level-${t.level}` }, h("span", { class: "visually-hidden" }, `${t.level}: `), t.message),
          ),
        ),
      );
      const shown = events.slice(-MAX_ROWS).reverse();
      eventsList.replaceChildren(
        ...shown.map((e) =>
          h(
            "li",
            { class: `event event-${e.kind}` },
            h("time", { class: "mono muted", datetime: new Date(e.at * 1000).toISOString(), title: dateTime(e.at) }, `+${(e.at - t0).toFixed(1)} s`),
            h("span", { class: "event-kind" }, e.kind.replace(/_/g, " ")),
            h("span", { class: "muted" }, eventSummary(e, tileName)),
          ),
        ),
      );
    };

    const details = new Throttled(async () => {
      try {
        const [d, events] = await Promise.all([getJob(jobId), jobEvents(jobId)]);
        if (disposed) return;
        renderStops(d);
        renderEvents(events);
      } catch (e) {
        setConnection(false, (e as Error).message);
      }
    }, 1500);
    cleanups.push(() => details.stop());

    let lastTilesDone = -1;
    let lastMerged = -1;
    const show = (j: Job) => {
      const wasFinished = FINISHED.has(job.state);
      job = j;
      const p = j.progress;
      updateBadge(badge, j.state);
      bar.update(p, j.state);
      setText(meanSpp, `${spp(p.mean_spp)} / ${j.settings.max_spp}`);
      errorVsTarget(error, p.error, j.settings.noise_threshold);
      setText(elapsed, duration(p.elapsed_s));
      setText(eta, FINISHED.has(j.state) ? "-" : duration(p.eta_s));
      setText(merged, si(p.samples_merged));
      setText(finishedCell, dateTime(j.finished_unix_s));
      const finished = FINISHED.has(j.state);
      cancelButton.hidden = finished || !confirmBox.hidden;
      if (finished) confirmBox.hidden = true;
      pauseButton.hidden = !(j.state === "queued" || j.state === "running");
      resumeButton.hidden = j.state !== "paused";
      retryButton.hidden = j.state !== "failed";
      continueForm.hidden = j.state !== "completed";
      setText(title, j.name || "(unnamed)");
      // Priority, max_spp and noise_threshold change with an update or a continue.
      for (const [k, v] of Object.entries(j.settings)) {
        const cell = settingsList.querySelector<HTMLElement>(`[data-setting="${k}"]`);
        if (cell) setText(cell, v === "" ? "-" : String(v));
      }
      failure.hidden = !j.error;
      setText(failure, j.error ? `This job failed: ${j.error}` : "");
      addPoint(p.elapsed_s, p.error);
      plotThrottle.request();
      viewer.update(p.samples_merged);
      if (p.tiles_done !== lastTilesDone) {
        lastTilesDone = p.tiles_done;
        details.request();
      }
      if (strip) {
        setText(framesDoneText, `${p.frames_done ?? 0} / ${p.frames_total ?? 1}`);
        if (movieServed) movie?.update(p.frames_done ?? 0, p.frames_total ?? 1);
        if (p.samples_merged !== lastMerged) {
          lastMerged = p.samples_merged;
          framesLoader.request();
        }
      }
      if (finished && !wasFinished) void onFinished();
      if (!finished && wasFinished) openStream(); // retried or continued: live again
    };

    // Runs a job-control request; a refusal is shown with the field the server named.
    const control = async (button: HTMLButtonElement, act: () => Promise<Job>, done: string) => {
      button.disabled = true;
      try {
        const j = await act();
        show(j);
        fillForms(j);
        controlMessage.classList.remove("error");
        controlMessage.dataset.field = "";
        setText(controlMessage, `${done}: the job is ${j.state}.`);
        details.request();
      } catch (e) {
        controlMessage.classList.add("error");
        controlMessage.dataset.field = e instanceof ApiError ? e.field : "";
        const field = e instanceof ApiError && e.field ? ` (${e.field})` : "";
        setText(controlMessage, `${(e as Error).message}${field}`);
      } finally {
        button.disabled = false;
      }
    };
    pauseButton.addEventListener("click", () => void control(pauseButton, () => pauseJob(jobId), "Paused"));
    resumeButton.addEventListener("click", () => void control(resumeButton, () => resumeJob(jobId), "Resumed"));
    retryButton.addEventListener("click", () => void control(retryButton, () => retryJob(jobId), "Retried"));
    continueForm.addEventListener("submit", (ev) => {
      ev.preventDefault();
      const change: { max_spp?: number; noise_threshold?: number } = {};
      if (maxSppInput.value !== "") change.max_spp = Number(maxSppInput.value);
      if (thresholdInput.value !== "") change.noise_threshold = Number(thresholdInput.value);
      const button = continueForm.querySelector<HTMLButtonElement>("button")!;
      sent(maxSppInput, thresholdInput);
      void control(button, () => continueJob(jobId, change), "Continued");
    });
    editForm.addEventListener("submit", (ev) => {
      ev.preventDefault();
      const change: { priority?: number; name?: string } = { name: nameInput.value };
      if (priorityInput.value !== "") change.priority = Number(priorityInput.value);
      const button = editForm.querySelector<HTMLButtonElement>("button")!;
      sent(priorityInput, nameInput);
      void control(button, () => updateJob(jobId, change), "Saved");
    });

    const onFinished = async () => {
      source?.close();
      source = null;
      await framesLoader.flush(); // a finished frame's image is final: the viewer keys it so
      await Promise.all([viewer.final(job.progress.samples_merged), details.flush(), loadHistory()]);
      drawPlot();
      // The server logs the finish right after the state changes: look again until it is there.
      for (let i = 0; i < 10 && !finishLogged && !disposed; i++) {
        await new Promise((r) => setTimeout(r, 500));
        await details.flush();
      }
    };

    cancelButton.addEventListener("click", () => {
      cancelButton.hidden = true;
      confirmBox.hidden = false;
      confirmBox.querySelector<HTMLButtonElement>('[data-action="keep"]')!.focus();
    });
    confirmBox.querySelector('[data-action="keep"]')!.addEventListener("click", () => {
      confirmBox.hidden = true;
      cancelButton.hidden = FINISHED.has(job.state);
      cancelButton.focus();
    });
    confirmBox.querySelector('[data-action="confirm-cancel"]')!.addEventListener("click", async (ev) => {
      const button = ev.currentTarget as HTMLButtonElement;
      button.disabled = true;
      try {
        show(await cancelJob(jobId));
      } catch (e) {
        failure.hidden = false;
        setText(failure, `Could not cancel: ${(e as Error).message}`);
      } finally {
        button.disabled = false;
      }
    });

    replace(
      root,
      h("nav", { class: "breadcrumb", "aria-label": "Breadcrumb" }, h("a", { href: "#/jobs" }, "Jobs"), h("span", { "aria-hidden": "true" }, " / "), h("span", { class: "mono" }, jobId)),
      h(
        "div",
        { class: "page-head" },
        h("div", { class: "title-group" }, title, badge),
        actions,
      ),
      failure,
      shortfall,
      stats,
      h(
        "div",
        { class: "job-grid" },
        h("div", { class: "job-main" }, viewer.el, strip?.el),
        h(
          "div",
          { class: "job-side" },
          card("Error against time", plotBox, plotNote),
          card("Job control", continueForm, editForm, controlMessage),
          card("Settings", settingsList),
        ),
      ),
      h(
        "div",
        { class: "job-lower" },
        card("Tile stop records", stopsNote, stopsTable),
        taskLogCard,
        card("Event log", h("div", { class: "table-scroll tall" }, eventsList)),
      ),
    );

    function openStream() {
      source?.close();
      source = new EventSource(watchUrl(jobId));
      source.addEventListener("job", (ev) => {
        setConnection(true);
        if (!disposed) show(JSON.parse((ev as MessageEvent).data) as Job);
      });
      source.onerror = () => {
        // The stream ends after the final state (handled in show); otherwise EventSource retries.
        if (source && source.readyState !== EventSource.OPEN) setConnection(false, "Live updates interrupted, reconnecting…");
      };
    }

    show(initial);
    fillForms(initial);
    renderStops(initial);
    details.request();
    if (FINISHED.has(initial.state)) {
      void onFinished();
      return;
    }
    void loadHistory().then(() => drawPlot());
    drawPlot();
    openStream();
  };

  void start();
  return () => {
    disposed = true;
    source?.close();
    for (const c of cleanups) c();
  };
}

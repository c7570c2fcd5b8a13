// The page: landmarks (radiograph clicks, CSV or a JSON payload) + boundary conditions → POST
// /v1/jobs → poll GET /v1/jobs/{id} → the reconstruction (3D, projections, tables, downloads).
import "./style.css";
import { Api, ApiError, loadApiKey, saveApiKey } from "./api";
import { landmarkCsv, parseLandmarkCsv, resultCsv } from "./csv";
import { Landmarker } from "./landmarker";
import { defaultBoundary, l5FromLandmarks, samplePayload } from "./payload";
import { drawProjections, type Backdrop } from "./projections";
import { fillLegend, fillMeasures, fillStrains } from "./results";
import { FINAL_STATUSES, type Job, type JobPayload, type Pose, type Problem, type Vec2, type Vec3, type ViewPayload } from "./types";
import { SpineViewer } from "./viewer3d";

const $ = <T extends HTMLElement = HTMLElement>(id: string): T => {
  const node = document.getElementById(id);
  if (!node) throw new Error(`#${id} is missing from the page`);
  return node as T;
};

// ------------------------------------------------------------------ state

type Source = "image" | "csv" | "json";
interface Draft {
  source: Source;
  pa: ViewPayload;
  lateral: ViewPayload | null;
  /** Other top-level members of a pasted payload (options, …), sent back as they were. */
  extras: Record<string, unknown>;
}

let draft: Draft | null = null;
let currentJob: Job | null = null;
let jobBackdrop: Backdrop | null = null;
let pollTimer: number | undefined;
let viewer: SpineViewer | null = null;

const apiKeyInput = $<HTMLInputElement>("api-key");
apiKeyInput.value = loadApiKey();
apiKeyInput.addEventListener("input", () => saveApiKey(apiKeyInput.value.trim()));
const api = new Api(() => apiKeyInput.value);

// ------------------------------------------------------------------ tabs

const tabs = [...document.querySelectorAll<HTMLButtonElement>("#source-tabs [role=tab]")];
function selectTab(tab: HTMLButtonElement, focus = true): void {
  for (const t of tabs) {
    const selected = t === tab;
    t.setAttribute("aria-selected", String(selected));
    t.tabIndex = selected ? 0 : -1;
    $(t.getAttribute("aria-controls") ?? "").hidden = !selected;
  }
  if (focus) tab.focus();
}
tabs.forEach((tab, i) => {
  tab.addEventListener("click", () => selectTab(tab));
  tab.addEventListener("keydown", (e) => {
    const to = { ArrowRight: i + 1, ArrowLeft: i - 1, Home: 0, End: tabs.length - 1 }[e.key];
    if (to === undefined) return;
    e.preventDefault();
    selectTab(tabs[(to + tabs.length) % tabs.length]);
  });
});

// ------------------------------------------------------------------ landmarks

const inputError = $("input-error");
function showInputError(message: string | null): void {
  inputError.hidden = !message;
  inputError.textContent = message ?? "";
}

const pixelSpacing = $<HTMLInputElement>("pixel-spacing");
const landmarker = new Landmarker($<HTMLCanvasElement>("image-canvas"), $("image-frame"), () => {
  if (!landmarker.image) return;
  const spacing = Number(pixelSpacing.value);
  draft = {
    source: "image",
    pa: { units: "px", pixel_spacing: [spacing, spacing], landmarks: landmarker.landmarks },
    lateral: null,
    extras: {},
  };
  const next = landmarker.nextLevel;
  const skipped = landmarker.skipped;
  $("click-prompt").textContent = next
    ? `Click the top endplate midpoint of ${next} (${landmarker.landmarks.length} placed${skipped.length ? `, skipped ${skipped.join(", ")}` : ""}).`
    : `All levels done: ${landmarker.landmarks.length} landmarks placed${skipped.length ? `, skipped ${skipped.join(", ")}` : ""}.`;
  draftChanged();
});
pixelSpacing.addEventListener("input", () => {
  if (draft?.source === "image") {
    const s = Number(pixelSpacing.value);
    draft.pa.pixel_spacing = [s, s];
    draftChanged();
  }
});
$<HTMLInputElement>("image-file").addEventListener("change", async (e) => {
  const file = (e.target as HTMLInputElement).files?.[0];
  if (!file) return;
  try {
    showInputError(null);
    await landmarker.load(file);
    $("image-canvas").focus({ preventScroll: true });
  } catch (error) {
    showInputError(error instanceof Error ? error.message : String(error));
  }
});
$("undo-landmark").addEventListener("click", () => landmarker.undo());
$("skip-level").addEventListener("click", () => landmarker.skip());
$("clear-landmarks").addEventListener("click", () => landmarker.clear());
$<HTMLSelectElement>("image-zoom").addEventListener("change", (e) => {
  const value = (e.target as HTMLSelectElement).value;
  landmarker.setZoom(value === "fit" ? "fit" : Number(value));
});

async function readFile(input: HTMLInputElement, into: HTMLTextAreaElement): Promise<void> {
  const file = input.files?.[0];
  if (file) into.value = await file.text();
}
const csvText = $<HTMLTextAreaElement>("csv-text");
$<HTMLInputElement>("csv-file").addEventListener("change", (e) => void readFile(e.target as HTMLInputElement, csvText));
$("use-csv").addEventListener("click", () => {
  const parsed = parseLandmarkCsv(csvText.value);
  if (parsed.errors.length) {
    showInputError(`The CSV has ${parsed.errors.length} problem(s): ${parsed.errors.slice(0, 5).join("; ")}`);
    return;
  }
  showInputError(null);
  const units = $<HTMLSelectElement>("csv-units").value as "mm" | "px";
  const spacing = Number($<HTMLInputElement>("csv-spacing").value);
  const view = (landmarks: ViewPayload["landmarks"]): ViewPayload =>
    units === "px" ? { units, pixel_spacing: [spacing, spacing], landmarks } : { units, landmarks };
  draft = { source: "csv", pa: view(parsed.pa), lateral: parsed.lateral.length ? view(parsed.lateral) : null, extras: {} };
  draftChanged();
});

const jsonText = $<HTMLTextAreaElement>("json-text");
$<HTMLInputElement>("json-file").addEventListener("change", (e) => void readFile(e.target as HTMLInputElement, jsonText));
$("load-sample").addEventListener("click", () => {
  jsonText.value = JSON.stringify(samplePayload(), null, 2);
  useJson();
});
$("use-json").addEventListener("click", useJson);

function useJson(): void {
  let value: unknown;
  try {
    value = JSON.parse(jsonText.value);
  } catch (error) {
    showInputError(`The payload is not valid JSON: ${error instanceof Error ? error.message : String(error)}`);
    return;
  }
  if (!value || typeof value !== "object" || Array.isArray(value)) {
    showInputError("The payload must be a JSON object with pa and boundary.");
    return;
  }
  const { pa, lateral, boundary, ...extras } = value as Record<string, unknown>;
  const landmarksOf = (v: unknown): boolean => !!v && typeof v === "object" && Array.isArray((v as ViewPayload).landmarks);
  if (!landmarksOf(pa)) {
    showInputError("The payload needs pa.landmarks (a list of {level, point}).");
    return;
  }
  showInputError(null);
  draft = { source: "json", pa: pa as ViewPayload, lateral: landmarksOf(lateral) ? (lateral as ViewPayload) : null, extras };
  if (boundary && typeof boundary === "object") {
    const b = boundary as Record<string, Pose>;
    autoL5.checked = false;
    setBoundary({ T1: b.T1 ?? defaultBoundary().T1, L5: b.L5 ?? defaultBoundary().L5 });
  }
  setNoBoundary(boundary === undefined || boundary === null);
  draftChanged();
}

function draftChanged(): void {
  const summary = $("landmark-summary");
  if (!draft) {
    summary.textContent = "No landmarks yet.";
  } else {
    const from = { image: "clicked on the radiograph", csv: "from the CSV", json: "from the payload" }[draft.source];
    const units = draft.pa.units === "px" ? `px at ${draft.pa.pixel_spacing?.[1] ?? "?"} mm/px` : "mm";
    const lat = draft.lateral ? `, ${draft.lateral.landmarks.length} lateral` : "";
    summary.textContent = `${draft.pa.landmarks.length} PA landmark${draft.pa.landmarks.length === 1 ? "" : "s"}${lat} ${from} (${units}).`;
  }
  $<HTMLButtonElement>("download-landmarks").disabled = !draft?.pa.landmarks.length;
  applyAutoL5();
  updatePreview();
}

// ------------------------------------------------------------------ boundary conditions

const boundaryFields = $("boundary-fields");
const inputs: Record<"T1" | "L5", { position: HTMLInputElement[]; directors: HTMLInputElement[][] }> = {
  T1: { position: [], directors: [] },
  L5: { position: [], directors: [] },
};
function numberInput(label: string, id: string): HTMLInputElement {
  const input = document.createElement("input");
  input.type = "number";
  input.step = "any";
  input.id = id;
  input.setAttribute("aria-label", label);
  input.addEventListener("input", updatePreview);
  return input;
}
for (const vertebra of ["T1", "L5"] as const) {
  const fieldset = document.createElement("fieldset");
  const legend = document.createElement("legend");
  legend.textContent = vertebra;
  const grid = document.createElement("div");
  grid.className = "pose-grid";
  const head = ["", "x", "y", "z"].map((t) => {
    const s = document.createElement("span");
    s.className = "pose-head";
    s.textContent = t;
    s.setAttribute("aria-hidden", "true");
    return s;
  });
  grid.append(...head);
  const rowLabel = (text: string): HTMLSpanElement => {
    const s = document.createElement("span");
    s.className = "pose-row";
    s.textContent = text;
    s.setAttribute("aria-hidden", "true");
    return s;
  };
  grid.append(rowLabel("position (mm)"));
  for (const axis of ["x", "y", "z"]) {
    const input = numberInput(`${vertebra} position ${axis} (mm)`, `${vertebra}-position-${axis}`);
    if (vertebra === "L5") input.addEventListener("input", () => (autoL5.checked = false));
    inputs[vertebra].position.push(input);
    grid.append(input);
  }
  for (const d of ["d1", "d2", "d3"]) {
    grid.append(rowLabel(d));
    const row: HTMLInputElement[] = [];
    for (const axis of ["x", "y", "z"]) {
      const input = numberInput(`${vertebra} director ${d} ${axis}`, `${vertebra}-${d}-${axis}`);
      row.push(input);
      grid.append(input);
    }
    inputs[vertebra].directors.push(row);
  }
  fieldset.append(legend, grid);
  boundaryFields.append(fieldset);
}

function setBoundary(boundary: { T1: Pose; L5: Pose }): void {
  for (const v of ["T1", "L5"] as const) {
    boundary[v].position.forEach((x, k) => (inputs[v].position[k].value = String(x)));
    boundary[v].directors.forEach((row, i) => row.forEach((x, k) => (inputs[v].directors[i][k].value = String(x))));
  }
  updatePreview();
}

function readBoundary(): { T1: Pose; L5: Pose } {
  const read = (input: HTMLInputElement): number => (input.value.trim() === "" ? NaN : Number(input.value));
  const pose = (v: "T1" | "L5"): Pose => ({
    position: inputs[v].position.map(read) as Vec3,
    directors: inputs[v].directors.map((row) => row.map(read)) as Pose["directors"],
  });
  return { T1: pose("T1"), L5: pose("L5") };
}

const autoL5 = $<HTMLInputElement>("auto-l5");
const magnification = $<HTMLInputElement>("magnification");
function applyAutoL5(): void {
  if (!autoL5.checked || !draft) return;
  const b = readBoundary();
  const l5 = l5FromLandmarks(draft.pa, b.T1.position, b.L5.position, Number(magnification.value));
  if (l5) l5.forEach((x, k) => (inputs.L5.position[k].value = String(x)));
}
autoL5.addEventListener("change", () => {
  applyAutoL5();
  updatePreview();
});
magnification.addEventListener("input", () => {
  applyAutoL5();
  updatePreview();
});
$("reset-boundary").addEventListener("click", () => {
  setBoundary(defaultBoundary());
  autoL5.checked = true;
  setNoBoundary(false);
  applyAutoL5();
  updatePreview();
});

// "T1 and L5 are not known": the payload goes without boundary, and the pose fields are disabled.
const noBoundary = $<HTMLInputElement>("no-boundary");
function setNoBoundary(on: boolean): void {
  noBoundary.checked = on;
  boundaryFields.querySelectorAll("fieldset").forEach((f) => (f.disabled = on));
  autoL5.disabled = on;
  magnification.disabled = on;
  updatePreview();
}
noBoundary.addEventListener("change", () => setNoBoundary(noBoundary.checked));

// ------------------------------------------------------------------ payload, submit, poll

function buildPayload(): JobPayload | null {
  if (!draft) return null;
  const payload: JobPayload = { ...draft.extras, pa: draft.pa };
  if (!noBoundary.checked) payload.boundary = readBoundary();
  if (draft.lateral) payload.lateral = draft.lateral;
  return payload;
}

function updatePreview(): void {
  const payload = buildPayload();
  // NaN (an empty or invalid field) is shown and sent as null, which the API names in its answer.
  $("payload-preview").textContent = payload ? JSON.stringify(payload, null, 2) : "Give landmarks first.";
}

const statusLine = $("job-status");
const problemBox = $("problem");
const submitButton = $<HTMLButtonElement>("submit");
const cancelButton = $<HTMLButtonElement>("cancel-job");

function showProblem(problem: Problem | null): void {
  problemBox.hidden = !problem;
  problemBox.replaceChildren();
  if (!problem) return;
  const title = document.createElement("p");
  title.className = "problem-title";
  title.textContent = `${problem.title}${problem.status ? ` (HTTP ${problem.status})` : ""}`;
  const detail = document.createElement("p");
  detail.textContent = problem.detail;
  problemBox.append(title, detail);
  if (problem.errors?.length) {
    const list = document.createElement("ul");
    for (const e of problem.errors) {
      const li = document.createElement("li");
      const code = document.createElement("code");
      code.textContent = e.path || "(body)";
      li.append(code, `: ${e.msg}`);
      list.append(li);
    }
    problemBox.append(list);
  }
}

submitButton.addEventListener("click", async () => {
  const payload = buildPayload();
  if (!payload) {
    showProblem({ type: "about:blank", title: "No landmarks", status: 0, detail: "Give the landmarks first: click them on a radiograph, or use a CSV or a payload." });
    return;
  }
  window.clearTimeout(pollTimer);
  showProblem(null);
  submitButton.disabled = true;
  statusLine.textContent = "Submitting…";
  try {
    const job = await api.submit(payload);
    jobBackdrop = draft?.source === "image" && landmarker.image
      ? { url: landmarker.image.url, width: landmarker.image.width, height: landmarker.image.height, spacing: (draft.pa.pixel_spacing ?? [1, 1]) as Vec2 }
      : null;
    track(job);
  } catch (error) {
    statusLine.textContent = "The job was not accepted.";
    showProblem(error instanceof ApiError ? error.problem : { type: "about:blank", title: "Error", status: 0, detail: String(error) });
  } finally {
    submitButton.disabled = false;
  }
});

cancelButton.addEventListener("click", async () => {
  if (!currentJob) return;
  try {
    track(await api.cancel(currentJob.id));
  } catch (error) {
    if (error instanceof ApiError) showProblem(error.problem);
  }
});

function track(job: Job, started = Date.now(), failures = 0): void {
  currentJob = job;
  const seconds = ((Date.now() - started) / 1000).toFixed(1);
  statusLine.dataset.status = job.status;
  const final = FINAL_STATUSES.has(job.status);
  statusLine.textContent = final
    ? `Job ${job.id} ${job.status}.`
    : `Job ${job.id} is ${job.status} (${seconds} s)…`;
  cancelButton.hidden = final;
  if (job.status === "succeeded" && job.result) {
    showResult(job);
    return;
  }
  if (job.status === "failed" && job.error) showProblem(job.error);
  if (final) return;
  const delay = Date.now() - started < 30_000 ? 400 : 2000;
  pollTimer = window.setTimeout(async () => {
    try {
      track(await api.job(job.id), started, 0);
    } catch (error) {
      if (failures >= 5) {
        statusLine.textContent = `Lost track of job ${job.id}.`;
        if (error instanceof ApiError) showProblem(error.problem);
        return;
      }
      track(job, started, failures + 1);
    }
  }, delay);
}

// ------------------------------------------------------------------ result

function showResult(job: Job): void {
  const result = job.result;
  if (!result) return;
  $("result-empty").hidden = true;
  $("result").hidden = false;
  viewer ??= new SpineViewer($("view3d"), $("view3d-orientation"));
  viewer.show(result);
  const payload = (job.payload ?? buildPayload()) as JobPayload;
  const { lateralFromImage } = drawProjections($("view-pa"), $("view-lateral"), result, payload, jobBackdrop);
  $("pa-caption").textContent = jobBackdrop ? " over the radiograph" : " (detector mm)";
  $("lateral-caption").textContent = lateralFromImage ? "Lateral projection (detector mm)" : "Lateral projection of the model (anterior right)";
  fillLegend($("legend"), result);
  fillMeasures($<HTMLTableElement>("measures"), job, result);
  fillStrains($<HTMLTableElement>("strains"), result);
  $("result").dataset.jobId = job.id;
}

function download(name: string, blob: Blob): void {
  const url = URL.createObjectURL(blob);
  const a = document.createElement("a");
  a.href = url;
  a.download = name;
  document.body.append(a);
  a.click();
  a.remove();
  window.setTimeout(() => URL.revokeObjectURL(url), 10_000);
}

$("download-landmarks").addEventListener("click", () => {
  if (draft) download(`landmarks-${draft.pa.units ?? "mm"}.csv`, new Blob([landmarkCsv(draft.pa.landmarks, draft.lateral?.landmarks ?? [])], { type: "text/csv" }));
});
$("download-json").addEventListener("click", () => {
  if (currentJob?.result) download(`spine-${currentJob.id}.json`, new Blob([JSON.stringify(currentJob.result, null, 2)], { type: "application/json" }));
});
$("download-csv").addEventListener("click", () => {
  if (currentJob?.result) download(`spine-${currentJob.id}.csv`, new Blob([resultCsv(currentJob.result)], { type: "text/csv" }));
});
for (const fmt of ["png", "svg"] as const) {
  $(`download-${fmt}`).addEventListener("click", async () => {
    if (!currentJob) return;
    try {
      download(`spine-${currentJob.id}.${fmt}`, await api.blob(`/v1/jobs/${currentJob.id}/figure.${fmt}`));
    } catch (error) {
      if (error instanceof ApiError) showProblem(error.problem);
    }
  });
}
$("view-front").addEventListener("click", () => viewer?.setView("front"));
$("view-side").addEventListener("click", () => viewer?.setView("side"));
$("view-reset").addEventListener("click", () => viewer?.setView("reset"));

setBoundary(defaultBoundary());
draftChanged();
document.body.dataset.ready = "true";

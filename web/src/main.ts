// The page: films (DICOM, PNG or JPEG) with their landmarks, a CSV or a JSON payload → POST
// /v1/jobs → poll GET /v1/jobs/{id} → the reconstruction (3D, projections, measures with their
// trust, report). #/jobs lists the caller's jobs; #/jobs/{id} reopens one after a reload;
// #/follow-up/{patient id} shows a patient's measures over time.
import "./style.css";
import { Api, ApiError, loadApiKey, saveApiKey } from "./api";
import { capabilities, type Capabilities } from "./capabilities";
import { GEOMETRY_FIELD_WORDS, geometryProblems, skippedVertebraWarnings } from "./checks";
import { csvBlob, landmarkCsv, measuresCsv, parseLandmarkCsv, resultCsv } from "./csv";
import { personName } from "./dicom";
import { changesTable, estimateNotes, fillFollowUp, notVisitWords, RULE_WORDS, undatedWords, visitsTable } from "./followup";
import { NoPacs, PacsOpener } from "./pacs";
import { orientationWords, sentences, warningList } from "./messages";
import { FilmPanel, type JobFilm, type ViewName } from "./panel";
import { defaultBoundary, l5FromLandmarks, samplePayload } from "./payload";
import { drawProjections, type Backdrop } from "./projections";
import { COBB_ESTIMATE_REASON, fillLegend, fillLenke, fillMeasures, fillStrains, measureRows, modelMark } from "./results";
import { FINAL_STATUSES, isLevel, type Job, type JobPayload, type Landmark, type Level, type Pose, type Problem, type Study, type Vec3, type ViewPayload } from "./types";
import type { SpineViewer } from "./viewer3d";

const $ = <T extends HTMLElement = HTMLElement>(id: string): T => {
  const node = document.getElementById(id);
  if (!node) throw new Error(`#${id} is missing from the page`);
  return node as T;
};

// ------------------------------------------------------------------ state

type Source = "image" | "csv" | "json";
interface Draft {
  source: Exclude<Source, "image">;
  pa: ViewPayload;
  lateral: ViewPayload | null;
  /** Other top-level members of a pasted payload (options, study, …), sent back as they were. */
  extras: Record<string, unknown>;
  /** Said with the landmark summary (e.g. the lateral spacing taken as the PA's). */
  note?: string;
}

let source: Source = "image";
let draft: Draft | null = null;
/** The reopened job's `study` and `options`, sent again with its landmarks (while a panel holds them). */
let reopenedJob: { study?: Study; options?: unknown } | null = null;
let caps: Capabilities | null = null;
let currentJob: Job | null = null;
let pollTimer: number | undefined;
let viewer: SpineViewer | null = null;
let figureUrl: string | null = null;
/** The PA film under the result's PA projection, when the job was sent from the films on this page. */
let backdrop: Backdrop | null = null;

const apiKeyInput = $<HTMLInputElement>("api-key");
apiKeyInput.value = loadApiKey();
apiKeyInput.addEventListener("input", () => {
  saveApiKey(apiKeyInput.value.trim());
  updatePreview(); // a missing key is listed before sending
});
const api = new Api(() => apiKeyInput.value);

// A refused key is said at the top, beside the key field, whatever asked; typing a key retries
// what the address asks for (the job, the list, the follow-up) without a reload.
const keyProblem = $("key-problem");
let refused = false;
api.onRefused = (problem) => {
  refused = true;
  keyProblem.hidden = false;
  const typed = apiKeyInput.value.trim();
  keyProblem.textContent = `${typed ? "The service refused this API key" : "An API key is needed"}: ${problem.detail || problem.title}. ${typed ? "Check it" : "Enter it above"}; the page retries as you type.`;
  apiKeyInput.setAttribute("aria-invalid", "true");
};
let keyRetry: number | undefined;
apiKeyInput.addEventListener("input", () => {
  window.clearTimeout(keyRetry);
  keyRetry = window.setTimeout(() => {
    if (!refused || !apiKeyInput.value.trim()) return;
    refused = false;
    keyProblem.hidden = true;
    apiKeyInput.removeAttribute("aria-invalid");
    currentJob = null;
    route();
    draftChanged();
  }, 400);
});

// ------------------------------------------------------------------ tabs

function tablist(listId: string, onSelect: (tab: HTMLButtonElement) => void = () => {}): (tab: HTMLButtonElement, focus?: boolean) => void {
  const tabs = [...document.querySelectorAll<HTMLButtonElement>(`#${listId} [role=tab]`)];
  const select = (tab: HTMLButtonElement, focus = true): void => {
    for (const t of tabs) {
      const selected = t === tab;
      t.setAttribute("aria-selected", String(selected));
      t.tabIndex = selected ? 0 : -1;
      $(t.getAttribute("aria-controls") ?? "").hidden = !selected;
    }
    if (focus) tab.focus();
    onSelect(tab);
  };
  tabs.forEach((tab, i) => {
    tab.addEventListener("click", () => select(tab));
    tab.addEventListener("keydown", (e) => {
      const to = { ArrowRight: i + 1, ArrowLeft: i - 1, Home: 0, End: tabs.length - 1 }[e.key];
      if (to === undefined) return;
      e.preventDefault();
      select(tabs[(to + tabs.length) % tabs.length]);
    });
  });
  return select;
}
const selectSourceTab = tablist("source-tabs");
const selectFilmTab = tablist("film-tabs");

// ------------------------------------------------------------------ films

const panels: Record<ViewName, FilmPanel> = {
  pa: new FilmPanel("pa", $("film-pa"), () => filmsChanged()),
  lateral: new FilmPanel("lateral", $("film-lateral"), () => filmsChanged()),
};

// A lateral film opened starts at the first level placed on the PA film that the lateral does not yet have
// (a lateral most often starts lower than T1, at the PA's first level); T1 when the PA has none.
panels.lateral.startLevel = () => {
  const onLateral = new Set(panels.lateral.editor.landmarks().map((lm) => lm.level));
  const onPa = panels.pa.editor.landmarks().map((lm) => lm.level);
  if (!onPa.length) return onLateral.has("T1") ? null : "T1";
  return onPa.find((lv) => !onLateral.has(lv)) ?? null;
};

const pacs = new PacsOpener({
  api,
  open: async (view, file) => {
    selectFilmTab($<HTMLButtonElement>(`tab-film-${view}`), false);
    await panels[view].open(file);
  },
});
let pacsCheck: number | undefined;
apiKeyInput.addEventListener("input", () => {
  window.clearTimeout(pacsCheck);
  pacsCheck = window.setTimeout(() => void pacs.refresh(caps?.pacsRoutes ?? false), 300);
});

function filmsChanged(): void {
  source = "image";
  draftChanged();
}

const inputError = $("input-error");
function showInputError(message: string | null): void {
  inputError.hidden = !message;
  inputError.textContent = message ?? "";
}

async function readFile(input: HTMLInputElement, into: HTMLTextAreaElement): Promise<void> {
  const file = input.files?.[0];
  if (file) into.value = await file.text();
}
const csvText = $<HTMLTextAreaElement>("csv-text");
$<HTMLInputElement>("csv-file").addEventListener("change", (e) => void readFile(e.target as HTMLInputElement, csvText));
$("use-csv").addEventListener("click", () => {
  const parsed = parseLandmarkCsv(csvText.value);
  const units = $<HTMLSelectElement>("csv-units").value as "mm" | "px";
  // Each film its own spacing: the lateral one, when left empty, is the PA film's (one detector).
  const spacing = Number($<HTMLInputElement>("csv-spacing").value);
  const lateralTyped = $<HTMLInputElement>("csv-spacing-lateral").value.trim();
  const lateralSpacing = lateralTyped === "" ? spacing : Number(lateralTyped);
  if (!parsed.errors.length && units === "px") {
    if (!(spacing > 0)) parsed.errors.push("pixel coordinates need the PA film's pixel spacing (mm per pixel): enter it beside the units");
    else if (parsed.lateral.length && !(lateralSpacing > 0)) parsed.errors.push(`the lateral film's pixel spacing ${JSON.stringify(lateralTyped)} is not a positive number of mm per pixel: enter it, or leave it empty to use the PA film's`);
  }
  if (parsed.errors.length) {
    const dropped = dropDraft("CSV");
    showInputError(`The CSV has ${parsed.errors.length} problem${parsed.errors.length === 1 ? "" : "s"}: ${parsed.errors.slice(0, 5).join("; ")}.${dropped}`);
    return;
  }
  showInputError(null);
  const view = (landmarks: ViewPayload["landmarks"], s: number): ViewPayload =>
    units === "px" ? { units, pixel_spacing: [s, s], landmarks } : { units, landmarks };
  const note = units === "px" && parsed.lateral.length && lateralTyped === ""
    ? `The lateral film's pixel spacing is taken as the PA film's, ${spacing} mm: enter its own beside the units if it differs.`
    : undefined;
  draft = { source: "csv", pa: view(parsed.pa, spacing), lateral: parsed.lateral.length ? view(parsed.lateral, lateralSpacing) : null, extras: {}, note };
  source = "csv";
  reopenedJob = null;
  draftChanged();
});

/** After a failed import: the previous CSV or payload is no longer what the text says, so it is not
 * sent; returns the sentence that says so (empty when there was none). */
function dropDraft(what: "CSV" | "payload"): string {
  if (source === "image" || !draft) return "";
  const was = draft.source === "csv" ? "CSV" : "payload";
  draft = null;
  draftChanged();
  return ` The landmarks of the ${was} used before were dropped, so that nothing is sent from it: fix this ${what} and use it again.`;
}

const jsonText = $<HTMLTextAreaElement>("json-text");
$<HTMLInputElement>("json-file").addEventListener("change", (e) => void readFile(e.target as HTMLInputElement, jsonText));
$("load-sample").addEventListener("click", () => {
  const sample = samplePayload();
  delete sample.boundary; // the clinic's default: nothing assumed about T1 and L5
  jsonText.value = JSON.stringify(sample, null, 2);
  useJson();
});
$("use-json").addEventListener("click", useJson);

function useJson(): void {
  let value: unknown;
  try {
    value = JSON.parse(jsonText.value);
  } catch (error) {
    showInputError(`The payload is not valid JSON: ${error instanceof Error ? error.message : String(error)}.${dropDraft("payload")}`);
    return;
  }
  if (!value || typeof value !== "object" || Array.isArray(value)) {
    showInputError(`The payload must be a JSON object with pa (and optionally lateral, boundary, study).${dropDraft("payload")}`);
    return;
  }
  const { pa, lateral, boundary, ...extras } = value as Record<string, unknown>;
  const landmarksOf = (v: unknown): boolean => !!v && typeof v === "object" && Array.isArray((v as ViewPayload).landmarks);
  if (!landmarksOf(pa)) {
    showInputError(`The payload needs pa.landmarks: a list of {level, point} or {level, corners}.${dropDraft("payload")}`);
    return;
  }
  showInputError(null);
  draft = { source: "json", pa: pa as ViewPayload, lateral: landmarksOf(lateral) ? (lateral as ViewPayload) : null, extras };
  source = "json";
  reopenedJob = null;
  applyBoundary(boundary);
  draftChanged();
}

function applyBoundary(boundary: unknown): void {
  if (boundary && typeof boundary === "object") {
    const b = boundary as Record<string, Pose>;
    autoL5.checked = false;
    setBoundary({ T1: b.T1 ?? defaultBoundary().T1, L5: b.L5 ?? defaultBoundary().L5 });
    setGiveBoundary(true);
    $<HTMLDetailsElement>("boundary-details").open = true;
  } else {
    setGiveBoundary(false);
  }
}

/** The views of the payload: from the films, or from the CSV / JSON draft. */
function views(): { pa: ViewPayload | null; lateral: ViewPayload | null } {
  if (source !== "image") return { pa: draft?.pa ?? null, lateral: draft?.lateral ?? null };
  const accepts = { acquisition: !!caps?.acquisition, calibration: !!caps?.calibration, imageSize: !!caps?.imageSize, projectionModel: !!caps?.projectionModel };
  return { pa: panels.pa.payload(accepts), lateral: panels.lateral.payload(accepts) };
}

function draftChanged(): void {
  const v = views();
  const summary = $("landmark-summary");
  if (!v.pa && !v.lateral) {
    summary.textContent = "No landmarks yet.";
  } else {
    const from = { image: "placed on the films", csv: "from the CSV", json: "from the payload" }[source];
    const count = (x: ViewPayload | null, name: string): string => (x ? `${x.landmarks.length} ${name} landmark${x.landmarks.length === 1 ? "" : "s"}` : "");
    const note = source !== "image" && draft?.note ? ` ${draft.note}` : "";
    summary.textContent = `${[count(v.pa, "PA"), count(v.lateral, "lateral")].filter(Boolean).join(", ")} ${from}.${note}`;
  }
  $<HTMLButtonElement>("download-landmarks").disabled = !(v.pa?.landmarks.length || v.lateral?.landmarks.length);
  applyAutoL5();
  updatePreview();
  updateStale();
}

// ------------------------------------------------------------------ boundary conditions (advanced)

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
  const cell = (text: string, cls: string): HTMLSpanElement => {
    const s = document.createElement("span");
    s.className = cls;
    s.textContent = text;
    s.setAttribute("aria-hidden", "true");
    return s;
  };
  grid.append(...["", "x", "y", "z"].map((t) => cell(t, "pose-head")));
  grid.append(cell("position (mm)", "pose-row"));
  for (const axis of ["x", "y", "z"]) {
    const input = numberInput(`${vertebra} position ${axis} (mm)`, `${vertebra}-position-${axis}`);
    if (vertebra === "L5") input.addEventListener("input", () => (autoL5.checked = false));
    inputs[vertebra].position.push(input);
    grid.append(input);
  }
  for (const d of ["d1", "d2", "d3"]) {
    grid.append(cell(d, "pose-row"));
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
  const pa = views().pa;
  if (!autoL5.checked || !pa) return;
  const b = readBoundary();
  const l5 = l5FromLandmarks(pa, b.T1.position, b.L5.position, Number(magnification.value));
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
  applyAutoL5();
  updatePreview();
});

// Poses are sent only when the user says so: the clinic's default assumes nothing about T1 and L5.
const giveBoundary = $<HTMLInputElement>("give-boundary");
function setGiveBoundary(on: boolean): void {
  giveBoundary.checked = on;
  boundaryFields.querySelectorAll("fieldset").forEach((f) => (f.disabled = !on));
  autoL5.disabled = !on;
  magnification.disabled = !on;
  updatePreview();
}
giveBoundary.addEventListener("change", () => setGiveBoundary(giveBoundary.checked));

// ------------------------------------------------------------------ payload, what is missing, submit, poll

function studyFromFilms(): Study | null {
  const pa = panels.pa.dicom?.study;
  const lat = panels.lateral.dicom?.study;
  const uid = pa?.study_instance_uid ?? lat?.study_instance_uid;
  if (source !== "image" || !uid) return null;
  const all: Record<string, string | undefined> = {
    study_instance_uid: uid,
    series_instance_uid: pa?.series_instance_uid ?? lat?.series_instance_uid,
    pa_sop_instance_uid: pa?.sop_instance_uid,
    lateral_sop_instance_uid: lat?.study_instance_uid === uid ? lat?.sop_instance_uid : undefined,
    patient_id: pa?.patient_id ?? lat?.patient_id,
    patient_name: pa?.patient_name ?? lat?.patient_name,
    accession_number: pa?.accession_number ?? lat?.accession_number,
    study_date: pa?.study_date ?? lat?.study_date,
  };
  const fields = caps?.studyFields ?? new Set(["study_instance_uid"]);
  const study: Record<string, string> = {};
  for (const [k, v] of Object.entries(all)) if (v && fields.has(k)) study[k] = v;
  return study as unknown as Study;
}

function buildPayload(): JobPayload | null {
  const v = views();
  if (!v.pa) return null;
  const payload: JobPayload = { ...(source === "image" ? {} : draft?.extras), pa: v.pa };
  if (v.lateral) payload.lateral = v.lateral;
  if (giveBoundary.checked) payload.boundary = readBoundary();
  // A reopened job's draft keeps its study and options while a panel holds its landmarks, unless a
  // DICOM film of another study replaced it (then the film's study, and no options of the job).
  const fromFilms = studyFromFilms();
  const replaced = !!fromFilms && !!reopenedJob?.study && fromFilms.study_instance_uid !== reopenedJob.study.study_instance_uid;
  const job = source === "image" && reopenedJob && !replaced && (panels.pa.fromJob || panels.lateral.fromJob) ? reopenedJob : null;
  const study = job?.study ? { ...job.study, ...fromFilms } : fromFilms;
  if (study) payload.study = study;
  if (job?.options !== undefined) payload.options = job.options as JobPayload["options"];
  return payload;
}

/** The PA and lateral DICOM films must be of one patient and one study: what says they are not. */
function filmsOfOnePatient(): string[] {
  const pa = panels.pa.dicom?.study;
  const lat = panels.lateral.dicom?.study;
  if (!pa || !lat) return [];
  const out: string[] = [];
  const close = "Close the film that is not this patient's (“Close film” under it) and open the right one.";
  if (pa.patient_id && lat.patient_id && pa.patient_id !== lat.patient_id) {
    out.push(`The films are of two patients: the PA film is of patient ID ${pa.patient_id}, the lateral film of patient ID ${lat.patient_id}. ${close}`);
  } else if (pa.study_instance_uid && lat.study_instance_uid && pa.study_instance_uid !== lat.study_instance_uid) {
    out.push(`The films are of two studies: the PA film is of study ${pa.study_instance_uid}, the lateral film of study ${lat.study_instance_uid}${pa.patient_id ? ` (patient ID ${pa.patient_id})` : ""}. Both films of a job come from one study: close the one that is not (“Close film” under it) and open the right one.`);
  }
  return out;
}

/** What stops the input from being a valid job, in plain words (the service checks again). */
function missing(): string[] {
  const out: string[] = [];
  const v = views();
  if (caps?.needsKey && !apiKeyInput.value.trim()) out.push("Enter the API key at the top of the page: `spine keys create` makes one (the first `spine serve` prints one).");
  if (source === "image") {
    out.push(...filmsOfOnePatient());
    out.push(...panels.pa.problems(), ...panels.lateral.problems());
    if (!panels.pa.hasFilm()) out.push("Open the PA film (DICOM, PNG or JPEG), or give the landmarks as a CSV or a payload.");
  }
  // The acquisition geometry the service refuses (its rules: checks.ts geometryProblems), named by field.
  for (const name of ["pa", "lateral"] as const) {
    const view = v[name];
    if (!view) continue;
    const remedy = source === "image" ? panels[name].geometryRemedy() : "correct the payload's acquisition";
    for (const p of geometryProblems(view)) {
      out.push(`${name === "pa" ? "PA" : "Lateral"} film, ${GEOMETRY_FIELD_WORDS[p.field]}: ${p.text}: ${remedy}.`);
    }
  }
  if (!v.pa) {
    if (source !== "image" || panels.pa.hasFilm()) out.push("Place landmarks on the PA film: the PA view is required.");
  } else if (caps?.acquisition) {
    // The engine takes any levels: at least 2 on the PA film, 3 on a lateral one
    // (spine_engine.validation.MIN_LEVELS_PA / MIN_LEVELS_LATERAL), none required by name.
    if (v.pa.landmarks.length < 2 && !v.pa.projection) out.push("Place at least two vertebrae on the PA film: with one, the film's position of the spine is undetermined.");
    const n = v.lateral?.landmarks.length ?? 0;
    if (n > 0 && n < 3 && !v.lateral?.projection) out.push(`Place at least three vertebrae on the lateral film (${n} now), or clear it: fewer cannot fix its scale and turn.`);
  } else {
    // This service's engine needs T1 and L5 on every film whose projection it estimates.
    for (const [name, view] of [["PA", v.pa], ["lateral", v.lateral]] as const) {
      if (!view || view.projection) continue;
      const levels = new Set(view.landmarks.map((l) => l.level));
      const lacking = (["T1", "L5"] as const).filter((l) => !levels.has(l));
      if (lacking.length) out.push(`Place ${lacking.join(" and ")} on the ${name} film: this service needs the first and last vertebrae to set the film's scale and place the spine.`);
    }
  }
  if (giveBoundary.checked) {
    const b = readBoundary();
    const bad = (["T1", "L5"] as const).filter((k) => [...b[k].position, ...b[k].directors.flat()].some((x) => !Number.isFinite(x)));
    if (bad.length) out.push(`Fill every number of the ${bad.join(" and ")} pose, or untick “Send these T1 and L5 poses”.`);
  }
  return out;
}

/** The payload (as JSON) of the last send the service refused as it was (`REFUSES_DRAFT`): while the draft is
 * still exactly that, "Before sending" says so instead of "Ready to send". */
let refusedDraft: string | null = null;
/** The answers to POST /v1/jobs that refuse its payload: malformed, too large, not JSON, or not a usable job. */
const REFUSES_DRAFT = new Set([400, 413, 415, 422]);

function updatePreview(): void {
  const payload = buildPayload();
  $("payload-preview").textContent = payload ? JSON.stringify(payload, null, 2) : "Give landmarks first.";
  const box = $("missing");
  const list = missing();
  const refusedNow = !!payload && refusedDraft !== null && refusedDraft === JSON.stringify(payload);
  box.replaceChildren();
  if (list.length) {
    const p = document.createElement("p");
    p.textContent = "Before this can be sent:";
    const ul = document.createElement("ul");
    for (const m of list) {
      const li = document.createElement("li");
      li.textContent = m;
      ul.append(li);
    }
    box.append(p, ul);
  } else if (refusedNow) {
    const p = document.createElement("p");
    p.className = "refused";
    p.textContent = "Refused when last sent: the service did not take this draft, for the reasons shown under the Reconstruct button. Change what they name, then send again.";
    box.append(p);
  } else if (payload) {
    const p = document.createElement("p");
    p.className = "ready";
    p.textContent = `Ready to send: ${payload.lateral ? "PA and lateral films" : "the PA film"}, ${payload.boundary ? "with the given T1 and L5 poses" : "no T1/L5 poses assumed"}.`;
    box.append(p);
  }
  const warnings = payload ? skippedVertebraWarnings(payload) : [];
  if (warnings.length) box.append(warningList(warnings));
  box.dataset.ready = String(!list.length && !!payload);
  box.dataset.refused = String(!list.length && refusedNow);
}

const statusLine = $("job-status");
const problemBox = $("problem");
const submitButton = $<HTMLButtonElement>("submit");
const cancelButton = $<HTMLButtonElement>("cancel-job");
const checkButton = $<HTMLButtonElement>("check-job");

function showProblem(box: HTMLElement, problem: Problem | null, payload?: unknown): void {
  box.hidden = !problem;
  box.replaceChildren();
  const ringed = box === problemBox ? markRefused(problem, payload) : "";
  const oriented = box === problemBox ? markOrientation(problem, payload) : [];
  if (!problem) return;
  const { title, lines } = sentences(problem, payload);
  const head = document.createElement("p");
  head.className = "problem-title";
  head.textContent = `${title}.`;
  box.append(head);
  const list = document.createElement("ul");
  for (const line of lines) {
    const li = document.createElement("li");
    li.textContent = line;
    list.append(li);
  }
  box.append(list);
  if (ringed) {
    const p = document.createElement("p");
    p.id = "refused-note";
    p.textContent = ringed;
    box.append(p);
  }
  for (const name of oriented) {
    const film = name === "pa" ? "PA" : "lateral";
    const p = document.createElement("p");
    p.textContent = `The orientation of the ${film} film was refused: it is said at the ${film} film's “Orientation”, with what to change there; the landmarks stay. `;
    const go = document.createElement("button");
    go.type = "button";
    go.className = "go-to-field";
    go.textContent = `Go to the ${film} film's orientation`;
    go.addEventListener("click", () => showFilm(name, true));
    p.append(go);
    box.append(p);
  }
}

/** Show a film's panel (the Films tab, the film's tab); with `focus`, its orientation controls focused. */
function showFilm(name: ViewName, focus = false): void {
  selectSourceTab($<HTMLButtonElement>("tab-image"), false);
  selectFilmTab($<HTMLButtonElement>(`tab-film-${name}`), false);
  if (focus) panels[name].focusOrientation();
}

/**
 * Say at each film's orientation controls a refusal naming its orientation (an error's path
 * `<view>.patient_orientation`: `orientation_not_of_view`, `lateral_profile_inverted`), while the film
 * holds the landmarks and orientation that were sent, and show the first such film's panel; returns the
 * views so marked. A problem of null takes the marks away.
 */
function markOrientation(problem: Problem | null, payload: unknown): ViewName[] {
  const sent = (payload && typeof payload === "object" ? payload : {}) as Partial<JobPayload>;
  const now = source === "image" ? views() : null;
  const marked: ViewName[] = [];
  for (const name of ["pa", "lateral"] as const) {
    const errors = (problem?.errors ?? []).filter((e) => e.path === `${name}.patient_orientation`);
    const was = sent[name];
    const held = now?.[name];
    const same = !!was && !!held && JSON.stringify(held.patient_orientation) === JSON.stringify(was.patient_orientation) &&
      JSON.stringify(held.landmarks.map(landmarkKey)) === JSON.stringify(was.landmarks.map(landmarkKey));
    const words = same && errors.length ? errors.map((e) => orientationWords(e, was.patient_orientation)).join(" ") : null;
    panels[name].refuseOrientation(words);
    if (words) marked.push(name);
  }
  if (marked.length) showFilm(marked[0]);
  return marked;
}

/** A landmark as compared between the payload sent and the films now: level and points, to 0.001. */
function landmarkKey(lm: Landmark): string {
  const r = (p: unknown): unknown => (Array.isArray(p) ? p.map(r) : typeof p === "number" ? Math.round(p * 1000) / 1000 : p ?? null);
  return JSON.stringify([lm.level, r(lm.point), r(lm.corners), r(lm.pedicles)]);
}

/**
 * Ring in red, on the films, the landmarks a refusal names (its errors' paths `pa.landmarks[3]…`,
 * the payload's own indices, as the service gives them), while the films hold exactly the landmarks
 * that were sent; returns the sentence that says so (empty when none is ringed). A problem of null
 * takes the rings away.
 */
function markRefused(problem: Problem | null, payload: unknown): string {
  const sent = (payload && typeof payload === "object" ? payload : {}) as Partial<JobPayload>;
  const now = source === "image" ? views() : null;
  const words: string[] = [];
  for (const name of ["pa", "lateral"] as const) {
    const landmarks = sent[name]?.landmarks;
    const levels: Level[] = [];
    for (const e of problem?.errors ?? []) {
      const m = /^(pa|lateral)\.landmarks\[(\d+)\]/.exec(e.path ?? "");
      const level = m && m[1] === name ? landmarks?.[Number(m[2])]?.level : undefined;
      if (typeof level === "string" && isLevel(level) && !levels.includes(level)) levels.push(level);
    }
    const same = !!now?.[name] && !!landmarks && JSON.stringify(now[name]!.landmarks.map(landmarkKey)) === JSON.stringify(landmarks.map(landmarkKey));
    const ringed = same ? levels : [];
    panels[name].editor.setRefused(ringed);
    if (ringed.length) words.push(`the ${name === "pa" ? "PA" : "lateral"} film (${ringed.join(", ")})`);
  }
  return words.length ? `The landmarks the service refused are ringed in red on ${words.join(" and on ")}: move them or place them again.` : "";
}

/** The Idempotency-Key of the draft as last sent: the same key while the payload is unchanged (an
 * accidental second click replays the job it made), a new one after any edit. */
let sent: { body: string; key: string } | null = null;
function idempotencyKey(payload: JobPayload): string {
  const body = JSON.stringify(payload);
  if (sent?.body !== body) {
    // crypto.getRandomValues, not randomUUID: the page may be served over plain HTTP (no secure context)
    const bytes = crypto.getRandomValues(new Uint8Array(16));
    sent = { body, key: `web-${[...bytes].map((b) => b.toString(16).padStart(2, "0")).join("")}` };
  }
  return sent.key;
}

submitButton.addEventListener("click", async () => {
  caps ??= await capabilities();
  const payload = buildPayload();
  const list = missing();
  if (!payload || list.length) {
    updatePreview();
    showProblem(problemBox, { type: "about:blank", title: "Not ready", status: 0, detail: list.join(" ") || "Give the landmarks first." });
    $("missing").focus?.();
    return;
  }
  stopPolling();
  openingJob = null; // a job still being opened by its address (its read retried) is not shown over the one sent
  showProblem(problemBox, null);
  submitButton.disabled = true;
  statusLine.textContent = "Submitting…";
  // The PA film as sent: taken now, not when the service answers (the film may be closed or replaced meanwhile).
  const under = source === "image" && !panels.pa.reopened ? panels.pa.backdrop() : Promise.resolve(null);
  try {
    const { job, replayed } = await api.submit(payload, idempotencyKey(payload));
    sentPayloads.set(job.id, payload);
    history.replaceState(null, "", `#/jobs/${job.id}`);
    if (backdrop) URL.revokeObjectURL(backdrop.url);
    backdrop = await under;
    replayedJob = replayed ? job.id : null;
    refusedDraft = null;
    track(job);
  } catch (error) {
    void under.then((b) => b && URL.revokeObjectURL(b.url));
    statusLine.textContent = "The job was not accepted.";
    showProblem(problemBox, problemOf(error), payload);
    // a refusal of the payload itself, not of the key (401, 403) nor a service out of reach (0, 429, 5xx)
    refusedDraft = error instanceof ApiError && REFUSES_DRAFT.has(error.problem.status) ? JSON.stringify(payload) : null;
    updatePreview();
  } finally {
    submitButton.disabled = false;
    // A disabled button loses the focus (to the page's body): give it back when the answer is in.
    if (document.activeElement === document.body || document.activeElement === submitButton || !document.activeElement) submitButton.focus();
  }
});

/** The job the service gave back for an unchanged draft sent again (same Idempotency-Key). */
let replayedJob: string | null = null;

cancelButton.addEventListener("click", async () => {
  if (!currentJob) return;
  try {
    track(await api.cancel(currentJob.id));
  } catch (error) {
    if (error instanceof ApiError) showProblem(problemBox, error.problem);
  }
});

/** When the service last answered about the tracked job (ms since the epoch), and how many polls in a
 * row since then it has not (no answer, or an answer that waiting may change). */
let lastAnswer = 0;
let unanswered = 0;
/** The job whose poll is waiting for the service ("Check now" then asks nothing more). */
let polling: string | null = null;
/** The job the page polls, and since when it has followed it (ms): none once another job is opened or sent. */
let following: { id: string; started: number } | null = null;

/** Poll no more (another job is opened or sent): an answer about the job followed until now is dropped. */
function stopPolling(): void {
  window.clearTimeout(pollTimer);
  openRetry?.stop(); // a reopened job's first read waiting to ask again: another job was opened or sent
  following = null;
  checkButton.hidden = true;
  delete statusLine.dataset.tracking;
}

/** An answer that waiting may change: none at all (network error, status 0), 408, 429 and 5xx (an API
 * restarting, a proxy without its upstream). 401/403 (the key) and 404 (no such job) will not. */
const transient = (status: number): boolean => !status || status === 408 || status === 429 || status >= 500;

/** The wait (ms) before the next poll after `tries` unanswered polls in a row: 1 s doubling to at most 30 s,
 * or the answer's Retry-After when it gives one (at least 1 s; at most 10 min, "Check now" asks sooner). */
function retryDelay(tries: number, retryAfterMs: number | null): number {
  if (retryAfterMs !== null) return Math.min(Math.max(retryAfterMs, 1000), 600_000);
  return Math.min(1000 * 2 ** (tries - 1), 30_000);
}

const clock = (ms: number): string => new Date(ms).toLocaleTimeString();

/** Show the job as the service last gave it and, until it is final, poll it again (every 0.4 s for its first
 * 30 s, then every 2 s). Called with each answer about the job. */
function track(job: Job, started = Date.now()): void {
  currentJob = job;
  following = { id: job.id, started };
  lastAnswer = Date.now();
  unanswered = 0;
  checkButton.hidden = true;
  delete statusLine.dataset.tracking;
  const seconds = ((Date.now() - started) / 1000).toFixed(1);
  statusLine.dataset.status = job.status;
  const final = FINAL_STATUSES.has(job.status);
  const again = replayedJob === job.id ? " Sent again unchanged: the service gave back this same job (nothing new was made)." : "";
  statusLine.textContent = (final ? `Job ${job.id} ${job.status}.` : `Job ${job.id} is ${job.status} (${seconds} s)…`) + again;
  cancelButton.hidden = final;
  if (job.status === "succeeded" && job.result) {
    showResult(job);
    return;
  }
  noResult(job);
  if (job.status === "failed" && job.error) showProblem(problemBox, job.error, job.payload);
  if (final) return;
  schedulePoll(job, started, Date.now() - started < 30_000 ? 400 : 2000);
}

function schedulePoll(job: Job, started: number, delay: number): void {
  window.clearTimeout(pollTimer);
  pollTimer = window.setTimeout(() => void poll(job, started), delay);
}

/** Ask the service for the job once. Without an answer, or with one that waiting may change, ask again
 * later (`retryDelay`), for as long as the job is the page's: the service keeps the job (stored in its
 * database) and its worker goes on with it whether or not the page reaches it. An answer that waiting
 * will not change (401, 403, 404, …) stops the polling and is shown. */
async function poll(job: Job, started: number): Promise<void> {
  window.clearTimeout(pollTimer);
  polling = job.id;
  let answer: Job;
  try {
    answer = await api.job(job.id);
  } catch (error) {
    if (following?.id !== job.id || currentJob?.id !== job.id) return; // another job was opened or sent meanwhile
    const problem = problemOf(error);
    if (!transient(problem.status)) {
      stopTracking(job, problem);
      return;
    }
    unanswered += 1;
    const wait = retryDelay(unanswered, error instanceof ApiError ? error.retryAfterMs : null);
    sayUnanswered(job, problem, wait);
    schedulePoll(job, started, wait);
    return;
  } finally {
    if (polling === job.id) polling = null;
  }
  if (following?.id !== job.id || currentJob?.id !== job.id) return; // another job was opened or sent while the service answered
  track(answer, started);
}

/** The status line while the service does not answer about the job: since when, why, when the page asks again. */
function sayUnanswered(job: Job, problem: Problem, wait: number): void {
  statusLine.dataset.tracking = "retrying";
  const why = problem.status ? `HTTP ${problem.status}, ${problem.detail || problem.title}` : problem.detail || problem.title;
  statusLine.textContent = `The service has not answered about job ${job.id} since ${clock(lastAnswer)} (${unanswered} ${unanswered === 1 ? "try" : "tries"}; the last: ${why}). ` +
    `The job is kept by the service, which goes on with it (it was ${job.status} then). ` +
    `The page asks again at ${clock(Date.now() + wait)}, or at once with “Check now”.`;
  checkButton.hidden = false;
}

/** The problem an API call's error carries: the service's problem+json, or one made of an error with no answer. */
function problemOf(error: unknown): Problem {
  return error instanceof ApiError ? error.problem : { type: "about:blank", title: "Error", status: 0, detail: String(error) };
}

/** Why an answer about a job will not change by waiting (401, 403, 404, …), in words. */
function finalWhy(problem: Problem): string {
  return problem.status === 404
    ? "the service has no such job for this API key"
    : problem.status === 401 || problem.status === 403
    ? "the service refused the API key (said at the top of the page)"
    : `the service answered HTTP ${problem.status}`;
}

/** Stop polling the job: the service's answer (401, 403, 404, …) will not change by waiting. */
function stopTracking(job: Job, problem: Problem): void {
  statusLine.dataset.tracking = "stopped";
  checkButton.hidden = true;
  statusLine.textContent = `Stopped following job ${job.id}: ${finalWhy(problem)}, which waiting will not change (the problem is shown below).`;
  showProblem(problemBox, problem);
}

checkButton.addEventListener("click", () => {
  if (openRetry) return openRetry.now(); // a reopened job's first read, waiting to ask again
  if (currentJob && following?.id === currentJob.id && polling !== currentJob.id) void poll(currentJob, following.started);
});

// ------------------------------------------------------------------ result and report

/** A job without a result (queued, running, failed, cancelled): no other job's result stays under its
 * address (its table, 3D view, downloads and printed report would pass for this job's). */
function noResult(job: Job): void {
  $("result").hidden = true;
  delete $("result").dataset.jobId;
  updateStale();
  delete $("view3d").dataset.shown;
  const empty = $("result-empty");
  empty.hidden = false;
  empty.textContent = job.status === "failed"
    ? `Job ${job.id.slice(0, 8)} failed: it has no result (why is said above).`
    : job.status === "cancelled"
    ? `Job ${job.id.slice(0, 8)} was cancelled: it has no result.`
    : `Job ${job.id.slice(0, 8)} is ${job.status}: its result appears here once it has succeeded.`;
}

function showResult(job: Job): void {
  const result = job.result;
  if (!result) return;
  $("result-empty").hidden = true;
  $("result").hidden = false;
  // three.js is loaded with the first result only: the page's first render does not wait for it.
  // Said while three.js is fetched (the first result), and when it cannot be: an empty box says neither.
  const view3d = $("view3d");
  const said = $("view3d-orientation");
  if (!viewer) {
    view3d.setAttribute("aria-busy", "true");
    said.textContent = "Loading the 3D view…";
  }
  void import("./viewer3d").then(({ SpineViewer }) => {
    view3d.removeAttribute("aria-busy");
    if (currentJob?.id !== job.id) return; // another job was opened while three.js was fetched
    viewer ??= new SpineViewer(view3d, said);
    viewer.show(result);
    view3d.dataset.shown = job.id;
  }, (error: unknown) => {
    view3d.removeAttribute("aria-busy");
    said.textContent = `The 3D view could not be loaded (${error instanceof Error ? error.message : String(error)}): ` +
      "the measures, the PA and lateral projections and the report below do not need it; reload the page to try again.";
  });
  drawViews(job);
  fillLegend($("legend"), result);
  fillMeasures($<HTMLTableElement>("measures"), job, result);
  fillLenke($("lenke"), result);
  fillStrains($<HTMLTableElement>("strains"), result);
  fillReportHead(job);
  $<HTMLAnchorElement>("job-link").href = `#/jobs/${job.id}`;
  const patientId = (job.study ?? job.payload?.study)?.patient_id;
  const followLink = $<HTMLAnchorElement>("followup-link");
  followLink.hidden = !patientId || !caps?.followUp;
  $("print-followup-row").hidden = followLink.hidden;
  if (patientId) followLink.href = `#/follow-up/${encodeURIComponent(patientId)}`;
  $<HTMLInputElement>("print-followup").checked = false;
  $("report-followup").hidden = true;
  $("result").dataset.jobId = job.id;
  updateStale();
  $("download-sr").hidden = !caps?.srExport;
  $("download-figure-dcm").hidden = !caps?.figureDcm;
  $("download-fhir").hidden = !caps?.fhirExport;
  figureLoading = loadFigure(job.id);
}

/** The result's PA and lateral projections, over the PA film when the page has it and the result is
 * still of the films and landmarks on screen (a stale result's projection is not drawn over the film). */
function drawViews(job: Job): void {
  if (!job.result) return;
  const payload = sentPayload(job);
  if (!payload) return;
  const under = backdrop && payload.pa.units === "px" && !staleReasons(job).length ? backdrop : null;
  const { lateralFromImage } = drawProjections($("view-pa"), $("view-lateral"), job.result, payload, under);
  $("pa-caption").textContent = under ? " over the film" : " (detector mm)";
  $("lateral-caption").textContent = lateralFromImage ? "Lateral projection (detector mm)" : "Lateral projection of the model (anterior right)";
}

// ------------------------------------------------------------------ a result of other films or landmarks

/** The payloads this page sent, by job: the POST's answer has none (only GET /v1/jobs/{id} gives it). */
const sentPayloads = new Map<string, JobPayload>();

/** The payload job `job` was sent with: the service's copy, or this page's; null when neither is known. */
function sentPayload(job: Job): JobPayload | null {
  return job.payload ?? sentPayloads.get(job.id) ?? null;
}

/** The job's patient and study in words: "DOE JANE, ID PAT-0042, study date 2026-11-30". */
function jobPatientWords(job: Job): string {
  const study = job.study ?? job.payload?.study ?? sentPayloads.get(job.id)?.study ?? null;
  return [personName(study?.patient_name ?? undefined), study?.patient_id && `patient ID ${study.patient_id}`, study?.study_date && `study date ${study.study_date}`]
    .filter(Boolean).join(", ") || "no patient named";
}

/** Why the result of `job` is not of the films and landmarks on screen now (empty when it is theirs, or
 * when the page cannot tell: no payload known): other landmarks than the job's, or a film of another
 * patient or study than the job's. */
function staleReasons(job: Job): string[] {
  const payload = sentPayload(job);
  if (!payload) return [];
  const now = views();
  const keys = (view: ViewPayload | null | undefined): string => JSON.stringify((view?.landmarks ?? []).map(landmarkKey).sort());
  const out: string[] = [];
  if (keys(payload.pa) !== keys(now.pa) || keys(payload.lateral) !== keys(now.lateral)) {
    const where = source === "image" ? "on the films" : source === "csv" ? "of the CSV" : "of the payload";
    out.push(now.pa?.landmarks.length || now.lateral?.landmarks.length
      ? `sent with other landmarks than those ${where} now`
      : `sent with landmarks that are no longer ${where} (none now)`);
  }
  const study = job.study ?? payload.study ?? null;
  if (source === "image" && study) {
    for (const name of ["pa", "lateral"] as const) {
      const film = panels[name].dicom?.study;
      if (!film) continue;
      const words = name === "pa" ? "PA" : "lateral";
      if (film.patient_id && study.patient_id && film.patient_id !== study.patient_id) {
        const who = personName(film.patient_name ?? undefined);
        out.push(`the ${words} film now open is of another patient (patient ID ${film.patient_id}${who ? `, ${who}` : ""})`);
      } else if (film.study_instance_uid && study.study_instance_uid && film.study_instance_uid !== study.study_instance_uid) {
        out.push(`the ${words} film now open is of another study (${film.study_instance_uid})`);
      }
    }
  }
  return out;
}

/** Above the result: a notice, while the films or landmarks on screen are not those its job was sent
 * with (a polite live region, so that a screen reader hears it once it appears). */
const staleNotice = Object.assign(document.createElement("p"), { id: "result-stale", className: "stale-notice no-print" });
staleNotice.setAttribute("role", "status");
$("result").prepend(staleNotice);

/** Mark the result shown stale (`data-stale`, the notice, its PA projection no longer over the film) or
 * not, as the films and landmarks on screen now say; the mark goes with a new result or when the
 * landmarks are back to exactly the ones sent. */
function updateStale(): void {
  const box = $("result");
  const job = currentJob?.result && box.dataset.jobId === currentJob.id ? currentJob : null;
  const reasons = job ? staleReasons(job) : [];
  const was = box.dataset.stale === "true";
  if (!job) delete box.dataset.stale;
  else box.dataset.stale = String(reasons.length > 0);
  staleNotice.textContent = job && reasons.length
    ? `This result is of job ${job.id.slice(0, 8)} (${jobPatientWords(job)}), ${reasons.join("; ")}: Reconstruct again to see theirs. ` +
      "Its PA projection is not drawn over the film meanwhile."
    : "";
  if (job && was !== reasons.length > 0) drawViews(job);
}

function fillReportHead(job: Job): void {
  const study = job.study ?? job.payload?.study ?? null;
  const rows: [string, string][] = [
    ["Patient", [personName(study?.patient_name ?? undefined), study?.patient_id && `ID ${study.patient_id}`].filter(Boolean).join(", ") || "not given"],
    ["Study", [study?.study_date, study?.accession_number && `accession ${study.accession_number}`, study?.study_instance_uid && `UID ${study.study_instance_uid}`].filter(Boolean).join(", ") || "not given"],
    ["Job", `${job.id}, created ${new Date(job.created_at).toLocaleString()}${job.finished_at ? `, finished ${new Date(job.finished_at).toLocaleString()}` : ""}`],
    ["Engine", `${job.result?.engine.version ?? job.engine_version ?? "?"}, profile ${job.result?.engine.profile ?? "?"}`],
    ["Inputs", `${job.payload?.pa.landmarks.length ?? "?"} PA landmarks${job.payload?.lateral ? `, ${job.payload.lateral.landmarks.length} lateral` : ""}; T1 and L5 poses ${job.payload?.boundary ? "given" : "not given (estimated)"}`],
  ];
  $("report-meta").replaceChildren(...rows.flatMap(([k, v]) => {
    const dt = document.createElement("dt");
    dt.textContent = k;
    const dd = document.createElement("dd");
    dd.textContent = v;
    return [dt, dd];
  }));
}

/** The report's figure of the job shown, being fetched (settled once it is shown, or could not be). */
let figureLoading: Promise<void> = Promise.resolve();

/** Fetch the service's figure of job `id` for the printed report. The figure of the job shown before is
 * taken away first (a report printed meanwhile would carry another job's figure), and a figure arriving
 * after another job was opened is not shown. */
async function loadFigure(id: string): Promise<void> {
  const img = $<HTMLImageElement>("report-figure");
  img.removeAttribute("src");
  img.dataset.loaded = "pending";
  img.dataset.jobId = id;
  try {
    const blob = await api.blob(`/v1/jobs/${id}/figure.png`);
    if (img.dataset.jobId !== id) return;
    if (figureUrl) URL.revokeObjectURL(figureUrl);
    figureUrl = URL.createObjectURL(blob);
    img.src = figureUrl;
    await img.decode();
    if (img.dataset.jobId === id) img.dataset.loaded = "true";
  } catch {
    if (img.dataset.jobId === id) img.dataset.loaded = "false";
  }
}

/** How long "Print the report" waits for the figure still being fetched before printing without it (ms). */
const FIGURE_WAIT_MS = 15_000;

$("print-report").addEventListener("click", async () => {
  const button = $<HTMLButtonElement>("print-report");
  if ($("report-figure").dataset.loaded === "pending") {
    // printed at once, the report would go without its figure: wait for it (or for the time limit)
    button.disabled = true;
    button.textContent = "Waiting for the figure…";
    await Promise.race([figureLoading, new Promise((done) => window.setTimeout(done, FIGURE_WAIT_MS))]);
    button.disabled = false;
    button.textContent = "Print the report";
  }
  window.print();
});

// The printed report's follow-up table: the patient's visits and changes, fetched when asked for.
// An answer that arrives after the box was unticked, or another job was opened, is dropped: the report
// of one job never shows another patient's follow-up.
$<HTMLInputElement>("print-followup").addEventListener("change", async (e) => {
  const box = $("report-followup");
  const tick = e.target as HTMLInputElement;
  const job = currentJob;
  const patientId = (job?.study ?? job?.payload?.study)?.patient_id;
  box.hidden = true;
  box.replaceChildren();
  if (!tick.checked || !patientId) return;
  const stale = (): boolean => !tick.checked || currentJob?.id !== job?.id;
  try {
    const [data, others] = await Promise.all([api.followUp(patientId), notVisitJobs(patientId)]);
    if (stale()) return;
    const head = document.createElement("h3");
    head.textContent = `Follow-up of patient ${patientId}`;
    // the patient's queued, running and failed jobs, named as the follow-up view names them
    const waiting = others ? notVisitWords(data, others) : "Whether this patient has jobs still queued, running or failed (no visits) could not be asked of the service.";
    const notes = [undatedWords(data), data.older_visits_left_out ? "Older visits were left out: only the patient's newest 1,000 succeeded jobs are read." : null, waiting]
      .filter((t): t is string => !!t).map((t) => Object.assign(document.createElement("p"), { textContent: t }));
    if (waiting) notes[notes.length - 1].id = "report-followup-not-visits";
    const estimates = estimateNotes(data);
    box.replaceChildren(head, visitsTable(data, "Measures by study date (± one SD)"), ...(estimates ? [estimates] : []), ...notes,
      changesTable(data, `Changes between consecutive visits. ${RULE_WORDS}`));
    box.hidden = false;
  } catch (error) {
    if (error instanceof ApiError && !stale()) showProblem(problemBox, error.problem);
  }
});

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
  const v = views();
  if (v.pa || v.lateral) download("landmarks.csv", new Blob([landmarkCsv(v.pa?.landmarks ?? [], v.lateral?.landmarks ?? [])], { type: "text/csv" }));
});
$("download-json").addEventListener("click", () => {
  if (currentJob?.result) download(`spine-${currentJob.id}.json`, new Blob([JSON.stringify(currentJob.result, null, 2)], { type: "application/json" }));
});
$("download-csv").addEventListener("click", () => {
  if (currentJob?.result) download(`spine-${currentJob.id}.csv`, new Blob([resultCsv(currentJob.result)], { type: "text/csv" }));
});
$("download-measures").addEventListener("click", () => {
  if (!currentJob?.result) return;
  const study = currentJob.study ?? currentJob.payload?.study ?? null;
  const about: [string, string][] = [
    ["Patient", personName(study?.patient_name ?? undefined) || "not given"],
    ["Patient ID", study?.patient_id || "not given"],
    ["Study date", study?.study_date || "not given"],
    ["Job", currentJob.id],
  ];
  download(`spine-${currentJob.id}-measures.csv`, csvBlob(measuresCsv(measureRows(currentJob, currentJob.result), about)));
});
// The service's artifacts of the job: [button, path under /v1/jobs/{id}/, file name suffix, Accept].
const ARTIFACTS: [string, string, string, string | undefined][] = [
  ["download-sr", "sr.dcm", "-sr.dcm", "application/dicom"],
  ["download-figure-dcm", "figure.dcm", "-figure.dcm", "application/dicom"],
  ["download-fhir", "fhir", "-fhir.json", "application/fhir+json"],
];
for (const [button, path, suffix, accept] of ARTIFACTS) {
  $(button).addEventListener("click", async () => {
    if (!currentJob) return;
    try {
      download(`spine-${currentJob.id}${suffix}`, await api.blob(`/v1/jobs/${currentJob.id}/${path}`, accept));
    } catch (error) {
      if (error instanceof ApiError) showProblem(problemBox, error.problem);
    }
  });
}
for (const fmt of ["png", "svg"] as const) {
  $(`download-${fmt}`).addEventListener("click", async () => {
    if (!currentJob) return;
    try {
      download(`spine-${currentJob.id}.${fmt}`, await api.blob(`/v1/jobs/${currentJob.id}/figure.${fmt}`));
    } catch (error) {
      if (error instanceof ApiError) showProblem(problemBox, error.problem);
    }
  });
}
$("view-front").addEventListener("click", () => viewer?.setView("front"));
$("view-side").addEventListener("click", () => viewer?.setView("side"));
$("view-reset").addEventListener("click", () => viewer?.setView("reset"));

// ------------------------------------------------------------------ jobs list and routes

const jobsFilter = $<HTMLFormElement>("jobs-filter");
jobsFilter.addEventListener("submit", (e) => {
  e.preventDefault();
  void showJobs();
});

async function showJobs(): Promise<void> {
  caps ??= await capabilities();
  const note = $("jobs-note");
  const filters: Record<string, string> = {};
  const ignored: string[] = [];
  for (const input of jobsFilter.querySelectorAll<HTMLInputElement>("input")) {
    if (!input.value.trim()) continue;
    if (caps.jobFilters.has(input.name)) filters[input.name] = input.value;
    else ignored.push(input.labels?.[0]?.textContent ?? input.name);
  }
  note.textContent = ignored.length ? `This service cannot filter by ${ignored.join(", ")} yet: showing all jobs.` : "";
  showProblem($("jobs-problem"), null);
  const body = $<HTMLTableElement>("jobs-table").tBodies[0];
  body.replaceChildren();
  jobsPaging = { filters, cursor: null, note: note.textContent ?? "" };
  await moreJobs();
}

/** The jobs list's filters and the cursor of its next (older) page; null once the list is complete. */
let jobsPaging: { filters: Record<string, string>; cursor: string | null; note: string } | null = null;

/** The next page of the jobs list (the first when none is shown), appended; "Show older jobs" while
 * the service says older ones follow (`next_cursor`), so that no job is out of reach. */
async function moreJobs(): Promise<void> {
  const paging = jobsPaging;
  if (!paging) return;
  const body = $<HTMLTableElement>("jobs-table").tBodies[0];
  const more = $<HTMLButtonElement>("jobs-more");
  const note = $("jobs-note");
  more.disabled = true;
  try {
    const page = await api.jobs(paging.filters, JOBS_PAGE, paging.cursor);
    if (jobsPaging !== paging) return; // the list was asked for again meanwhile
    body.append(...page.jobs.map(jobRow));
    paging.cursor = page.next_cursor ?? null;
    more.hidden = !paging.cursor;
    const shown = body.rows.length;
    note.textContent = [
      paging.note,
      !shown ? "No job matches." : paging.cursor ? `The newest ${shown} jobs are shown: “Show older jobs” below the list adds the next ${JOBS_PAGE}.` : "",
    ].filter(Boolean).join(" ");
  } catch (error) {
    if (jobsPaging !== paging) return;
    more.hidden = true;
    showProblem($("jobs-problem"), problemOf(error));
  } finally {
    more.disabled = false;
  }
}

/** Jobs asked of the service at a time for the jobs list. */
const JOBS_PAGE = 50;
$("jobs-more").addEventListener("click", () => void moreJobs());

function jobRow(job: Job): HTMLTableRowElement {
  const tr = document.createElement("tr");
  const cell = (content: string | Node): HTMLTableCellElement => {
    const td = document.createElement("td");
    td.append(content);
    return td;
  };
  const link = document.createElement("a");
  link.href = `#/jobs/${job.id}`;
  link.textContent = job.id.slice(0, 8);
  link.setAttribute("aria-label", `Open job ${job.id}`);
  const s = job.study;
  const major = job.result?.measures.cobb.find((c) => c.major);
  tr.append(
    cell(link),
    cell(statusWords(job)),
    cell(new Date(job.created_at).toLocaleString()),
    cell([personName(s?.patient_name ?? undefined), s?.patient_id].filter(Boolean).join(", ") || "—"),
    cell([s?.accession_number, s?.study_instance_uid].filter(Boolean).join(" · ") || "—"),
    cell(major ? `${major.angle_deg.toFixed(1)}°${major.angle_sd_deg != null ? ` ± ${major.angle_sd_deg.toFixed(1)}°` : ""} (${major.upper}–${major.lower})` : "—"),
  );
  if (major && job.result?.fit.unreliable?.includes("cobb")) tr.lastElementChild?.append(" ", modelMark(COBB_ESTIMATE_REASON));
  return tr;
}

/** A job's status in the jobs list; a failed job's with why, in the words of its problem (the first
 * sentence `sentences` gives, as the job's own page says it). */
function statusWords(job: Job): string {
  if (job.status !== "failed" || !job.error) return job.status;
  const { lines } = sentences(job.error, job.payload);
  return `failed: ${lines[0] ?? job.error.title}`;
}

/** The job asked for last (its address): an earlier job's answer arriving after it is dropped. */
let openingJob: string | null = null;

/** The first read of a job opened by its address, waiting to ask the service again: "Check now" asks at once
 * (`now`), and opening or sending another job ends the wait (`stop`). */
let openRetry: { id: string; timer: number; now: () => void; stop: () => void } | null = null;

/** Wait `ms` before asking again for the job being opened; true: ask (the time is up, or "Check now"), false:
 * another job was opened or sent meanwhile. */
function waitToReopen(id: string, ms: number): Promise<boolean> {
  return new Promise((resolve) => {
    const end = (ask: boolean): void => {
      if (openRetry?.id === id) {
        window.clearTimeout(openRetry.timer);
        openRetry = null;
      }
      resolve(ask);
    };
    openRetry = { id, timer: window.setTimeout(() => end(true), ms), now: () => end(true), stop: () => end(false) };
  });
}

/** Reopen a job: its films' landmarks (from the stored payload) in the editors, its result. Its first read is
 * retried as the polling is (`poll`): without an answer, or with one that waiting may change (`transient`:
 * none, 408, 429, 5xx), it asks again 1 s later, doubling to at most 30 s or after the answer's Retry-After,
 * saying since when the service has not answered ("Check now" asks at once); 401, 403 and 404 stop it, the
 * problem shown. */
async function openJob(id: string): Promise<void> {
  openingJob = id;
  if (currentJob?.id === id) return;
  stopPolling();
  statusLine.textContent = `Opening job ${id}…`;
  const since = Date.now();
  let tries = 0;
  let job: Job;
  for (;;) {
    try {
      job = await api.job(id);
      break;
    } catch (error) {
      if (openingJob !== id) return;
      const problem = problemOf(error);
      if (!transient(problem.status)) {
        statusLine.dataset.tracking = "stopped";
        checkButton.hidden = true;
        statusLine.textContent = `Job ${id} could not be opened: ${finalWhy(problem)}, which waiting will not change (the problem is shown below).`;
        showProblem(problemBox, problem);
        return;
      }
      tries += 1;
      const wait = retryDelay(tries, error instanceof ApiError ? error.retryAfterMs : null);
      const last = problem.status ? `HTTP ${problem.status}, ${problem.detail || problem.title}` : problem.detail || problem.title;
      statusLine.dataset.tracking = "retrying";
      statusLine.textContent = `Opening job ${id}: the service has not answered since ${clock(since)} (${tries} ${tries === 1 ? "try" : "tries"}; the last: ${last}). ` +
        `The job is kept by the service. The page asks again at ${clock(Date.now() + wait)}, or at once with “Check now”.`;
      checkButton.hidden = false;
      if (!(await waitToReopen(id, wait)) || openingJob !== id) return;
    }
  }
  if (openingJob !== id) return; // another job was asked for meanwhile
  checkButton.hidden = true;
  delete statusLine.dataset.tracking;
  try {
    backdrop = null;
    showProblem(problemBox, null); // another job's refusal or failure is not this one's
    if (job.payload) {
      // Exactly the job's payload: both panels and the draft are reset to it, whatever was open before.
      const p = job.payload;
      draft = null;
      // the job's film as its payload's study names it, or the header values the service read for it
      const study: Partial<Study> | null = p.study || job.study ? { ...job.study, ...p.study } : null;
      const film = (sop: string | null | undefined): JobFilm | null =>
        study ? { sop_instance_uid: sop, study_instance_uid: study.study_instance_uid, patient_id: study.patient_id } : null;
      panels.pa.restore(p.pa, film(study?.pa_sop_instance_uid));
      if (p.lateral) panels.lateral.restore(p.lateral, film(study?.lateral_sop_instance_uid));
      else panels.lateral.reset();
      reopenedJob = { ...(p.study ? { study: p.study } : {}), ...(p.options !== undefined ? { options: p.options } : {}) };
      void reopenFilms(job);
      source = "image";
      applyBoundary(p.boundary);
      selectSourceTab($<HTMLButtonElement>("tab-image"), false);
      draftChanged();
    }
    track(job);
  } catch (error) {
    if (openingJob !== id) return;
    statusLine.textContent = `Job ${id} could not be opened.`;
    showProblem(problemBox, problemOf(error));
  }
}

// ------------------------------------------------------------------ follow-up

const followForm = $<HTMLFormElement>("followup-form");
const followInput = $<HTMLInputElement>("followup-patient");
followForm.addEventListener("submit", (e) => {
  e.preventDefault();
  const value = followInput.value.trim();
  if (value) location.hash = `#/follow-up/${encodeURIComponent(value)}`;
});

const UUID = /^[0-9a-fA-F]{8}-[0-9a-fA-F]{4}-[0-9a-fA-F]{4}-[0-9a-fA-F]{4}-[0-9a-fA-F]{12}$/;

/** The patient's queued, running and failed jobs (no visits), when the service filters jobs by patient ID:
 * [] when it does not (nothing to say), null when they could not be listed (the follow-up says so). */
async function notVisitJobs(patientId: string): Promise<Job[] | null> {
  caps ??= await capabilities();
  if (!caps.jobFilters.has("patient_id")) return [];
  try {
    return (await api.jobs({ patient_id: patientId, status: ["queued", "running", "failed"] }, 100)).jobs;
  } catch {
    return null;
  }
}

/** The follow-up asked for last: an answer to an earlier request that arrives after it is dropped. */
let followRequest = 0;

/** The follow-up of a patient ID, or of a job's patient when given a job ID; with the patient's jobs that
 * are not visits (queued, running, failed) when the service filters jobs by patient ID. */
async function showFollowUp(idOrJob: string): Promise<void> {
  const box = $("followup");
  const problem = $("followup-problem");
  const request = ++followRequest;
  showProblem(problem, null);
  box.replaceChildren();
  delete box.dataset.patient;
  followInput.value = idOrJob;
  if (!idOrJob) return;
  try {
    let patientId = idOrJob;
    if (UUID.test(idOrJob)) {
      const job = await api.job(idOrJob);
      if (request !== followRequest) return;
      const pid = (job.study ?? job.payload?.study)?.patient_id;
      if (!pid) {
        showProblem(problem, { type: "about:blank", title: "No patient", status: 0, detail: `Job ${idOrJob} names no patient: its payload and films gave no Patient ID.` });
        return;
      }
      patientId = pid;
    }
    const [data, others] = await Promise.all([api.followUp(patientId), notVisitJobs(patientId)]);
    if (request !== followRequest) return;
    fillFollowUp(box, data, others);
    box.dataset.patient = patientId;
  } catch (error) {
    if (request !== followRequest) return;
    showProblem(problem, problemOf(error));
  }
}

/** A reopened job's films fetched again from the PACS when it named them by UID; else why not, in place. */
async function reopenFilms(job: Job): Promise<void> {
  caps ??= await capabilities();
  const study = job.payload?.study;
  for (const view of ["pa", "lateral"] as const) {
    const landmarks = view === "pa" ? job.payload?.pa : job.payload?.lateral;
    const sop = view === "pa" ? study?.pa_sop_instance_uid : study?.lateral_sop_instance_uid;
    const uid = study?.study_instance_uid;
    if (!landmarks || !uid || !sop) continue; // not from the PACS: restore() said so
    const panel = panels[view];
    const blank = "The landmarks are shown on a blank frame; open the film to see it under them.";
    const noPacs = `Not stored by the service, and this service has no PACS to fetch it from again (image ${sop} of study ${uid}). ${blank}`;
    if (!caps?.pacsRoutes) {
      panel.explainBlank(noPacs);
      continue;
    }
    if (panel.reopenedInMm()) {
      panel.explainBlank(`The landmarks are in mm without a pixel spacing, so their place on the film (image ${sop} of study ${uid}) is unknown: they are shown on a blank frame (1 px = 1 mm), not over the film.`);
      continue;
    }
    panel.explainBlank(`Fetching the film (image ${sop}) from the PACS…`);
    // A film opened by hand meanwhile (or being read), or the panel closed: the PACS's film does not
    // replace it (its landmarks would go with it), and no note of the fetch covers its header.
    const handled = (): boolean => !!panel.editor.source || !!panel.editor.loading || !panel.reopened;
    try {
      const file = await pacs.fetchFilm(uid, sop);
      if (currentJob?.id !== job.id) return; // another job was opened meanwhile
      if (handled()) continue;
      await panel.open(file);
      if (view === "pa" && currentJob?.id === job.id) {
        if (backdrop) URL.revokeObjectURL(backdrop.url);
        backdrop = await panel.backdrop(); // the result's PA projection over the film again
        if (currentJob.result) drawViews(currentJob);
      }
    } catch (error) {
      if (currentJob?.id !== job.id) return;
      if (handled()) continue;
      if (error instanceof NoPacs) panel.explainBlank(noPacs);
      else panel.explainBlank(`The film is image ${sop} of study ${uid} in the PACS, but it could not be fetched again: ${error instanceof Error ? error.message : String(error)}. ${blank}`);
    }
  }
}

function route(): void {
  const hash = location.hash.replace(/^#/, "");
  const jobsPage = hash === "/jobs";
  const followMatch = hash.match(/^\/follow-up(?:\/(.*))?$/);
  $("page-jobs").hidden = !jobsPage;
  $("page-follow-up").hidden = !followMatch;
  $("page-job").hidden = jobsPage || !!followMatch;
  document.querySelectorAll<HTMLAnchorElement>(".site-nav a").forEach((a) => {
    const href = a.getAttribute("href");
    const here = href === `#${hash}` || (href === "#/follow-up" && !!followMatch) || (href === "#/" && !jobsPage && !followMatch && !hash.startsWith("/jobs/"));
    if (here) a.setAttribute("aria-current", "page");
    else a.removeAttribute("aria-current");
  });
  if (jobsPage) void showJobs();
  if (followMatch) void showFollowUp(decodeURIComponent(followMatch[1] ?? ""));
  const m = hash.match(/^\/jobs\/([0-9a-fA-F-]{36})$/);
  if (m) void openJob(m[1]);
}
window.addEventListener("hashchange", route);

setBoundary(defaultBoundary());
setGiveBoundary(false);
selectFilmTab($<HTMLButtonElement>("tab-film-pa"), false);
draftChanged();
void capabilities().then((c) => {
  caps = c;
  draftChanged();
  if (apiKeyInput.value.trim()) void pacs.refresh(c.pacsRoutes);
});
route();
document.body.dataset.ready = "true";

// The Follow-up view: a patient's visits by study date (GET /v1/patients/{id}/measures: one per study
// among the key's succeeded jobs, its latest job standing for it), the measures with their ±, each
// change between consecutive visits (flagged beyond both 5° and 1.96 × the combined SD, with the rule
// that decided), and one small plot per measure over time (the value with its 95 % interval, ±1.96 SD;
// a flagged change drawn in red). A visit without a study date has no place on the time axis: it is in
// the table, left out of the plots and changes, and the page says so. A value that comes from the spine
// model's prior rather than the films (`model_estimate`, the reason in words) carries the result view's
// "model estimate" mark with the reason as its tooltip and in a note under the table, is drawn hollow in
// its plot, and a change involving it says that it compares model estimates: a flagged progression
// between model estimates is not a measured progression.
import { MODEL_MARK, modelMark, withSd } from "./results";
import type { Job } from "./types";

export type MeasureName = "major_cobb" | "minor_cobb" | "kyphosis_t4_t12" | "lordosis_l1_l5" | "apex_axial_rotation";

export interface MeasureValue {
  value_deg: number;
  sd_deg: number | null;
  levels: string | null;
  /** Why the value comes from the spine model's prior rather than the films (the job's fit.unreliable or
   * fit.assumed in words, as the SR and FHIR say it); null when the films determine it; absent from older services. */
  model_estimate?: string | null;
}

export interface Visit {
  job_id: string;
  study_date: string | null;
  study_instance_uid: string | null;
  accession_number: string | null;
  finished_at: string | null;
  major_cobb: MeasureValue | null;
  minor_cobb: MeasureValue | null;
  kyphosis_t4_t12: MeasureValue;
  lordosis_l1_l5: MeasureValue;
  apex_axial_rotation: MeasureValue | null;
}

export interface Change {
  measure: MeasureName;
  from_job: string;
  to_job: string;
  from_date: string;
  to_date: string;
  change_deg: number;
  combined_sd_deg: number | null;
  threshold_deg: number;
  flagged: boolean;
  decided_by: "convention_5deg" | "combined_sd";
}

export interface PatientMeasures {
  patient_id: string;
  visits: Visit[];
  changes: Change[];
  rule: string;
  /** Older visits were left out: only the newest succeeded jobs are read (absent from older services). */
  older_visits_left_out?: boolean;
}

export const MEASURE_NAMES: Record<MeasureName, string> = {
  major_cobb: "Major Cobb",
  minor_cobb: "Minor Cobb",
  kyphosis_t4_t12: "Kyphosis T4–T12",
  lordosis_l1_l5: "Lordosis L1–L5",
  apex_axial_rotation: "Apex axial rotation",
};
const ORDER = Object.keys(MEASURE_NAMES) as MeasureName[];

/** The sign convention of each signed measure, in the result view's words (results.ts); a Cobb angle is a
 * magnitude. A signed value or change means nothing to its reader without it. */
export const SIGNS: Partial<Record<MeasureName, string>> = {
  kyphosis_t4_t12: "positive: convex posteriorly",
  lordosis_l1_l5: "positive: convex anteriorly",
  apex_axial_rotation: "positive: toward the patient's left, seen from above",
};

/** The flagging rule, as the page words it (the API's `rule` names its own fields). */
export const RULE_WORDS = "A change between consecutive visits is flagged when it exceeds both 5° (the convention for progression) " +
  "and 1.96 × √(sd₁² + sd₂²) (the 95 % interval of the difference of two measures with their SDs); “Decided by” names the larger of the two thresholds.";

/** Degrees with one decimal and a sign, never "-0.0". */
const signed = (x: number): string => {
  const r = Math.round(x * 10) / 10;
  return `${r > 0 ? "+" : ""}${(r === 0 ? 0 : r).toFixed(1)}°`;
};

/** A plot tick's value: whole degrees, 0 for anything that rounds to zero (never "-0"). */
export const wholeDegrees = (v: number): number => Math.round(v) || 0;

const el = <K extends keyof HTMLElementTagNameMap>(tag: K, text?: string, cls?: string): HTMLElementTagNameMap[K] => {
  const node = document.createElement(tag);
  if (text !== undefined) node.textContent = text;
  if (cls) node.className = cls;
  return node;
};

function cell(m: MeasureValue | null): string {
  if (!m) return "—";
  return `${withSd(m.value_deg, m.sd_deg)}${m.levels ? ` (${m.levels})` : ""}`;
}

/** A visit in words: its study date, with its job when another visit has the same date (or none). */
const visitName = (v: Visit, visits: Visit[]): string =>
  v.study_date === null ? `job ${v.job_id.slice(0, 8)} (no study date)`
    : visits.some((o) => o !== v && o.study_date === v.study_date) ? `${v.study_date} (job ${v.job_id.slice(0, 8)})` : v.study_date;

/** The two visits of a change: their study dates; two visits of one study date are told apart by their
 * jobs, and said to be of one day (a difference between two studies of one day is not a progression). */
export function between(c: Change): string {
  if (c.from_date !== c.to_date) return `${c.from_date} → ${c.to_date}`;
  return `${c.from_date} (job ${c.from_job.slice(0, 8)}) → ${c.to_date} (job ${c.to_job.slice(0, 8)}), same day: not a progression over time`;
}

/** The model-estimated values of a change's two visits: which visit, and why; empty when both are measured. */
export function changeEstimates(data: PatientMeasures, c: Change): { visit: Visit; reason: string }[] {
  return [c.from_job, c.to_job].flatMap((id) => {
    const visit = data.visits.find((v) => v.job_id === id);
    const reason = visit?.[c.measure]?.model_estimate;
    return visit && reason ? [{ visit, reason }] : [];
  });
}

/** "compares model estimates" (both values) or "compares a model estimate" (one); null when both are measured. */
export function changeEstimateWords(data: PatientMeasures, c: Change): string | null {
  const n = changeEstimates(data, c).length;
  return n ? (n > 1 ? "compares model estimates" : "compares a model estimate") : null;
}

/** The model estimates of the visits table in words, one item per reason: which measures of which visits
 * (the print shows no tooltip, and a screen reader may not read it); null when every value is measured. */
export function estimateNotes(data: PatientMeasures): HTMLElement | null {
  const byReason = new Map<string, Map<MeasureName, string[]>>();
  for (const v of data.visits) {
    for (const k of ORDER) {
      const reason = v[k]?.model_estimate;
      if (!reason) continue;
      const measures = byReason.get(reason) ?? new Map<MeasureName, string[]>();
      measures.set(k, [...(measures.get(k) ?? []), visitName(v, data.visits)]);
      byReason.set(reason, measures);
    }
  }
  if (!byReason.size) return null;
  const box = el("div", undefined, "followup-estimates help");
  const head = el("p");
  head.append(modelMark(), " values come from the spine model's prior, not from the films; a change involving one compares model estimates, not measures:");
  const list = el("ul");
  for (const [reason, measures] of byReason) {
    const where = [...measures].map(([k, visits]) => `${MEASURE_NAMES[k]} of ${visits.join(", ")}`);
    list.append(el("li", `${where.join("; ")}: ${reason}.`));
  }
  box.append(head, list);
  return box;
}

/** The visits table: one row per visit (the job that stands for it linked), by study date, undated last. */
export function visitsTable(data: PatientMeasures, caption: string): HTMLTableElement {
  const table = el("table", undefined, "data followup-visits");
  table.createCaption().textContent = caption;
  const head = table.createTHead().insertRow();
  for (const h of ["Study date", "Job", ...ORDER]) {
    const k = ORDER.find((m) => m === h);
    const th = el("th", k ? MEASURE_NAMES[k] : h);
    const sign = k && SIGNS[k];
    if (sign) th.append(" ", el("span", `(${sign})`, "th-note"));
    th.scope = "col";
    head.append(th);
  }
  const body = table.createTBody();
  for (const v of data.visits) {
    const tr = body.insertRow();
    const link = el("a", v.job_id.slice(0, 8));
    link.href = `#/jobs/${v.job_id}`;
    link.setAttribute("aria-label", `Open job ${v.job_id}`);
    const date = el("th", v.study_date ?? "no study date: not on the time axis");
    date.scope = "row";
    tr.append(date);
    tr.insertCell().append(link);
    for (const k of ORDER) {
      const td = tr.insertCell();
      td.textContent = cell(v[k]);
      const reason = v[k]?.model_estimate;
      if (reason) {
        td.className = "is-model";
        td.dataset.measure = k;
        td.append(" ", modelMark(reason));
      }
    }
  }
  return table;
}

/** The changes table: per measure and pair of consecutive visits, flagged or not and why. */
export function changesTable(data: PatientMeasures, caption: string): HTMLTableElement {
  const table = el("table", undefined, "data followup-changes");
  table.createCaption().textContent = caption;
  const head = table.createTHead().insertRow();
  for (const h of ["Measure", "Between", "Change", "Threshold", "Verdict", "Decided by"]) {
    const th = el("th", h);
    th.scope = "col";
    head.append(th);
  }
  const body = table.createTBody();
  for (const c of data.changes) {
    const tr = body.insertRow();
    tr.dataset.measure = c.measure;
    tr.dataset.flagged = String(c.flagged);
    if (c.flagged) tr.className = "flagged";
    const name = el("th", MEASURE_NAMES[c.measure]);
    name.scope = "row";
    tr.append(name);
    tr.insertCell().textContent = between(c);
    if (c.from_date === c.to_date) tr.dataset.sameDay = "true";
    const change = tr.insertCell();
    change.textContent = signed(c.change_deg);
    const estimates = changeEstimates(data, c);
    const words = changeEstimateWords(data, c);
    if (words) {
      tr.dataset.modelEstimate = "true";
      const note = el("span", words, "model-mark");
      note.title = `${estimates.map((e) => `The ${visitName(e.visit, data.visits)} value is a model estimate: ${e.reason}.`).join(" ")} ` +
        (c.flagged ? "The flag is not a measured progression." : "The change is not a measured one.");
      change.append(" ", note);
    }
    tr.insertCell().textContent = `${c.threshold_deg.toFixed(1)}°`;
    tr.insertCell().textContent = c.flagged ? "⚠ exceeds both rules" : "within";
    tr.insertCell().textContent = c.decided_by === "combined_sd"
      ? `1.96 × combined SD (${c.combined_sd_deg?.toFixed(1)}°) = ${c.threshold_deg.toFixed(1)}° > 5°`
      : `5° convention${c.combined_sd_deg != null ? ` (1.96 × combined SD ${c.combined_sd_deg.toFixed(1)}° = ${(1.96 * c.combined_sd_deg).toFixed(1)}° is less)` : " (no SD)"}`;
  }
  return table;
}

const SVG = "http://www.w3.org/2000/svg";
function svg<K extends keyof SVGElementTagNameMap>(tag: K, attrs: Record<string, string | number>): SVGElementTagNameMap[K] {
  const node = document.createElementNS(SVG, tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, String(v));
  return node;
}

/** CSS px between the points of visits of one study date, drawn side by side around their date. */
export const SAME_DAY_PX = 8;

/** One small plot of a measure over time: points with ±1.96 SD bars, flagged changes in red. Visits of
 * one study date are drawn side by side, SAME_DAY_PX apart and centred on their date (the date's tick
 * stays at the date), each point named by its job in its tooltip and in the plot's description. */
export function measurePlot(data: PatientMeasures, name: MeasureName): SVGSVGElement | null {
  const dated = data.visits.filter((v) => v.study_date && v[name]);
  const points = dated.map((v) => {
    const m = v[name] as MeasureValue;
    const day = dated.filter((o) => o.study_date === v.study_date);
    const dx = (day.indexOf(v) - (day.length - 1) / 2) * SAME_DAY_PX;
    return { t: Date.parse(v.study_date as string), m, job: v.job_id, dx, label: visitName(v, data.visits) };
  });
  if (!points.length) return null;
  const sameDay = points.some((p) => p.dx !== 0);
  // a model estimate is drawn hollow; a plot with one has a legend row under its title
  const estimated = points.some((p) => p.m.model_estimate);
  const legend = estimated ? 14 : 0;
  const W = 260;
  const H = 140 + legend;
  const pad = { l: 40, r: 10, t: 22 + legend, b: 24 };
  const lo = Math.min(...points.map((p) => p.m.value_deg - 1.96 * (p.m.sd_deg ?? 0)));
  const hi = Math.max(...points.map((p) => p.m.value_deg + 1.96 * (p.m.sd_deg ?? 0)));
  const span = Math.max(hi - lo, 5);
  const [y0, y1] = [lo - span * 0.1, lo + span * 1.1];
  const [t0, t1] = [points[0].t, points[points.length - 1].t];
  const x = (t: number): number => pad.l + (t1 > t0 ? ((t - t0) / (t1 - t0)) * (W - pad.l - pad.r) : (W - pad.l - pad.r) / 2);
  const y = (v: number): number => H - pad.b - ((v - y0) / (y1 - y0)) * (H - pad.t - pad.b);
  const root = svg("svg", { viewBox: `0 0 ${W} ${H}`, width: W, height: H, role: "img", class: "followup-plot" });
  root.dataset.measure = name;
  const flagged = data.changes.filter((c) => c.measure === name && c.flagged);
  const words = (p: (typeof points)[number]): string => `${p.label} ${withSd(p.m.value_deg, p.m.sd_deg)}${p.m.model_estimate ? ` (${MODEL_MARK})` : ""}`;
  root.setAttribute("aria-label", `${MEASURE_NAMES[name]}${SIGNS[name] ? ` (${SIGNS[name]})` : ""} over time: ${points.map(words).join(", ")}` +
    `${flagged.length ? `; ${flagged.length} flagged change${flagged.length > 1 ? "s" : ""}` : ""}` +
    `${sameDay ? `; visits of one study date are drawn side by side at that date, ${SAME_DAY_PX} px apart, in the table's order` : ""}.`);
  const title = svg("text", { x: pad.l, y: 14, class: "plot-title" });
  title.textContent = `${MEASURE_NAMES[name]} (°)`;
  root.append(title, svg("line", { x1: pad.l, y1: H - pad.b, x2: W - pad.r, y2: H - pad.b, class: "axis" }),
    svg("line", { x1: pad.l, y1: pad.t, x2: pad.l, y2: H - pad.b, class: "axis" }));
  if (estimated) {
    const key = svg("g", { class: "plot-legend", "aria-hidden": "true" });
    const entry = (cx: number, cls: string, words: string): void => {
      const label = svg("text", { x: cx + 7, y: 30, class: "tick" });
      label.textContent = words;
      key.append(svg("circle", { cx, cy: 27, r: 3.5, class: cls }), label);
    };
    const measured = points.some((p) => !p.m.model_estimate);
    if (measured) entry(pad.l + 4, "point", "from the films");
    entry(pad.l + (measured ? 84 : 4), "point model-estimate", MODEL_MARK);
    root.append(key);
  }
  // two ticks at whole degrees near 10 % and 90 % of the axis, each drawn at its own value
  for (const v of [y0 + (y1 - y0) * 0.1, y0 + (y1 - y0) * 0.9].map(wholeDegrees)) {
    const tick = svg("text", { x: pad.l - 4, y: y(v) + 4, class: "tick y-tick", "text-anchor": "end" });
    tick.textContent = `${v}°`;
    root.append(tick);
  }
  // the first and last study dates (the day: visits months apart, or on one day, must be told apart)
  const ends = t1 > t0 ? [points[0], points[points.length - 1]] : [points[0]];
  for (const [i, p] of ends.entries()) {
    const label = svg("text", { x: x(p.t), y: H - 8, class: "tick date-tick", "text-anchor": ends.length === 1 ? "middle" : i ? "end" : "start" });
    label.textContent = new Date(p.t).toISOString().slice(0, 10);
    root.append(label);
  }
  for (let i = 1; i < points.length; i++) {
    const [a, b] = [points[i - 1], points[i]];
    const red = flagged.some((c) => c.from_job === a.job && c.to_job === b.job);
    root.append(svg("line", { x1: x(a.t) + a.dx, y1: y(a.m.value_deg), x2: x(b.t) + b.dx, y2: y(b.m.value_deg), class: red ? "trend flagged" : "trend" }));
  }
  for (const p of points) {
    const sd = p.m.sd_deg ?? 0;
    const cx = x(p.t) + p.dx;
    const point = svg("circle", { cx, cy: y(p.m.value_deg), r: 3.5, class: p.m.model_estimate ? "point model-estimate" : "point" });
    point.dataset.job = p.job;
    const tip = svg("title", {});
    tip.textContent = words(p);
    point.append(tip);
    root.append(svg("line", { x1: cx, y1: y(p.m.value_deg - 1.96 * sd), x2: cx, y2: y(p.m.value_deg + 1.96 * sd), class: "bar" }), point);
  }
  return root;
}

/** Why visits without a study date are not on the time axis, in words; null when every visit has one. */
export function undatedWords(data: PatientMeasures): string | null {
  const undated = data.visits.filter((v) => !v.study_date);
  if (!undated.length) return null;
  const one = undated.length === 1;
  const which = undated.map((v) => `job ${v.job_id.slice(0, 8)}${v.study_instance_uid ? ` (study ${v.study_instance_uid})` : ""}`).join(", ");
  return `${one ? "One visit has" : `${undated.length} visits have`} no study date: ${which}. ${one ? "It is" : "They are"} left out of the time axis — the plots and the changes between visits — because neither the films' Study Date (0008,0020) nor the payload's study_date says when ${one ? "it was" : "they were"} filmed, so ${one ? "its" : "their"} place between the other visits is unknown. ${one ? "Its" : "Their"} measures are in the table, last.`;
}

/** The patient's jobs that are not visits because they have not succeeded (queued or running: not yet;
 * failed: never), in words, each with its study date and whether its study is already a visit (a new
 * reading of it); null when there are none. Cancelled jobs were stopped on purpose and are not named. */
export function notVisitWords(data: PatientMeasures, jobs: Job[]): string | null {
  const left = jobs.filter((j) => (j.status === "queued" || j.status === "running" || j.status === "failed")
    && !data.visits.some((v) => v.job_id === j.id));
  if (!left.length) return null;
  const words = left.map((j) => {
    const study = j.study ?? j.payload?.study ?? null;
    const state = j.status === "failed" ? "failed" : `is still ${j.status}`;
    const visit = study?.study_instance_uid ? data.visits.find((v) => v.study_instance_uid === study.study_instance_uid) : undefined;
    const of = visit ? `, a new reading of the ${visit.study_date ?? "undated"} visit's study` : "";
    return `job ${j.id.slice(0, 8)} (${study?.study_date ? `study date ${study.study_date}` : "no study date"}${of}) ${state}`;
  });
  const n = left.length;
  return `${n === 1 ? "One job" : `${n} jobs`} of this patient ${n === 1 ? "is" : "are"} not in the follow-up, which counts succeeded jobs only: ${words.join("; ")}. ` +
    "A running job's visit appears when it succeeds (reload); a failed job's study is a visit only once it is sent again and succeeds.";
}

/** A flagged change in the summary: "Major Cobb +8.0° (2025-01-10 → 2025-07-08)", and whether it compares model estimates. */
function flaggedWords(data: PatientMeasures, c: Change): string {
  const estimates = changeEstimateWords(data, c);
  return `${MEASURE_NAMES[c.measure]} ${signed(c.change_deg)} (${between(c)}${estimates ? `, ${estimates}` : ""})`;
}

/** Fill the Follow-up view: summary, the patient's jobs that are not visits (`jobs`: their queued, running
 * and failed ones; null: they could not be listed), visits, changes, plots. */
export function fillFollowUp(container: HTMLElement, data: PatientMeasures, jobs: Job[] | null = []): void {
  const flagged = data.changes.filter((c) => c.flagged);
  const n = data.visits.length;
  const summary = el("p", n
    ? `${n} visit${n > 1 ? "s" : ""} of patient ${data.patient_id}; ${flagged.length ? `${flagged.length} change${flagged.length > 1 ? "s" : ""} flagged: ${flagged.map((c) => flaggedWords(data, c)).join("; ")}` : "no change flagged"}.`
    : `No visit of patient ${data.patient_id}: no succeeded job of this patient with this API key.`, "summary");
  summary.id = "followup-summary";
  const notes: HTMLElement[] = [];
  const undated = undatedWords(data);
  if (undated) notes.push(Object.assign(el("p", undated, "warning"), { id: "followup-undated" }));
  const waiting = jobs ? notVisitWords(data, jobs) : "Whether this patient has jobs still queued, running or failed (no visits) could not be asked of the service.";
  if (waiting) notes.push(Object.assign(el("p", waiting, "warning"), { id: "followup-not-visits" }));
  if (data.older_visits_left_out) {
    // the service reads the newest MAX_PATIENT_JOBS (services/db/jobs.py) succeeded jobs
    notes.push(Object.assign(el("p", "Older visits were left out: only the patient's newest 1,000 succeeded jobs are read.", "warning"), { id: "followup-older" }));
  }
  const rule = el("p", RULE_WORDS, "help");
  const scroll = (table: HTMLTableElement, id: string): HTMLElement => {
    const div = el("div", undefined, "table-scroll");
    div.tabIndex = 0;
    div.setAttribute("role", "region");
    table.caption!.id = `${id}-caption`;
    div.setAttribute("aria-labelledby", `${id}-caption`);
    div.append(table);
    return div;
  };
  const plots = el("div", undefined, "followup-plots");
  for (const name of ORDER) {
    const plot = measurePlot(data, name);
    if (plot) plots.append(plot);
  }
  container.replaceChildren(summary, ...notes, rule);
  if (!data.visits.length) return;
  const estimates = estimateNotes(data);
  container.append(
    scroll(visitsTable(data, `Patient ${data.patient_id}: measures by study date (± one SD)`), "followup-visits"),
    ...(estimates ? [estimates] : []),
    scroll(changesTable(data, "Changes between consecutive visits"), "followup-changes"),
    plots,
  );
}

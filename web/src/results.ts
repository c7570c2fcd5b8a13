// The result's tables (clinical measures, Lenke inputs, strains per vertebra) and the colour
// legend. Every number with its trust: ± one SD where the result gives one, and a visible
// "model estimate" mark on the quantities listed in fit.unreliable (they come from the model's
// prior, not from the landmarks).
import { bendingLimit, gradientCss } from "./colors";
import { frontalBending, LEVELS, sagittalBending, type CobbCurve, type Job, type RegistrationResult } from "./types";

export const MODEL_MARK = "model estimate";

/** Why the frontal Cobb angles are model estimates when fit.unreliable lists `cobb`: the sentence of
 * services/core/estimates.py `model_estimate_reason(fit, "cobb")` (docs/measures.md). */
export const COBB_ESTIMATE_REASON = "the PA film's landmarks do not reach every level from T1 to L5 (two or more levels in a " +
  "row without one), or a Cobb angle's standard deviation exceeds half the population's: the frontal Cobb angles depend " +
  "on the spine model's prior where no landmark is, and each such angle's SD is at least the population's " +
  "(fit.unreliable: cobb)";

const MARK_TITLE = "From the model's prior, not from the landmarks: do not read it as measured.";

const num = (x: number | null | undefined, digits = 1): string => (x === null || x === undefined || !Number.isFinite(x) ? "—" : x.toFixed(digits));

/** "12.3° ± 1.4°" with a SD, "12.3°" without. */
export function withSd(value: number | null | undefined, sd: number | null | undefined, unit = "°", digits = 1): string {
  const v = `${num(value, digits)}${unit}`;
  return sd === null || sd === undefined || !Number.isFinite(sd) ? v : `${v} ± ${num(sd, digits)}${unit}`;
}

export function unreliable(result: RegistrationResult): Set<string> {
  return new Set(result.fit.unreliable ?? []);
}


/** The visible "model estimate" mark; `reason` (why the films leave it to the prior) goes in its tooltip. */
export function modelMark(reason?: string): HTMLElement {
  const s = document.createElement("span");
  s.className = "model-mark";
  s.textContent = MODEL_MARK;
  s.title = reason ? `From the model's prior: ${reason}.` : MARK_TITLE;
  return s;
}
const mark = modelMark;

/** Where a curve's apex is: its apical vertebra ("T8"), or for a curve of one segment the SRS apical disc
 * between `apex` and the vertebra below it ("T8/T9 disc", `apical_disc`, docs/measures.md). */
export function apexWords(curve: Pick<CobbCurve, "apex" | "apical_disc">): string {
  const below = LEVELS[LEVELS.indexOf(curve.apex) + 1];
  return curve.apical_disc && below ? `${curve.apex}/${below} disc` : curve.apex;
}

/** A measure as a number, for the measures CSV's `value`, `sd` and `unit` columns (the CLI's names and units,
 * spine_client/tables.py `MEASURE_COLUMNS`: deg, mm; empty for a factor); null where the result gives none. */
export interface Amount {
  value: number | null | undefined;
  sd?: number | null;
  unit: string;
}

export interface MeasureRow {
  name: string;
  value: string;
  model: boolean;
  note?: string;
  /** Why the value is a model estimate, where the page says more than the general mark. */
  reason?: string;
  /** The value as a number with its SD (the CSV); absent where the value is words ("none of 10° or more"). */
  amount?: Amount;
  /** Rows of the CSV only: further numbers the value's words hold (the Cobb angle in the plane of maximum curvature). */
  more?: MeasureRow[];
}

/** What each of fit.assumed's names says in a few words (spine_engine/models.py `AssumptionName`); its
 * `reason` says the rest. A name a newer service adds (the list is an extensible enum) is shown as written. */
const ASSUMED: Record<string, string> = {
  central_ray_at_image_centre: "central ray at the image's centre",
  central_ray_near_landmarks: "central ray near the landmarks",
  magnification_prior: "magnification of full-spine radiography",
  standing_orientation: "a standing patient facing the detector",
  population_sagittal_shape: "the population's sagittal shape",
  full_spine_geometry: "the geometry of full-spine radiography",
  population_axial_rotation: "the population's axial rotation",
  projection_unstated: "projection not stated: perspective read from the films",
};

/** The measures as rows of words (the page's table, the printed report and the CSV share them). */
export function measureRows(job: Job, result: RegistrationResult): MeasureRow[] {
  const m = result.measures;
  const u = unreliable(result);
  const rows: MeasureRow[] = [];
  const byLevel = new Map(result.vertebrae.map((v) => [v.level, v]));
  // Every frontal Cobb angle (the curves', the largest angle, whether any reaches 10°) is the prior's when fit.unreliable lists cobb.
  const cobb = u.has("cobb");
  const cobbReason = cobb ? COBB_ESTIMATE_REASON : undefined;
  if (!m.cobb.length) rows.push({ name: "Frontal curves", value: "none of 10° or more", model: cobb, reason: cobbReason });
  const largest = m.largest_cobb;
  if (largest && !largest.reported_as_curve) {
    rows.push({
      name: `Largest frontal angle ${largest.upper}–${largest.lower}`,
      value: withSd(largest.angle_deg, largest.angle_sd_deg),
      amount: { value: largest.angle_deg, sd: largest.angle_sd_deg, unit: "deg" },
      model: cobb,
      note: "below the 10° of a scoliotic curve",
      reason: cobbReason,
    });
  }
  for (const c of m.cobb) {
    rows.push({
      name: `${c.major ? "Major" : "Minor"} curve ${c.upper}–${c.lower}, Cobb angle`,
      value: withSd(c.angle_deg, c.angle_sd_deg),
      amount: { value: c.angle_deg, sd: c.angle_sd_deg, unit: "deg" },
      model: cobb,
      note: `apex ${apexWords(c)}, convex to the patient's ${c.convexity}`,
      reason: cobbReason,
    });
    const rotation = c.apex_axial_rotation_deg;
    const toward = rotation === 0 ? "" : (rotation > 0) === (c.convexity === "left") ? "toward the convexity" : "toward the concavity";
    rows.push({
      // an apical disc has no rotation of its own: the engine gives its upper vertebra's (`apex`)
      name: c.apical_disc ? `Apex ${apexWords(c)}: ${c.apex} axial rotation` : `Apex ${c.apex} axial rotation`,
      value: withSd(rotation, byLevel.get(c.apex)?.axial_rotation_sd_deg),
      amount: { value: rotation, sd: byLevel.get(c.apex)?.axial_rotation_sd_deg, unit: "deg" },
      model: u.has("axial_rotation"),
      note: `the vertebral body turned ${toward || "straight ahead"} (positive: toward the patient's left, seen from above)`,
    });
    rows.push({
      name: `Plane of maximum curvature ${c.upper}–${c.lower}`,
      value: `${num(c.plane_of_max_curvature_deg)}° (Cobb ${num(c.max_curvature_deg)}° in it)`,
      amount: { value: c.plane_of_max_curvature_deg, unit: "deg" },
      model: u.has("plane_of_max_curvature"),
      note: "azimuth from the frontal plane, toward anterior",
      more: [{
        name: `Cobb angle in the plane of maximum curvature ${c.upper}–${c.lower}`,
        value: `${num(c.max_curvature_deg)}°`,
        amount: { value: c.max_curvature_deg, unit: "deg" },
        model: u.has("plane_of_max_curvature"),
      }],
    });
  }
  if (cobb) rows.push({ name: "Frontal Cobb angles", value: "from the model's prior", model: true, note: COBB_ESTIMATE_REASON.replace(/^t/, "T"), reason: cobbReason });
  if (m.aasce2019) rows.push({ name: `AASCE 2019 major angle ${m.aasce2019.upper}–${m.aasce2019.lower}`, value: `${num(m.aasce2019.angle_deg)}°`, amount: { value: m.aasce2019.angle_deg, unit: "deg" }, model: false, note: "from the four corners" });
  const kyph = u.has("kyphosis");
  rows.push({ name: "Thoracic kyphosis T4–T12", value: withSd(m.thoracic_kyphosis_t4_t12_deg, m.thoracic_kyphosis_t4_t12_sd_deg), amount: { value: m.thoracic_kyphosis_t4_t12_deg, sd: m.thoracic_kyphosis_t4_t12_sd_deg, unit: "deg" }, model: kyph, note: "positive: convex posteriorly" });
  rows.push({ name: "Thoracic kyphosis T5–T12", value: withSd(m.thoracic_kyphosis_t5_t12_deg, m.thoracic_kyphosis_t5_t12_sd_deg), amount: { value: m.thoracic_kyphosis_t5_t12_deg, sd: m.thoracic_kyphosis_t5_t12_sd_deg, unit: "deg" }, model: kyph, note: "positive: convex posteriorly" });
  rows.push({ name: "Lumbar lordosis L1–L5", value: withSd(m.lumbar_lordosis_l1_l5_deg, m.lumbar_lordosis_l1_l5_sd_deg), amount: { value: m.lumbar_lordosis_l1_l5_deg, sd: m.lumbar_lordosis_l1_l5_sd_deg, unit: "deg" }, model: u.has("lordosis"), note: "positive: convex anteriorly" });
  const f = result.fit;
  for (const view of ["pa", "lateral"] as const) {
    const p = f[view];
    if (!p) continue;
    const source = p.scale_source ? `, ${({ given: "given in the payload", acquisition: "from the acquisition geometry", prior: "from the model's prior on magnification", estimated: "estimated from the landmarks" } as Record<string, string>)[p.scale_source] ?? p.scale_source}` : "";
    const cal = p.pixel_spacing_calibration ? `; spacing calibration ${p.pixel_spacing_calibration}` : "";
    rows.push({
      name: `${view === "pa" ? "PA" : "Lateral"} film scale`,
      value: `${num(p.scale, 3)}`,
      amount: { value: p.scale, unit: "" },
      model: u.has("scale") || p.scale_source === "prior",
      note: `detector mm per patient mm${source}${p.model ? `, ${p.model.replace("_", " ")} projection` : ""}${p.rotation_deg !== undefined ? `, film rotated ${num(p.rotation_deg)}°` : ""}${cal}`,
    });
  }
  if (u.has("depth")) rows.push({ name: "Depth (front–back position)", value: "from the model", model: true, note: "no lateral film constrains it" });
  if (u.has("twist")) rows.push({ name: "Twist between vertebrae", value: "see the strains table", model: true });
  rows.push({ name: "Mean PA registration error", value: `${num(f.mean_registration_error_mm, 2)} mm`, amount: { value: f.mean_registration_error_mm, unit: "mm" }, model: false });
  rows.push({ name: "Fit", value: `${f.converged ? "converged" : "did not converge"} in ${f.iterations} iterations, ${num(f.runtime_ms, 0)} ms`, model: false });
  const boundary = { given: "given (fixed)", soft: "given with an uncertainty", estimated: "not given: estimated from the landmarks and the model" }[f.boundary ?? "given"];
  rows.push({ name: "T1 and L5 poses", value: boundary, model: false });
  for (const a of f.assumed ?? []) {
    const film = a.view ? `, ${a.view === "pa" ? "PA" : "lateral"} film` : "";
    rows.push({ name: `Assumed${film}`, value: ASSUMED[a.name] ?? a.name.replaceAll("_", " "), model: false, note: a.reason });
  }
  const misfit = f.landmark_misfit_ratio;
  if (misfit != null) {
    rows.push({
      name: "Landmark misfit ratio", value: num(misfit, 2), amount: { value: misfit, unit: "1" }, model: false,
      note: misfit > 1
        ? "the landmarks lie farther from the fitted spine than their stated SD explains (a projection that is not the film's, or an SD stated too small): every standard deviation is widened by it"
        : "the landmarks lie within what their stated SD explains",
    });
  }
  if (f.uncertainty_scale != null) rows.push({ name: "Uncertainty scale", value: num(f.uncertainty_scale, 2), amount: { value: f.uncertainty_scale, unit: "" }, model: false, note: "applied to the standard deviations: calibrated on real spines, times the misfit ratio when above 1" });
  rows.push({ name: "Engine", value: `${result.engine.version}, profile ${result.engine.profile}`, model: false, note: `job ${job.id}` });
  return rows;
}

function td(text: string, cls?: string): HTMLTableCellElement {
  const d = document.createElement("td");
  d.textContent = text;
  if (cls) d.className = cls;
  return d;
}

export function fillMeasures(table: HTMLTableElement, job: Job, result: RegistrationResult): void {
  const rows = measureRows(job, result).map((r) => {
    const tr = document.createElement("tr");
    const th = document.createElement("th");
    th.scope = "row";
    th.textContent = r.name;
    if (r.note) {
      const note = document.createElement("span");
      note.className = "note";
      note.textContent = r.note;
      th.append(note);
    }
    const value = td(r.value, "value");
    if (r.model) {
      tr.className = "is-model";
      value.append(" ", mark(r.reason));
    }
    tr.append(th, value);
    return tr;
  });
  table.tBodies[0].replaceChildren(...rows);
}

/** "; P(≥ +20°) 0.86": the probability the result gives of a Lenke criterion, or nothing without one. */
function chance(p: number | null | undefined, what: string): string {
  return p === null || p === undefined || !Number.isFinite(p) ? "" : `; P(${what}) ${p.toFixed(2)}`;
}

export function fillLenke(container: HTMLElement, result: RegistrationResult): void {
  const l = result.measures.lenke;
  const cobb = unreliable(result).has("cobb");
  container.replaceChildren();
  if (!l) {
    container.textContent = "This result carries no Lenke inputs.";
    return;
  }
  const p = document.createElement("p");
  p.append(mark(), " Inputs of the Lenke classification from the 3D model; side-bending films decide which curves are structural.");
  const table = document.createElement("table");
  table.className = "data";
  const cap = table.createCaption();
  cap.id = "lenke-caption";
  cap.textContent = "Lenke inputs";
  const head = table.createTHead().insertRow();
  for (const h of ["Region", "Curve", "Apex", "Cobb", "Major", "≥ 25° (by magnitude)", "Regional kyphosis ≥ +20°"]) {
    const th = document.createElement("th");
    th.scope = "col";
    th.textContent = h;
    if (h === "Cobb" && cobb) {
      th.append(document.createElement("br"), mark(COBB_ESTIMATE_REASON));
      th.classList.add("is-model");
    }
    head.append(th);
  }
  const body = table.createTBody();
  const region: Record<string, string> = { proximal_thoracic: "Proximal thoracic", main_thoracic: "Main thoracic", thoracolumbar_lumbar: "Thoracolumbar/lumbar" };
  for (const c of l.curves) {
    const tr = body.insertRow();
    // A Lenke curve is one of measures.cobb (the largest of its region): its apex is that curve's, disc or vertebra.
    const curve = result.measures.cobb.find((k) => k.upper === c.upper && k.lower === c.lower && k.apex === c.apex);
    // Lenke's kyphosis criterion is regional (docs/measures.md): T2–T5 for the proximal thoracic curve,
    // T10–L2 for the others; the thoracic T5–T12 kyphosis sets the sagittal modifier, not this column.
    const [span, kyphosis, sd] = c.region === "proximal_thoracic"
      ? ["T2–T5", l.t2_t5_kyphosis_deg, l.t2_t5_kyphosis_sd_deg] : ["T10–L2", l.t10_l2_kyphosis_deg, l.t10_l2_kyphosis_sd_deg];
    tr.append(td(region[c.region] ?? c.region), td(`${c.upper}–${c.lower}`), td(apexWords({ apex: c.apex, apical_disc: curve?.apical_disc })), td(`${num(c.angle_deg)}°`), td(c.major ? "yes" : "no"), td(c.structural_by_magnitude ? "yes" : "no"),
      td(`${c.structural_by_kyphosis ? "yes" : "no"} (${span} ${withSd(kyphosis, sd)}${chance(c.structural_by_kyphosis_probability, "≥ +20°")})`));
  }
  const facts = document.createElement("p");
  const modifier = { "-": "− (hypokyphotic, T5–T12 < 10°)", N: "N (normal, 10–40°)", "+": "+ (hyperkyphotic, > 40°)" }[l.sagittal_thoracic_modifier];
  facts.textContent = "The kyphosis criterion of a minor curve is regional (T2–T5 above a proximal thoracic curve, T10–L2 for the others); " +
    `the thoracic kyphosis T5–T12 gives the sagittal modifier. Sagittal thoracic modifier ${modifier}${chance(l.sagittal_thoracic_modifier_probability, "this class")}; ` +
    `kyphosis T2–T5 ${withSd(l.t2_t5_kyphosis_deg, l.t2_t5_kyphosis_sd_deg)}, T5–T12 ${withSd(l.t5_t12_kyphosis_deg, l.t5_t12_kyphosis_sd_deg)}, T10–L2 ${withSd(l.t10_l2_kyphosis_deg, l.t10_l2_kyphosis_sd_deg)}.` +
    (l.not_supported.length ? ` Not given by the reconstruction: ${l.not_supported.join("; ").replace(/_/g, " ")}.` : "");
  // Scrolled within its own box, as the other result tables: a phone-width window (320 CSS px, WCAG 2.1
  // SC 1.4.10 Reflow) keeps the page from scrolling sideways; focusable and named so it scrolls by keyboard.
  const scroll = document.createElement("div");
  scroll.className = "table-scroll";
  scroll.tabIndex = 0;
  scroll.setAttribute("role", "region");
  scroll.setAttribute("aria-labelledby", cap.id);
  scroll.append(table);
  container.append(p, scroll, facts);
}

/** The strains table's columns: head, tooltip, and the fit.unreliable entry that makes the column a model
 * estimate (u1 is the sagittal bending strain: marked as "Sagittal bending (°)" is, by `kyphosis`). */
const STRAIN_COLUMNS: [string, string, string | null][] = [
  ["Level", "", null], ["u1", "sagittal bending strain", "kyphosis"], ["u2", "frontal bending strain", null], ["u3", "twist strain", "twist"],
  ["v1", "shear", null], ["v2", "shear", null], ["v3", "stretch", null], ["Sagittal bending (°)", "", "kyphosis"], ["Frontal bending (°)", "", null],
  ["Twist (°)", "", "twist"], ["Axial rotation (°)", "positive toward the patient's left", "axial_rotation"], ["Position SD (mm, x y z)", "", null], ["PA residual (mm)", "", null],
  ["Lateral residual (mm)", "“—” where the level has no landmark on the lateral film", null],
];

export function fillStrains(table: HTMLTableElement, result: RegistrationResult): void {
  const u = unreliable(result);
  const head = document.createElement("tr");
  for (const [name, title, key] of STRAIN_COLUMNS) {
    const th = document.createElement("th");
    th.scope = "col";
    th.textContent = name;
    if (title) th.title = title;
    if (key && u.has(key)) {
      th.append(document.createElement("br"), mark());
      th.classList.add("is-model");
    }
    head.append(th);
  }
  table.tHead?.replaceChildren(head);
  const residual = new Map(result.fit.residuals.filter((r) => r.view === "pa").map((r) => [r.level, r.residual_mm]));
  const lateral = new Map(result.fit.residuals.filter((r) => r.view === "lateral").map((r) => [r.level, r.residual_mm]));
  const rows = result.vertebrae.map((v) => {
    const tr = document.createElement("tr");
    const th = document.createElement("th");
    th.scope = "row";
    th.textContent = v.level;
    tr.append(th);
    const cells = [
      ...(v.u ?? [null, null, null]).map((x) => num(x === null ? null : x * 1e3, 2)),
      ...(v.v ?? [null, null, null]).map((x) => num(x, 3)),
      num(sagittalBending(v)), num(frontalBending(v)), num(v.twist_deg),
      withSd(v.axial_rotation_deg, v.axial_rotation_sd_deg, ""),
      v.position_sd_mm ? v.position_sd_mm.map((x) => num(x, 1)).join(" ") : "—",
      num(residual.get(v.level), 2),
      num(lateral.get(v.level), 2),
    ];
    for (const text of cells) tr.append(td(text));
    return tr;
  });
  table.tBodies[0].replaceChildren(...rows);
}

export function fillLegend(legend: HTMLElement, result: RegistrationResult): void {
  const limit = bendingLimit(result.vertebrae.map(frontalBending));
  const bar = document.createElement("div");
  bar.className = "legend-bar";
  bar.style.background = gradientCss();
  bar.setAttribute("aria-hidden", "true");
  const labels = document.createElement("div");
  labels.className = "legend-labels";
  for (const x of [-limit, 0, limit]) {
    const s = document.createElement("span");
    s.textContent = `${x > 0 ? "+" : ""}${x.toFixed(1)}°`;
    labels.append(s);
  }
  const caption = document.createElement("p");
  caption.className = "help";
  caption.textContent =
    `Vertebrae coloured by frontal (coronal) bending u2·Δs of the segment below (blue −${limit.toFixed(1)}° to red +${limit.toFixed(1)}°; L5 grey). ` +
    "Positions in patient coordinates LPS (mm): +x patient's left, +y posterior, +z head.";
  legend.replaceChildren(bar, labels, caption);
}

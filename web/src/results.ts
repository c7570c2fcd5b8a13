// The result's tables (clinical measures, strains per vertebra) and the colour legend.
import { bendingLimit, gradientCss } from "./colors";
import type { Job, RegistrationResult } from "./types";

const num = (x: number | null | undefined, digits = 1): string => (x === null || x === undefined ? "—" : x.toFixed(digits));

function row(th: string, td: string): HTMLTableRowElement {
  const tr = document.createElement("tr");
  const h = document.createElement("th");
  h.scope = "row";
  h.textContent = th;
  const d = document.createElement("td");
  d.textContent = td;
  tr.append(h, d);
  return tr;
}

export function fillMeasures(table: HTMLTableElement, job: Job, result: RegistrationResult): void {
  const body = table.tBodies[0];
  const m = result.measures;
  const rows: HTMLTableRowElement[] = [];
  if (!m.cobb.length) rows.push(row("Frontal curves", "none found"));
  for (const c of m.cobb) {
    rows.push(row(
      `${c.major ? "Major" : "Minor"} curve ${c.upper}–${c.lower}`,
      `Cobb ${num(c.angle_deg)}°, apex ${c.apex}, convex to the ${c.convexity}; apex axial rotation ${num(c.apex_axial_rotation_deg)}°; ` +
        `plane of maximum curvature ${num(c.plane_of_max_curvature_deg)}° (${num(c.max_curvature_deg)}° in it)`,
    ));
  }
  rows.push(row("Thoracic kyphosis T4–T12", `${num(m.thoracic_kyphosis_t4_t12_deg)}°`));
  rows.push(row("Thoracic kyphosis T5–T12", `${num(m.thoracic_kyphosis_t5_t12_deg)}°`));
  rows.push(row("Lumbar lordosis L1–L5", `${num(m.lumbar_lordosis_l1_l5_deg)}°`));
  const f = result.fit;
  rows.push(row("Mean PA registration error", `${num(f.mean_registration_error_mm, 2)} mm`));
  rows.push(row("Fit", `${f.converged ? "converged" : "did not converge"} in ${f.iterations} iterations, ${num(f.runtime_ms, 0)} ms`));
  if (f.boundary === "estimated") {
    rows.push(row("T1 and L5", `estimated from the generic model and the landmarks; from the model only: ${(f.unreliable ?? []).join(", ") || "none"}`));
  }
  rows.push(row("Job", `${job.id} · engine ${result.engine.version}, profile ${result.engine.profile}`));
  body.replaceChildren(...rows);
}

const STRAIN_COLUMNS: [string, string][] = [
  ["Level", ""], ["u1", "sagittal bending strain"], ["u2", "lateral bending strain"], ["u3", "twist strain"],
  ["v1", "shear"], ["v2", "shear"], ["v3", "stretch"], ["Sagittal bending", "degrees"], ["Lateral bending", "degrees"],
  ["Twist", "degrees"], ["Axial rotation", "degrees"], ["PA residual", "mm"],
];

export function fillStrains(table: HTMLTableElement, result: RegistrationResult): void {
  const head = document.createElement("tr");
  for (const [name, title] of STRAIN_COLUMNS) {
    const th = document.createElement("th");
    th.scope = "col";
    th.textContent = name;
    if (title) th.title = title;
    head.append(th);
  }
  table.tHead?.replaceChildren(head);
  const residual = new Map(result.fit.residuals.filter((r) => r.view === "pa").map((r) => [r.level, r.residual_mm]));
  const rows = result.vertebrae.map((v) => {
    const tr = document.createElement("tr");
    const th = document.createElement("th");
    th.scope = "row";
    th.textContent = v.level;
    tr.append(th);
    const cells = [
      ...(v.u ?? [null, null, null]).map((x) => num(x === null ? null : x * 1e3, 2)),
      ...(v.v ?? [null, null, null]).map((x) => num(x, 3)),
      num(v.pa_bending_deg), num(v.lateral_bending_deg), num(v.twist_deg), num(v.axial_rotation_deg),
      num(residual.get(v.level), 2),
    ];
    for (const text of cells) {
      const td = document.createElement("td");
      td.textContent = text;
      tr.append(td);
    }
    return tr;
  });
  table.tBodies[0].replaceChildren(...rows);
}

export function fillLegend(legend: HTMLElement, result: RegistrationResult): void {
  const limit = bendingLimit(result.vertebrae.map((v) => v.lateral_bending_deg));
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
    `Vertebrae coloured by lateral bending u2·Δs of the segment below (blue −${limit.toFixed(1)}° to red +${limit.toFixed(1)}°; L5 grey). ` +
    "Yellow dots: landmarks; red lines: residuals. 3D axes: red = patient left (x), green = posterior (y), blue = head (z).";
  legend.replaceChildren(bar, labels, caption);
}

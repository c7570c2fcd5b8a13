// The landmark CSV the page accepts, and the CSV of a result it offers for download.
//
// Landmark CSV: one landmark a line, `level,column,row[,view]`. level is T1..L5; column and row
// are the image coordinates (in the units chosen beside the CSV), decimal numbers; view is `pa` (the
// default) or `lateral`. An optional header line (starting with "level"), blank lines and lines starting
// with "#" are skipped. A level may appear once per view.
import { frontalBending, isLevel, landmarkPoint, LEVELS, sagittalBending, type Landmark, type RegistrationResult } from "./types";

export interface ParsedCsv {
  pa: Landmark[];
  lateral: Landmark[];
  errors: string[];
}

/** A decimal number as Python's float() reads one (sign, digits with an optional point, exponent), without
 * its underscores, "inf" and "nan": what a landmark CSV's column and row may hold. */
const DECIMAL = /^[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?$/;

const byLevel = (a: Landmark, b: Landmark): number => LEVELS.indexOf(a.level) - LEVELS.indexOf(b.level);

export function parseLandmarkCsv(text: string): ParsedCsv {
  const out: ParsedCsv = { pa: [], lateral: [], errors: [] };
  const seen = { pa: new Set<string>(), lateral: new Set<string>() };
  text.split(/\r?\n/).forEach((raw, index) => {
    const line = raw.trim();
    const where = `line ${index + 1}`;
    if (!line || line.startsWith("#")) return;
    const cells = line.split(",").map((c) => c.trim());
    if (cells[0].toLowerCase() === "level") return; // a header line
    if (cells.length < 3 || cells.length > 4) {
      out.errors.push(`${where}: expected level,column,row[,view], got ${cells.length} fields`);
      return;
    }
    const level = cells[0].toUpperCase();
    if (!isLevel(level)) {
      out.errors.push(`${where}: level ${JSON.stringify(cells[0])} is not one of T1..T12, L1..L5`);
      return;
    }
    // Decimal numbers only: Number() would also read "0x1A" as 26 (and 0b…, 0o…, "Infinity"), which
    // no landmark tool writes and the Python client (float()) refuses.
    const bad = [1, 2].find((k) => !DECIMAL.test(cells[k]));
    if (bad !== undefined) {
      const cell = cells[bad];
      const field = `field ${bad + 1} (${bad === 1 ? "column" : "row"})`;
      out.errors.push(cell !== "" && Number.isFinite(Number(cell))
        ? `${where}, ${field}: ${JSON.stringify(cell)} is not a decimal number (hexadecimal, octal and binary notations are not read): write it with the digits 0–9, e.g. 12.5`
        : `${where}: column and row must be finite decimal numbers; ${field} is ${JSON.stringify(cell)}`);
      return;
    }
    const column = Number(cells[1]);
    const row = Number(cells[2]);
    const view = (cells[3] || "pa").toLowerCase();
    if (view !== "pa" && view !== "lateral") {
      out.errors.push(`${where}: view ${JSON.stringify(cells[3])} is not pa or lateral`);
      return;
    }
    if (seen[view].has(level)) {
      out.errors.push(`${where}: level ${level} is given more than once for the ${view} view`);
      return;
    }
    seen[view].add(level);
    out[view].push({ level, point: [column, row] });
  });
  out.pa.sort(byLevel);
  out.lateral.sort(byLevel);
  if (!out.errors.length && !out.pa.length) out.errors.push("no PA landmark found");
  return out;
}

export function landmarkCsv(pa: Landmark[], lateral: Landmark[]): string {
  const rows = ["level,column,row,view"];
  for (const [view, list] of [["pa", pa], ["lateral", lateral]] as const) {
    for (const lm of list) rows.push(`${lm.level},${landmarkPoint(lm)[0]},${landmarkPoint(lm)[1]},${view}`);
  }
  return rows.join("\n") + "\n";
}

export const RESULT_CSV_COLUMNS = [
  "level", "x_mm", "y_mm", "z_mm", "position_sd_x_mm", "position_sd_y_mm", "position_sd_z_mm",
  "d1_x", "d1_y", "d1_z", "d2_x", "d2_y", "d2_z", "d3_x", "d3_y", "d3_z",
  "u1_rad_per_mm", "u2_rad_per_mm", "u3_rad_per_mm", "v1", "v2", "v3",
  "sagittal_bending_deg", "frontal_bending_deg", "twist_deg", "axial_rotation_deg", "axial_rotation_sd_deg",
  "pa_residual_mm", "model_estimate", "lateral_residual_mm",
];

/** Columns that come from the model's prior when fit.unreliable names the quantity. */
const MODEL_COLUMNS: Record<string, string[]> = {
  depth: ["y_mm"], axial_rotation: ["axial_rotation_deg"], twist: ["u3_rad_per_mm", "twist_deg"], kyphosis: ["u1_rad_per_mm", "sagittal_bending_deg"],
};

/** A number as a spreadsheet reads one: left as it is, whatever its sign. */
const NUMBER = /^[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$/;

/** One CSV field (RFC 4180 §2: quoted when it holds a quote, comma or line break). A text that a
 * spreadsheet would take as a formula (it starts with =, +, -, @, a tab or a carriage return: OWASP
 * "CSV Injection") is given a leading apostrophe, so that "=cmd" or "-12.3 ± 1.2°" stays text; a
 * number is left as it is. */
export const cell = (v: number | string | null | undefined): string => {
  if (v === null || v === undefined) return "";
  let text = String(v);
  if (typeof v === "string" && /^[=+\-@\t\r]/.test(text) && !NUMBER.test(text)) text = `'${text}`;
  return /[",\n\r]/.test(text) ? `"${text.replace(/"/g, '""')}"` : text;
};

/** A CSV file's text as a download: UTF-8 with a byte order mark, so that a spreadsheet opening it reads
 * "±", "°", "–" and a patient's name in any alphabet as written (without one, Excel takes the file for
 * the Windows code page); lines end in CRLF (RFC 4180 §2). */
export function csvBlob(text: string): Blob {
  return new Blob(["\ufeff", text.replace(/\r?\n/g, "\r\n")], { type: "text/csv;charset=utf-8" });
}

/** One row per vertebra: pose (LPS mm, directors as rows) with SDs, strains, angles, PA residual and model marks,
 * then the lateral residual (appended last, so the earlier columns keep their places; empty for a level
 * without a lateral landmark or a PA-only job). */
export function resultCsv(result: RegistrationResult): string {
  const residual = new Map(result.fit.residuals.filter((r) => r.view === "pa").map((r) => [r.level, r.residual_mm]));
  const lateral = new Map(result.fit.residuals.filter((r) => r.view === "lateral").map((r) => [r.level, r.residual_mm]));
  const model = (result.fit.unreliable ?? []).flatMap((q) => MODEL_COLUMNS[q] ?? []).join(";");
  const rows = [RESULT_CSV_COLUMNS.join(",")];
  for (const v of result.vertebrae) {
    rows.push([
      v.level, ...v.position, ...(v.position_sd_mm ?? [null, null, null]), ...v.directors.flat(),
      ...(v.u ?? [null, null, null]), ...(v.v ?? [null, null, null]),
      sagittalBending(v), frontalBending(v), v.twist_deg,
      v.axial_rotation_deg, v.axial_rotation_sd_deg, residual.get(v.level), model, lateral.get(v.level),
    ].map(cell).join(","));
  }
  return rows.join("\n") + "\n";
}

/** The measures CSV's columns: `value`, `sd` and `unit` named as the CLI's (`spine get --measures --format csv`,
 * spine_client/tables.py `MEASURE_COLUMNS`), the model-estimate mark and the page's note after them. */
export const MEASURES_CSV_COLUMNS = ["measure", "value", "sd", "unit", "model_estimate", "note"];

/** One row of the measures CSV: its name, value, SD, unit, model-estimate mark and note; `amount` the value as a
 * number (a measure without one keeps its words in `value`, its `sd` and `unit` empty). */
interface MeasuresCsvRow {
  name: string;
  value: string;
  model: boolean;
  note?: string;
  amount?: { value: number | null | undefined; sd?: number | null; unit: string };
  more?: MeasuresCsvRow[];
}

/** The measures as the page shows them, each number in a cell of its own that a spreadsheet computes with:
 * value and SD (plain numbers, in `unit`), whether it is a model estimate, and the note; a value in words
 * ("none of 10° or more", the fit, the engine) stays words. First the rows `about` that say whose they are
 * (patient, patient ID, study date, job), as the printed report's head does, so that a file saved apart
 * from the page still names its patient. */
export function measuresCsv(rows: MeasuresCsvRow[], about: [string, string][] = []): string {
  const out = [MEASURES_CSV_COLUMNS.join(",")];
  const finite = (x: number | null | undefined): number | null => (typeof x === "number" && Number.isFinite(x) ? x : null);
  for (const [name, value] of about) out.push([name, value, "", "", "", ""].map(cell).join(","));
  for (const r of rows.flatMap((row) => [row, ...(row.more ?? [])])) {
    const [value, sd, unit] = r.amount ? [finite(r.amount.value), finite(r.amount.sd), r.amount.unit] : [r.value, null, ""];
    out.push([r.name, value, sd, unit, r.model ? "model estimate" : "", r.note ?? ""].map(cell).join(","));
  }
  return out.join("\n") + "\n";
}

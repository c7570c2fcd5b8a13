// What is wrong with landmarks placed on one film, found before anything is sent: four corners
// that are not a convex quadrilateral in the contract's order or are turned by 90° or more, and
// pedicles given image-right first (the service's own rules, in its words), vertebrae out of order
// down the spine, and bodies that overlap their neighbours; and the acquisition geometry (SID, SOD,
// magnification, central ray) that the service refuses, by its rules and in its words.
// Coordinates are image (column, row); "down the spine" is +row unless the film's orientation says
// its rows run toward the head (DICOM (0020,0020) Patient Orientation, PS3.3 §C.7.6.1.1.1).
import { landmarkPoint, LEVELS, type Landmark, type Level, type Vec2, type ViewPayload } from "./types";

export interface MarkProblem {
  level: Level;
  /** Plain words, e.g. "its four corners make a crossed quadrilateral (…)". */
  text: string;
  /** A few words drawn beside the body on the film, e.g. "crossed: top-left and top-right swapped?". */
  short: string;
}

/** Corner order of the contract: top-left, top-right, bottom-left, bottom-right (AASCE 2019). */
const TL = 0;
const TR = 1;
const BL = 2;
const BR = 3;
/** The quadrilateral's outline in drawing order: TL → TR → BR → BL. */
const OUTLINE = [TL, TR, BR, BL];

/** Overlap allowed between neighbouring bodies, as a fraction of the smaller body's height: clicks
 * are about 1 mm off (DESIGN.md), a thoracic body is 15–25 mm high, so two noisy corners can cross
 * by up to ~2 mm ≈ 10 % of a body. */
export const OVERLAP_TOLERANCE = 0.1;

const cross = (o: Vec2, a: Vec2, b: Vec2): number => (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]);

function segmentsCross(p1: Vec2, p2: Vec2, q1: Vec2, q2: Vec2): boolean {
  const d1 = cross(q1, q2, p1);
  const d2 = cross(q1, q2, p2);
  const d3 = cross(p1, p2, q1);
  const d4 = cross(p1, p2, q2);
  return d1 * d2 < 0 && d3 * d4 < 0;
}

const CORNER_WORDS = ["top-left", "top-right", "bottom-left", "bottom-right"];
/** The single swaps that can cross a quadrilateral: the two of one endplate, the two of one side. */
const SWAPS: [number, number][] = [[TL, TR], [BL, BR], [TL, BL], [TR, BR]];

/** The turns of the outline TL → TR → BR → BL in image (column, row) coordinates, rows running down:
 * at each corner (b − a) × (c − b), > 0 when the turn is clockwise as displayed. */
function turns(c: Vec2[]): number[] {
  const outline = OUTLINE.map((k) => c[k]);
  const edges = outline.map((p, k): Vec2 => [outline[(k + 1) % 4][0] - p[0], outline[(k + 1) % 4][1] - p[1]]);
  return edges.map((e, k) => e[0] * edges[(k + 1) % 4][1] - e[1] * edges[(k + 1) % 4][0]);
}

/** Convex and clockwise as displayed, in the contract's order: every turn > 0. */
const convexInOrder = (c: Vec2[]): boolean => Math.min(...turns(c)) > 0;

const GIVE_THEM = "give them as they appear in the image, in the order top-left, top-right, bottom-left, bottom-right, forming a convex quadrilateral";

/**
 * What the service refuses in one set of four corners (spine_engine/validation.py `_corner_errors`,
 * the same rule and words): taken around the outline TL → TR → BR → BL in image (column, row)
 * coordinates, every turn must be clockwise as displayed (corners_not_convex: they run the wrong way
 * round, cross each other, or do not form a convex quadrilateral); then the top edge (TL → TR) and
 * the bottom edge (BL → BR) must run toward the image's right (corners_not_upright). The film's
 * orientation does not change the rule: corners are named as they appear in the image. The text is
 * the service's, with the page's hint after a semicolon (which corners look swapped); returns
 * [text, short] pairs (empty when the service accepts the corners).
 */
export function cornerProblems(c: Vec2[], level: string = "the vertebra"): [string, string][] {
  if (c.length !== 4) return [];
  const t = turns(c);
  if (Math.min(...t) <= 0) {
    let kind: string;
    let short: string;
    let hint = "";
    if (Math.max(...t) < 0) {
      const below = c[TL][1] > c[BL][1] && c[TR][1] > c[BR][1];
      const mirrored = c[TL][0] > c[TR][0] && c[BL][0] > c[BR][0];
      kind = "run the wrong way round (two corners swapped)";
      hint = below ? "; its top corners are below its bottom ones" : mirrored ? "; its left corners are right of its right ones" : "";
      short = below ? "wrong way round: top below bottom" : mirrored ? "wrong way round: left and right swapped" : "wrong way round";
    } else if (segmentsCross(c[TL], c[TR], c[BR], c[BL]) || segmentsCross(c[TR], c[BR], c[BL], c[TL])) {
      const swap = SWAPS.find(([i, j]) => {
        const d = [...c];
        [d[i], d[j]] = [d[j], d[i]];
        return convexInOrder(d);
      });
      hint = swap ? `; the ${CORNER_WORDS[swap[0]]} and ${CORNER_WORDS[swap[1]]} corners look swapped` : "";
      kind = "cross each other";
      short = `crossed${swap ? `: ${CORNER_WORDS[swap[0]]} and ${CORNER_WORDS[swap[1]]} swapped?` : ""}`;
    } else {
      kind = "do not form a convex quadrilateral";
      short = "not convex";
    }
    return [[`the corners of ${level} ${kind}: ${GIVE_THEM}${hint}`, short]];
  }
  if (!(c[TR][0] > c[TL][0] && c[BR][0] > c[BL][0])) {
    return [[
      `the corners of ${level} are turned by 90° or more in the image: its top edge (top-left → top-right) and bottom edge (bottom-left → bottom-right) must run toward the image's right, as an endplate tilted less than 90° does; give the corners as they appear`,
      "turned 90° or more",
    ]];
  }
  return [];
}

/**
 * What the service refuses in a PA landmark's two pedicle centres (spine_engine/validation.py
 * `_pedicle_errors`, pedicles_not_in_order): the first (image-left) pedicle's column must be smaller
 * than the second's.
 */
export function pedicleProblems(p: Vec2[], level: string = "the vertebra"): [string, string][] {
  if (p.length !== 2) return [];
  const [left, right] = [p[0][0], p[1][0]];
  if (left < right) return [];
  const where = left === right ? "at one column" : `image-right first (columns ${left} then ${right})`;
  return [[
    `the pedicles of ${level} are given ${where}: give the image-left pedicle's centre first, then the image-right one; a vertebra's two pedicles lie side by side on a PA film`,
    left === right ? "pedicles at one column" : "pedicles right first",
  ]];
}

/** Height of a body: the mean of its left and right sides, image px. */
const height = (c: Vec2[]): number => (Math.hypot(c[BL][0] - c[TL][0], c[BL][1] - c[TL][1]) + Math.hypot(c[BR][0] - c[TR][0], c[BR][1] - c[TR][1])) / 2;

/** Depth by which two convex polygons overlap (separating axis theorem): 0 when they do not. */
function overlapDepth(a: Vec2[], b: Vec2[]): number {
  let depth = Infinity;
  for (const poly of [a, b]) {
    for (let i = 0; i < poly.length; i++) {
      const p = poly[i];
      const q = poly[(i + 1) % poly.length];
      const len = Math.hypot(q[0] - p[0], q[1] - p[1]);
      if (len === 0) continue;
      const axis: Vec2 = [-(q[1] - p[1]) / len, (q[0] - p[0]) / len];
      const project = (poly2: Vec2[]): [number, number] => {
        const d = poly2.map((v) => v[0] * axis[0] + v[1] * axis[1]);
        return [Math.min(...d), Math.max(...d)];
      };
      const [a0, a1] = project(a);
      const [b0, b1] = project(b);
      depth = Math.min(depth, Math.min(a1, b1) - Math.max(a0, b0));
      if (depth <= 0) return 0;
    }
  }
  return depth;
}

/** The landmark's top endplate midpoint and its bottom (or the point itself for a midpoint). */
interface Placed {
  level: Level;
  top: Vec2;
  corners: Vec2[] | null;
}

/**
 * The problems of the landmarks of one film: each set of four corners on its own, then each pair
 * of consecutive placed levels (out of order down the spine along the film's head-to-feet axis, `headAxis`:
 * 1 when its rows run toward H or F, 0 when its columns do, null when neither, as the service judges it:
 * validation.py `_order_errors`; bodies overlapping by more than OVERLAP_TOLERANCE of the smaller one's height).
 */
export function filmProblems(marks: Map<Level, { point?: Vec2; corners?: Vec2[]; pedicles?: Vec2[] }>, towardHead = false, headAxis: 0 | 1 | null = 1): MarkProblem[] {
  const down = towardHead ? -1 : 1;
  const out: MarkProblem[] = [];
  const placed: Placed[] = [];
  for (const level of LEVELS) {
    const m = marks.get(level);
    if (!m) continue;
    const corners = m.corners?.length === 4 ? m.corners : null;
    if (corners) for (const [text, short] of cornerProblems(corners, level)) out.push({ level, text, short });
    if (m.pedicles?.length === 2) for (const [text, short] of pedicleProblems(m.pedicles, level)) out.push({ level, text, short });
    const top = m.point ?? (corners ? landmarkPoint({ corners }, towardHead) : null);
    if (top) placed.push({ level, top, corners });
  }
  const bad = new Set(out.map((p) => p.level));
  // landmarks in order along another direction than the orientation's: the orientation is blamed, not the order
  const judgeOrder = headAxis !== null && !orderAlongAnother(placed.map((p) => p.top), headAxis, towardHead);
  for (let i = 1; i < placed.length; i++) {
    const upper = placed[i - 1];
    const lower = placed[i];
    if (judgeOrder && headAxis !== null && (lower.top[headAxis] - upper.top[headAxis]) * down <= 0) {
      out.push({ level: lower.level, text: `it is placed above ${upper.level} (levels go down the spine in order: was a level skipped or repeated?)`, short: `above ${upper.level}` });
      continue;
    }
    const adjacent = LEVELS.indexOf(lower.level) - LEVELS.indexOf(upper.level) === 1;
    if (!adjacent || !upper.corners || !lower.corners || bad.has(upper.level) || bad.has(lower.level)) continue;
    const poly = (c: Vec2[]): Vec2[] => OUTLINE.map((k) => c[k]);
    const depth = overlapDepth(poly(upper.corners), poly(lower.corners));
    if (depth > OVERLAP_TOLERANCE * Math.min(height(upper.corners), height(lower.corners))) {
      out.push({ level: lower.level, text: `its top endplate overlaps ${upper.level}'s bottom endplate`, short: `overlaps ${upper.level}` });
    }
  }
  return out;
}

// ---------------------------------------------------------------- the order that says the orientation is wrong

/** The fewest placed levels whose order is taken as evidence of the film's head-to-feet direction: two steps
 * that agree (with one step, a level placed above the one before it is as likely a mislabel). */
export const ORDER_EVIDENCE_LEVELS = 3;

/** An image direction: along columns (0) or rows (1), toward the patient's head or feet as the index grows. */
export interface HeadToFeet {
  axis: 0 | 1;
  toward: "H" | "F";
}

/**
 * When the top endplate midpoints `tops` (in level order, image (column, row)) are out of order along the stated
 * head-to-feet direction (`headAxis`, toward the head when `towardHead`: validation.py `_head_to_feet_axis`,
 * `_order_errors`, held strictly as the page's order check is) but every step runs one way along the opposite
 * direction or along the other image axis, the direction they do run in (the landmarks run head to feet in level
 * order: growing rows are toward F, shrinking toward H); null otherwise, or with fewer than ORDER_EVIDENCE_LEVELS
 * levels. A film clicked top to bottom whose rows are said to run toward H, or whose rows and columns are
 * swapped, reads so: the orientation, not every landmark, is the likelier mistake (the service says so at
 * `<view>.patient_orientation` as `spine_across_the_film` when the order is within its noise allowance).
 */
export function orderAlongAnother(tops: Vec2[], headAxis: 0 | 1 | null, towardHead: boolean): HeadToFeet | null {
  if (headAxis === null || tops.length < ORDER_EVIDENCE_LEVELS) return null;
  const steps = tops.slice(1).map((p, i): Vec2 => [p[0] - tops[i][0], p[1] - tops[i][1]]);
  const inOrder = (axis: 0 | 1, sign: number): boolean => steps.every((d) => d[axis] * sign > 0);
  const stated = towardHead ? -1 : 1;
  if (inOrder(headAxis, stated)) return null;
  const other: 0 | 1 = headAxis === 1 ? 0 : 1;
  const found = ([[headAxis, -stated], [other, 1], [other, -1]] as [0 | 1, number][]).find(([axis, sign]) => inOrder(axis, sign));
  return found ? { axis: found[0], toward: found[1] > 0 ? "F" : "H" } : null;
}

/**
 * The words of `orderAlongAnother`'s finding on a film with orientation [column, row], and the orientation
 * controls to change (0: toward the image's right, 1: toward its bottom): the landmarks `first`–`last` run in
 * order along another direction than the orientation says, so the orientation is likely wrong; what to choose.
 */
export function orientationFromOrder(view: "pa" | "lateral", orientation: readonly [string, string], found: HeadToFeet, first: Level, last: Level): { text: string; controls: (0 | 1)[] } {
  const where = ["toward the image's right", "toward its bottom"];
  const runs = found.axis === 1 ? (found.toward === "F" ? "down the image (head at its top)" : "up the image (head at its bottom)")
    : found.toward === "F" ? "across the image, head at its left" : "across the image, head at its right";
  const statedAxis = UPRIGHT_ROWS.includes(orientation[1]) ? 1 : 0;
  const says = `the orientation says the patient's ${dir(orientation[statedAxis])} is ${where[statedAxis]}`;
  const other: 0 | 1 = found.axis === 1 ? 0 : 1;
  const across = view === "pa" ? "L (left side) or R (right side)" : "A (front, anterior) or P (back, posterior)";
  const controls: (0 | 1)[] = [found.axis];
  let choose = `choose “${dir(found.toward)}” for “${ORIENTATION_LABELS[found.axis]}”`;
  if (UPRIGHT_ROWS.includes(orientation[other])) {
    choose += ` and ${across} for “${ORIENTATION_LABELS[other]}”`;
    controls.push(other);
  }
  return {
    text: `the landmarks ${first}–${last} run in order ${runs}, but ${says}, so they read as out of order: the orientation is likely wrong, not the landmarks. Look at the film: if the patient's ${found.toward === "F" ? "feet are" : "head is"} ${found.axis === 1 ? "toward its bottom" : "toward its right"}, ${choose} under the film (the landmarks stay where they are)`,
    controls: controls.sort(),
  };
}

// ---------------------------------------------------------------- acquisition geometry

/** The bounds of the service's geometry rules (spine_engine/validation.py, spine_engine/models.py), mirrored. */
export const MAGNIFICATION_RANGE: readonly [number, number] = [0.9, 1.4];
export const UNVERIFIED_SCALE = 2.5;
export const SOURCE_TO_SPINE_MIN_MM = 300;
export const RAY_OBLIQUITY_MAX_DEG = 45;
export const FULL_SPINE_SID_MM = 1800;
export const SPINE_TO_DETECTOR_MM = 200;
export const NOISE_SDS = 3;
export const LANDMARK_SD_MM_DEFAULT = 1;

/** A view's `acquisition` as the payload carries it (models.Acquisition). */
export interface AcquisitionPayload {
  magnification?: number | null;
  distance_source_to_detector_mm?: number | null;
  distance_source_to_patient_mm?: number | null;
  central_ray?: Vec2 | null;
  image_size?: [number, number] | null;
  projection_model?: "perspective" | "weak_perspective" | null;
}

/** The acquisition field a geometry problem is about ("acquisition" when it is SID and SOD together). */
export type GeometryField = "magnification" | "distance_source_to_detector_mm" | "distance_source_to_patient_mm" | "acquisition" | "central_ray" | "image_size";

export interface GeometryProblem {
  field: GeometryField;
  /** The service's words (its FieldError message). */
  text: string;
}

/** Python's `format(x, f".{p}g")`: p significant digits, trailing zeros dropped, exponent below 1e-4 or from 10^p. */
export function pyG(x: number, p = 6): string {
  if (!Number.isFinite(x)) return String(x);
  if (x === 0) return Object.is(x, -0) ? "-0" : "0";
  const strip = (s: string): string => (s.includes(".") ? s.replace(/\.?0+$/, "") : s);
  const [mantissa, e] = x.toExponential(p - 1).split("e");
  const exp = Number(e);
  if (exp < -4 || exp >= p) return `${strip(mantissa)}e${exp < 0 ? "-" : "+"}${String(Math.abs(exp)).padStart(2, "0")}`;
  return strip(x.toFixed(p - 1 - exp));
}

const given = (x: number | null | undefined): x is number => x !== null && x !== undefined;

/** (column, row) mm per unit of the view's coordinates: the pixel spacing [row, column] swapped in px, 1 in mm
 * or without a spacing (validation.py `_mm_per_unit_if_known`). */
function mmPerUnit(view: ViewPayload): Vec2 {
  const s = view.pixel_spacing;
  return view.units === "px" && s ? [s[1], s[0]] : [1, 1];
}

/** The view's landmarks in level order (the service sorts them so). */
const byLevel = (view: ViewPayload): Landmark[] => [...view.landmarks].filter((lm) => LEVELS.includes(lm.level)).sort((a, b) => LEVELS.indexOf(a.level) - LEVELS.indexOf(b.level));

/** validation.py `_outside_image_errors`: with image_size, every landmark point on the image, give or take
 * NOISE_SDS landmark SDs. */
function outsideImage(view: ViewPayload, acq: AcquisitionPayload): GeometryProblem[] {
  if (!acq.image_size) return [];
  const [columns, rows] = acq.image_size;
  const [cm, rm] = mmPerUnit(view);
  const sd = typeof view.landmark_sd_mm === "number" ? view.landmark_sd_mm : LANDMARK_SD_MM_DEFAULT;
  const margin = NOISE_SDS * sd;
  for (const lm of byLevel(view)) {
    const points = [lm.point, ...(lm.corners ?? []), ...(lm.pedicles ?? [])].filter((p): p is Vec2 => !!p);
    for (const [c, r] of points) {
      if (!(-margin / cm <= c && c <= columns + margin / cm && -margin / rm <= r && r <= rows + margin / rm)) {
        return [{
          field: "image_size",
          text: `landmark ${lm.level} at (column ${pyG(c)}, row ${pyG(r)}) lies off the image of ${pyG(columns)} × ${pyG(rows)} (columns × rows, in ${view.units ?? "mm"}): the image size and the landmarks must be in the same units, the landmarks on the image`,
        }];
      }
    }
  }
  return [];
}

/**
 * What the service refuses in a view's acquisition geometry, by its rules and in its words:
 * models.Acquisition (the SOD must be below the SID) and validation.py `_geometry_errors` — a
 * magnification within MAGNIFICATION_RANGE widened by UNVERIFIED_SCALE (0.36–3.5); landmarks on the
 * image of `image_size`; then, for a point-source view (SID and SOD, or projection_model
 * "perspective", the missing ones filled as `Acquisition.point_source_distances` does: SID 1800 mm
 * when neither is given, the other SPINE_TO_DETECTOR_MM apart or through the magnification, SID =
 * SOD·m), the spine at least SOURCE_TO_SPINE_MIN_MM from the source, a magnification SID/SOD of at
 * most 3.5, and every landmark's top midpoint within SID·tan(RAY_OBLIQUITY_MAX_DEG) film mm of the
 * central ray (the given one, else the image's centre). Empty when the service accepts the geometry.
 */
export function geometryProblems(view: ViewPayload): GeometryProblem[] {
  const acq = view.acquisition as AcquisitionPayload | null | undefined;
  if (!acq || typeof acq !== "object") return [];
  const sid0 = acq.distance_source_to_detector_mm;
  const sod0 = acq.distance_source_to_patient_mm;
  const m = acq.magnification;
  if (given(sid0) && given(sod0) && !(sod0 < sid0)) {
    return [{ field: "acquisition", text: `the SOD (${pyG(sod0)} mm) must be smaller than the SID (${pyG(sid0)} mm): the spine lies between the source and the detector` }];
  }
  const low = MAGNIFICATION_RANGE[0] / UNVERIFIED_SCALE;
  const high = MAGNIFICATION_RANGE[1] * UNVERIFIED_SCALE;
  const out: GeometryProblem[] = [];
  if (given(m) && !(low <= m && m <= high)) {
    out.push({ field: "magnification", text: `a magnification of ${pyG(m)} is beyond any radiograph's: the spine's image is ${pyG(low, 2)}–${pyG(high, 2)} times its size (ERMF, DICOM (0018,1114))` });
  }
  out.push(...outsideImage(view, acq));
  const pointSource = (given(sid0) && given(sod0)) || acq.projection_model === "perspective";
  if (!pointSource || out.length) return out;
  let sid = sid0 ?? null;
  let sod = sod0 ?? null;
  if (sid === null && sod === null) sid = FULL_SPINE_SID_MM;
  if (sod === null) sod = given(m) ? (sid as number) / m : (sid as number) - SPINE_TO_DETECTOR_MM;
  if (sid === null) sid = given(m) ? sod * m : sod + SPINE_TO_DETECTOR_MM;
  const stated = (["distance_source_to_detector_mm", "distance_source_to_patient_mm"] as const).filter((f) => given(acq[f]));
  const field: GeometryField = stated.length === 1 ? stated[0] : "acquisition";
  if (sod < SOURCE_TO_SPINE_MIN_MM) {
    const sodAssumed = !given(sod0) && !given(m);
    const how = sodAssumed ? `SID ${pyG(sid)} mm puts the spine` : "the geometry puts the spine";
    const assumed = sodAssumed ? ` (with no SOD or magnification given, the spine's mid-plane is taken ${pyG(SPINE_TO_DETECTOR_MM)} mm before the detector)` : "";
    out.push({ field, text: `${how} ${pyG(sod)} mm from the source${assumed}; a radiograph's source lies at least ${pyG(SOURCE_TO_SPINE_MIN_MM)} mm from the skin, the spine deeper` });
  } else if (sid / sod > high) {
    out.push({ field, text: `SID ${pyG(sid)} mm and SOD ${pyG(sod)} mm${stated.length < 2 ? " (assumed)" : ""} magnify the spine ${pyG(sid / sod, 3)} times; no radiograph magnifies it more than ${pyG(high, 2)} times` });
  } else {
    const ray: [GeometryField, Vec2] | null = acq.central_ray
      ? ["central_ray", [acq.central_ray[0], acq.central_ray[1]]]
      : acq.image_size ? ["image_size", [0.5 * acq.image_size[0], 0.5 * acq.image_size[1]]] : null;
    const landmarks = byLevel(view);
    if (ray && landmarks.length) {
      const [cm, rm] = mmPerUnit(view);
      const [rc, rr] = ray[1];
      const farthest = Math.max(...landmarks.map((lm) => {
        const [c, r] = landmarkPoint(lm);
        return Math.hypot((c - rc) * cm, (r - rr) * rm);
      }));
      if (farthest > sid * Math.tan(RAY_OBLIQUITY_MAX_DEG * (Math.PI / 180))) {
        out.push({
          field: ray[0],
          text: `the central ray${ray[0] === "image_size" ? " (the image centre)" : ""} meets the film ${farthest.toFixed(0)} mm from the farthest landmark, more than the SID (${pyG(sid)} mm): the spine would be filmed by rays more than ${pyG(RAY_OBLIQUITY_MAX_DEG)}° from the central ray, which no X-ray tube emits`,
        });
      }
    }
  }
  return out;
}

/** The field of a geometry problem in words, with the DICOM attribute it comes from (PS3.3 §C.8.11.7, DX Positioning
 * Module, for ERMF, SID and SOD; §C.7.6.3, Image Pixel Module, for Columns and Rows). */
export const GEOMETRY_FIELD_WORDS: Record<GeometryField, string> = {
  magnification: "magnification (ERMF, DICOM (0018,1114))",
  distance_source_to_detector_mm: "SID (source to detector, DICOM (0018,1110))",
  distance_source_to_patient_mm: "SOD (source to patient, DICOM (0018,1111))",
  acquisition: "SID and SOD (DICOM (0018,1110) and (0018,1111))",
  image_size: "image size (its centre taken as the central ray; Columns (0028,0011) × Rows (0028,0010))",
  central_ray: "central ray",
};

// ---------------------------------------------------------------- patient orientation

/** The patient directions of Patient Orientation (0020,0020), DICOM PS3.3 C.7.6.1.1.1, in words. */
export const DIRECTION_WORDS: Record<string, string> = { L: "left side", R: "right side", A: "front, anterior", P: "back, posterior", H: "head", F: "feet" };
/** The orientation controls' labels: Patient Orientation's first value is the direction toward the image's
 * right (along a row), its second toward the image's bottom (down a column), PS3.3 C.7.6.1.1.1. */
export const ORIENTATION_LABELS = ["Toward the image's right: the patient's", "Toward the image's bottom: the patient's"] as const;
/** The patient's three axes (PS3.3 C.7.6.1.1.1: L/R, A/P, H/F), as spine_engine/models.py `_View._orientation` pairs them. */
const AXIS: Record<string, number> = { L: 0, R: 0, A: 1, P: 1, H: 2, F: 2 };
const AXIS_WORDS = ["left–right", "front–back", "head–feet"];
/** spine_engine/validation.py `_UPRIGHT_ROWS`, `_FRONTAL_COLUMNS`, `_DEPTH_AXES`. */
const UPRIGHT_ROWS = ["H", "F"];
const FRONTAL_COLUMNS = ["L", "R"];
const DEPTH_AXES = ["A", "P"];

export type OrientationRule = "value_error" | "orientation_not_of_view" | "corners_need_upright_view" | "pedicles_not_supported";

export interface OrientationProblem {
  /** The service's error type (its FieldError): value_error is models.py's "not orthogonal". */
  type: OrientationRule;
  /** The levels whose corners or pedicles the orientation refuses (the service names each landmark); [] for the others. */
  levels: Level[];
  /** Plain words for the clinician: what is wrong and what to choose at the orientation controls. */
  text: string;
  /** The service's own message, with its Python quotes and list taken away ("got A, F"), once per problem. */
  service: string;
}

const dir = (d: string): string => `${d} (${DIRECTION_WORDS[d] ?? "?"})`;
const levelList = (levels: Level[]): string => (levels.length === 1 ? levels[0] : `${levels.slice(0, -1).join(", ")} and ${levels[levels.length - 1]}`);

/**
 * What the service refuses in a view's patient orientation [column, row] (the direction toward the image's
 * right, then toward its bottom), by its rules: models.py `_View._orientation` refuses two values on one
 * axis of the patient (L/R, A/P, H/F; then nothing else of the payload is judged, as pydantic stops there);
 * validation.py `_plane_errors` (orientation_not_of_view) refuses a PA (frontal, x–z) view with a direction
 * A or P and a lateral (sagittal, y–z) one with L or R, so a PA turned in its plane (["F", "L"]) or an AP
 * (["R", "F"]) stays frontal; `_landmark_form_errors` refuses four corners unless the rows run toward H or F
 * (corners_need_upright_view) and pedicles on the PA view unless its columns run toward L or R
 * (pedicles_not_supported; the page places pedicles on the PA film only). Empty when the service accepts it.
 */
export function orientationProblems(view: "pa" | "lateral", orientation: readonly [string, string], landmarks: readonly Landmark[]): OrientationProblem[] {
  const [column, row] = orientation;
  const film = view === "pa" ? "PA" : "lateral";
  const axes = view === "pa" ? "left–right (L or R) and head–feet (H or F)" : "front–back (A or P) and head–feet (H or F)";
  if (AXIS[column] === undefined || AXIS[row] === undefined) return []; // the controls offer L, R, A, P, H, F only
  if (AXIS[column] === AXIS[row]) {
    return [{
      type: "value_error", levels: [],
      text: `toward the image's right and toward its bottom are both the patient's ${AXIS_WORDS[AXIS[column]]} axis (${column === row ? `${column} twice` : `${column} and ${row}`}): the two must be two different axes of the patient; a ${film} film's are ${axes}`,
      service: `column and row directions ${column}, ${row} are not orthogonal`,
    }];
  }
  const out: OrientationProblem[] = [];
  const excluded = view === "pa" ? DEPTH_AXES : FRONTAL_COLUMNS;
  if (excluded.includes(column) || excluded.includes(row)) {
    const plane = view === "pa" ? "frontal (x, z)" : "sagittal (y, z)";
    const shows = view === "pa"
      ? "a PA film is a frontal film: it shows the patient's left–right and head–feet, not front–back, so neither direction can be A (front) or P (back); so labelled it would show no left–right position of the spine (every frontal Cobb angle the model's guess)"
      : "a lateral film is a side view: it shows the patient's front–back and head–feet, not left–right, so neither direction can be L (left) or R (right); so labelled it would show no depth (kyphosis and lordosis read from a frontal film)";
    const [other, tab] = view === "pa" ? ["lateral", "Lateral film"] : ["PA", "PA film"];
    out.push({
      type: "orientation_not_of_view", levels: [],
      text: `${shows}. If this is the ${other} film, open it in the “${tab}” tab instead; otherwise choose ${axes} here`,
      service: `the ${view} view is a ${plane} film, so neither its column nor its row direction can be ${excluded.join(" or ")}; got ${column}, ${row}: check which film is which and its orientation`,
    });
  }
  const cornered = landmarks.filter((lm) => lm.corners).map((lm) => lm.level);
  if (cornered.length && !UPRIGHT_ROWS.includes(row)) {
    out.push({
      type: "corners_need_upright_view", levels: cornered,
      text: `the four corners of ${levelList(cornered)} need an upright film, its bottom toward the patient's head or feet (corners are named top-left to bottom-right as they appear on an upright film), not ${dir(row)}: choose H (head) or F (feet) for “${ORIENTATION_LABELS[1]}”, or place ${cornered.length === 1 ? "that level" : "those levels"} as endplate midpoints`,
      service: `corners need an upright image (row direction H or F), got patient orientation ${column}, ${row}`,
    });
  }
  const pedicled = landmarks.filter((lm) => lm.pedicles).map((lm) => lm.level);
  if (pedicled.length && (view !== "pa" || !FRONTAL_COLUMNS.includes(column))) {
    out.push({
      type: "pedicles_not_supported", levels: pedicled,
      text: view === "pa"
        ? `the pedicles of ${levelList(pedicled)} are read side by side across the film, so its right must be toward the patient's left or right, not ${dir(column)}: choose L (left side) or R (right side) for “${ORIENTATION_LABELS[0]}”, or delete those pedicles`
        : `the pedicles of ${levelList(pedicled)} are taken on the PA film only: delete them from the lateral film`,
      service: "pedicles are supported on the PA view only, with columns toward the patient's L or R",
    });
  }
  return out;
}

// ---------------------------------------------------------------- a skipped vertebra

/**
 * A gap between consecutive placed levels larger than this many times the median of its neighbouring gaps
 * is warned about as a vertebra possibly skipped (every label below it one level off); the service accepts
 * it (validation.py allows up to 2.5 × the median spacing). Derived by `python -m tools.spacing_ratio`
 * (gap: the chain distance between top endplate midpoints per level spanned; neighbours: up to
 * SKIP_NEIGHBOURS gaps on each side, at least SKIP_MIN_NEIGHBOURS): over 458 AASCE 2019 training PA
 * radiographs (23 with levels out of order left out) and 24 VerSe dev spines, frontal and lateral
 * projections, the largest ratio of a real film is 1.71 but for one radiograph (1.89 at T1–T2, its T1
 * corners misplaced); 1.75 is the next multiple of 0.05 above 1.71. It warns on 0.2 % of real films
 * (1 of 506; AASCE training 1 of 458) and catches 91.0 % of skips (one interior level dropped and the rest
 * relabelled: AASCE 90.5 %, VerSe frontal 95.6 %, lateral 96.9 %; a dropped T2, compared with the gaps
 * below only, 47 %, T3 73 %, T4–L4 94–98 %); skipped vertebrae's ratios have a median of 1.99.
 */
export const SKIP_RATIO = 1.75;
export const SKIP_NEIGHBOURS = 2;
export const SKIP_MIN_NEIGHBOURS = 2;

export interface SpacingWarning {
  /** The levels on either side of the gap. */
  upper: Level;
  lower: Level;
  /** The gap (per level spanned) over the median of its neighbouring gaps. */
  ratio: number;
}

/**
 * The gaps of a view's landmarks that are more than SKIP_RATIO times their neighbours': gap i between
 * consecutive placed levels a and b is the distance in mm (px scaled by the pixel spacing) between their
 * top endplate midpoints, along the landmark chain (whatever the film's orientation), divided by the number
 * of levels b − a; it is compared with the median of the up to SKIP_NEIGHBOURS gaps on each side, when
 * there are at least SKIP_MIN_NEIGHBOURS of them (four levels placed). Empty when no gap stands out.
 */
export function spacingWarnings(view: ViewPayload): SpacingWarning[] {
  const [cm, rm] = mmPerUnit(view);
  // a pasted payload may hold anything: a landmark without two numbers for its top midpoint is left out
  const pair = (p: unknown): boolean => Array.isArray(p) && p.length >= 2 && p.every((x) => typeof x === "number");
  const marks = byLevel({ ...view, landmarks: view.landmarks.filter((lm) => !!lm && typeof lm === "object") }).filter((lm) => (lm.point ? pair(lm.point) : Array.isArray(lm.corners) && lm.corners.length === 4 && lm.corners.every(pair)));
  const gaps: number[] = [];
  for (let i = 1; i < marks.length; i++) {
    const [a, b] = [landmarkPoint(marks[i - 1]), landmarkPoint(marks[i])];
    const levels = LEVELS.indexOf(marks[i].level) - LEVELS.indexOf(marks[i - 1].level);
    gaps.push(Math.hypot((b[0] - a[0]) * cm, (b[1] - a[1]) * rm) / Math.max(levels, 1));
  }
  const out: SpacingWarning[] = [];
  gaps.forEach((gap, i) => {
    const near = gaps.filter((_, j) => j !== i && Math.abs(j - i) <= SKIP_NEIGHBOURS).sort((x, y) => x - y);
    if (near.length < SKIP_MIN_NEIGHBOURS) return;
    const h = near.length >> 1;
    const median = near.length % 2 ? near[h] : (near[h - 1] + near[h]) / 2;
    const ratio = gap / median;
    if (median > 0 && ratio > SKIP_RATIO) out.push({ upper: marks[i].level, lower: marks[i + 1].level, ratio });
  });
  return out;
}

/** The skipped-vertebra warnings of a payload's films, in words naming the film and the two levels. */
export function skippedVertebraWarnings(payload: { pa?: ViewPayload | null; lateral?: ViewPayload | null }): string[] {
  const out: string[] = [];
  for (const [name, view] of [["PA", payload.pa], ["Lateral", payload.lateral]] as const) {
    if (!Array.isArray(view?.landmarks)) continue;
    for (const w of spacingWarnings(view)) {
      const between = LEVELS.indexOf(w.lower) - LEVELS.indexOf(w.upper) > 1 ? " (per level between them)" : "";
      out.push(`${name} film, ${w.upper}–${w.lower}: this gap is ${w.ratio.toFixed(1)} × its neighbours'${between}; a vertebra may have been skipped, and every label below it would be one level off. Look at the film between ${w.upper} and ${w.lower}: if a vertebra lies between them, the landmarks from ${w.lower} down are one level too high; if not, it can be sent as it is.`);
    }
  }
  return out;
}

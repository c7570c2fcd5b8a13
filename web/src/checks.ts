// What is wrong with landmarks placed on one film, found before anything is sent: four corners
// that are not a convex quadrilateral in the contract's order or are turned by 90° or more, and
// pedicles given image-right first (the service's own rules, in its words), vertebrae out of order
// down the spine, and bodies that overlap their neighbours.
// Coordinates are image (column, row); "down the spine" is +row unless the film's orientation says
// its rows run toward the head (DICOM (0020,0020) Patient Orientation, PS3.3 §C.7.6.1.1.1).
import { LEVELS, type Level, type Vec2 } from "./types";

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
 * of consecutive placed levels (out of order down the spine; bodies overlapping by more than
 * OVERLAP_TOLERANCE of the smaller one's height).
 */
export function filmProblems(marks: Map<Level, { point?: Vec2; corners?: Vec2[]; pedicles?: Vec2[] }>, rowsTowardHead = false): MarkProblem[] {
  const down = rowsTowardHead ? -1 : 1;
  const out: MarkProblem[] = [];
  const placed: Placed[] = [];
  for (const level of LEVELS) {
    const m = marks.get(level);
    if (!m) continue;
    const corners = m.corners?.length === 4 ? m.corners : null;
    if (corners) for (const [text, short] of cornerProblems(corners, level)) out.push({ level, text, short });
    if (m.pedicles?.length === 2) for (const [text, short] of pedicleProblems(m.pedicles, level)) out.push({ level, text, short });
    const top = m.point ?? (corners ? ([(corners[TL][0] + corners[TR][0]) / 2, (corners[TL][1] + corners[TR][1]) / 2] as Vec2) : null);
    if (top) placed.push({ level, top, corners });
  }
  const bad = new Set(out.map((p) => p.level));
  for (let i = 1; i < placed.length; i++) {
    const upper = placed[i - 1];
    const lower = placed[i];
    if ((lower.top[1] - upper.top[1]) * down <= 0) {
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

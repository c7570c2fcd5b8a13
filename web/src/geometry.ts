// Weak perspective and vertebra glyphs, as spine_engine.projection and spine_engine.figures draw them.
import type { Vec2, Vec3, VertebraResult } from "./types";

export const PATIENT_AXES: Record<string, Vec3> = {
  L: [1, 0, 0],
  R: [-1, 0, 0],
  P: [0, 1, 0],
  A: [0, -1, 0],
  H: [0, 0, 1],
  F: [0, 0, -1],
};
export const PA_ORIENTATION: [string, string] = ["L", "F"];
export const LATERAL_ORIENTATION: [string, string] = ["A", "F"];

/** Drawn body width and height (along d3), as multiples of the segment length. */
export const BODY_WIDTH = 1.4;
export const BODY_HEIGHT = 0.7;
export const BODY_DEPTH = 1.2;

export const dot = (a: Vec3, b: Vec3): number => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
export const add = (a: Vec3, b: Vec3): Vec3 => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
export const sub = (a: Vec3, b: Vec3): Vec3 => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
export const mul = (a: Vec3, s: number): Vec3 => [a[0] * s, a[1] * s, a[2] * s];
export const norm = (a: Vec3): number => Math.hypot(a[0], a[1], a[2]);

export function imageAxes(orientation: [string, string] | undefined): [Vec3, Vec3] {
  const [c, r] = orientation ?? PA_ORIENTATION;
  const ec = PATIENT_AXES[c];
  const er = PATIENT_AXES[r];
  if (!ec || !er) throw new Error(`unknown patient orientation ${c},${r}`);
  return [ec, er];
}

/** image point = s·(e_c·r, e_r·r) + T (detector mm). */
export function project(r: Vec3, axes: [Vec3, Vec3], scale: number, translation: Vec2): Vec2 {
  return [scale * dot(axes[0], r) + translation[0], scale * dot(axes[1], r) + translation[1]];
}

/** Distance from each vertebra to the next (the last repeats the one before). */
export function segmentLengths(vertebrae: VertebraResult[]): number[] {
  const gaps = vertebrae.slice(0, -1).map((v, i) => norm(sub(vertebrae[i + 1].position, v.position)));
  return [...gaps, gaps.length ? gaps[gaps.length - 1] : 25];
}

/** Corners of a vertebra's drawn box below its top endplate midpoint: across d1 (0) or d2 (1), down d3. */
export function bodyCorners(v: VertebraResult, seg: number, across: 0 | 1): Vec3[] {
  const a = mul(v.directors[across], (BODY_WIDTH * seg) / 2);
  const d = mul(v.directors[2], BODY_HEIGHT * seg);
  const p = v.position;
  return [sub(p, a), add(p, a), add(add(p, a), d), add(sub(p, a), d)];
}

/** Landmark points in detector mm (px times the DICOM pixel spacing [row, column]). */
export function toDetectorMm(point: Vec2, units: "mm" | "px" | undefined, spacing: Vec2 | null | undefined): Vec2 {
  if (units === "px" && spacing) return [point[0] * spacing[1], point[1] * spacing[0]];
  return point;
}

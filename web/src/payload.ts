// Defaults, the sample payload and the boundary conditions helpers.
import { imageAxes, toDetectorMm } from "./geometry";
import { landmarkPoint, LEVELS, type JobPayload, type Landmark, type Mat3, type Pose, type Vec3, type ViewPayload } from "./types";

/** Directors (rows d1, d2, d3) of an upright, untwisted vertebra: left, anterior, caudal. */
export const IDENTITY_LPS: Mat3 = [[1, 0, 0], [0, -1, 0], [0, 0, -1]];
export const DEFAULT_LENGTH_MM = 420;

export function defaultBoundary(): { T1: Pose; L5: Pose } {
  return {
    T1: { position: [0, 0, 0], directors: structuredClone(IDENTITY_LPS) },
    L5: { position: [0, 0, -DEFAULT_LENGTH_MM], directors: structuredClone(IDENTITY_LPS) },
  };
}

/** A C-curve of 17 endplate midpoints (detector mm) with T1 and L5 given: what "Load a sample" gives. */
export function samplePayload(curveMm = 30, lengthMm = DEFAULT_LENGTH_MM): JobPayload {
  const landmarks: Landmark[] = LEVELS.map((level, i) => {
    const t = i / (LEVELS.length - 1);
    const x = curveMm * Math.sin(Math.PI * t);
    return { level, point: [round3(100 + x), round3(50 + lengthMm * t)] };
  });
  const boundary = defaultBoundary();
  boundary.L5.position = [0, 0, -lengthMm];
  return { pa: { landmarks }, boundary };
}

const round3 = (x: number): number => Math.round(x * 1000) / 1000;

/**
 * L5's position from the T1 and L5 landmarks of a view: T1's position plus their image offset
 * (detector mm over the magnification) along the view's column and row directions; the
 * component out of the image plane is kept from `currentL5`.
 */
export function l5FromLandmarks(view: ViewPayload, t1: Vec3, currentL5: Vec3, magnification: number): Vec3 | null {
  const top = view.landmarks.find((lm) => lm.level === "T1");
  const bottom = view.landmarks.find((lm) => lm.level === "L5");
  if (!top || !bottom || !(magnification > 0)) return null;
  const a = toDetectorMm(landmarkPoint(top), view.units, view.pixel_spacing);
  const b = toDetectorMm(landmarkPoint(bottom), view.units, view.pixel_spacing);
  const [ec, er] = imageAxes(view.patient_orientation);
  const normal: Vec3 = [
    ec[1] * er[2] - ec[2] * er[1],
    ec[2] * er[0] - ec[0] * er[2],
    ec[0] * er[1] - ec[1] * er[0],
  ];
  const dc = (b[0] - a[0]) / magnification;
  const dr = (b[1] - a[1]) / magnification;
  const out = normal.reduce((s, n, k) => s + n * (currentL5[k] - t1[k]), 0);
  return [0, 1, 2].map((k) => round3(t1[k] + dc * ec[k] + dr * er[k] + out * normal[k])) as Vec3;
}

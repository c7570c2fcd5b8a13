// PA and lateral projections of the reconstruction as SVG: over the radiograph when one was
// loaded (image pixels), else in detector mm. Vertebrae coloured by lateral bending, landmarks
// and residual lines, as spine_engine.figures draws them.
import { bendingColour, bendingLimit } from "./colors";
import { bodyCorners, imageAxes, LATERAL_ORIENTATION, project, segmentLengths, toDetectorMm } from "./geometry";
import { frontalBending, landmarkPoint, type JobPayload, type Level, type RegistrationResult, type Vec2, type ViewPayload, type ViewProjection } from "./types";

const SVG_NS = "http://www.w3.org/2000/svg";

export interface Backdrop {
  url: string;
  width: number;
  height: number;
  /** mm per image pixel [row, column], to place detector mm on the image. */
  spacing: Vec2;
}

function el<K extends keyof SVGElementTagNameMap>(name: K, attrs: Record<string, string | number>, text?: string): SVGElementTagNameMap[K] {
  const node = document.createElementNS(SVG_NS, name);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, String(v));
  if (text !== undefined) node.textContent = text;
  return node;
}

const fmt = (x: number): string => x.toFixed(2);

interface ViewSpec {
  title: string;
  view: ViewPayload | null;
  projection: ViewProjection | { scale: number; translation: Vec2 };
  orientation: [string, string];
  across: 0 | 1;
  backdrop: Backdrop | null;
}

function drawView(container: HTMLElement, result: RegistrationResult, spec: ViewSpec): void {
  const vertebrae = result.vertebrae;
  const axes = imageAxes(spec.orientation);
  const segs = segmentLengths(vertebrae);
  const limit = bendingLimit(vertebrae.map(frontalBending));
  const { scale, translation } = spec.projection;
  // Detector mm → drawing units (image px over a backdrop, else mm).
  const toDraw = (p: Vec2): Vec2 => (spec.backdrop ? [p[0] / spec.backdrop.spacing[1], p[1] / spec.backdrop.spacing[0]] : p);
  const proj = (r: [number, number, number]): Vec2 => toDraw(project(r, axes, scale, translation));
  const bodies = vertebrae.map((v, i) => bodyCorners(v, segs[i], spec.across).map(proj));
  const centre = vertebrae.map((v) => proj(v.position));
  const marks: [Level, Vec2][] = (spec.view?.landmarks ?? []).map((lm) => [
    lm.level,
    toDraw(toDetectorMm(landmarkPoint(lm), spec.view?.units, spec.view?.pixel_spacing)),
  ]);

  const all = [...bodies.flat(), ...marks.map((m) => m[1])];
  let [x0, y0] = [Math.min(...all.map((p) => p[0])), Math.min(...all.map((p) => p[1]))];
  let [x1, y1] = [Math.max(...all.map((p) => p[0])), Math.max(...all.map((p) => p[1]))];
  const pad = 0.06 * Math.max(x1 - x0, y1 - y0);
  [x0, y0, x1, y1] = [x0 - pad, y0 - pad, x1 + pad, y1 + pad];
  const minWidth = 0.5 * (y1 - y0);
  if (x1 - x0 < minWidth) {
    const cx = (x0 + x1) / 2;
    [x0, x1] = [cx - minWidth / 2, cx + minWidth / 2];
  }
  const size = y1 - y0;
  const titleId = `${container.id}-title`;
  const svg = el("svg", {
    viewBox: `${fmt(x0)} ${fmt(y0)} ${fmt(x1 - x0)} ${fmt(size)}`,
    role: "img",
    "aria-labelledby": titleId,
    preserveAspectRatio: "xMidYMid meet",
  });
  svg.append(el("title", { id: titleId }, spec.title));
  if (spec.backdrop) {
    svg.append(el("image", { href: spec.backdrop.url, x: 0, y: 0, width: spec.backdrop.width, height: spec.backdrop.height }));
  } else {
    svg.append(el("rect", { x: x0, y: y0, width: x1 - x0, height: size, fill: "#f7f8fa" }));
  }
  const r = size * 0.006;
  const gBodies = el("g", { stroke: "#333", "stroke-width": 0.8, "vector-effect": "non-scaling-stroke" });
  vertebrae.forEach((v, i) => {
    const poly = el("polygon", {
      points: bodies[i].map((p) => `${fmt(p[0])},${fmt(p[1])}`).join(" "),
      fill: bendingColour(frontalBending(v), limit),
      "fill-opacity": spec.backdrop ? 0.75 : 1,
      "vector-effect": "non-scaling-stroke",
    });
    const frontal = frontalBending(v);
    const bending = frontal === null ? "no segment below" : `lateral bending ${frontal.toFixed(1)}°`;
    poly.append(el("title", {}, `${v.level}: ${bending}`));
    gBodies.append(poly);
  });
  svg.append(gBodies);
  svg.append(el("polyline", {
    points: centre.map((p) => `${fmt(p[0])},${fmt(p[1])}`).join(" "),
    fill: "none", stroke: "#111", "stroke-width": 1.2, "vector-effect": "non-scaling-stroke",
  }));
  const index = new Map(vertebrae.map((v, i) => [v.level, i]));
  for (const [level, p] of marks) {
    const i = index.get(level);
    if (i !== undefined) {
      svg.append(el("line", {
        x1: p[0], y1: p[1], x2: centre[i][0], y2: centre[i][1],
        stroke: "#d0021b", "stroke-width": 1.5, "vector-effect": "non-scaling-stroke",
      }));
    }
    const mark = el("circle", { cx: p[0], cy: p[1], r, fill: "#ffd000", stroke: "#000", "stroke-width": 1, "vector-effect": "non-scaling-stroke" });
    mark.append(el("title", {}, `${level} landmark`));
    svg.append(mark);
  }
  for (const i of [0, Math.floor(vertebrae.length / 2), vertebrae.length - 1]) {
    const y = centre[i][1];
    const t = el("text", { x: x0 + size * 0.01, y, "font-size": size * 0.03, "dominant-baseline": "middle", fill: spec.backdrop ? "#fff" : "#222", stroke: spec.backdrop ? "#000" : "none", "stroke-width": 0.5, "paint-order": "stroke", "vector-effect": "non-scaling-stroke" }, vertebrae[i].level);
    t.setAttribute("aria-hidden", "true");
    svg.append(t);
  }
  container.replaceChildren(svg);
}

/** Draw the PA and lateral projections of a job's result into their containers. */
export function drawProjections(
  pa: HTMLElement,
  lateral: HTMLElement,
  result: RegistrationResult,
  payload: JobPayload,
  backdrop: Backdrop | null,
): { lateralFromImage: boolean } {
  drawView(pa, result, {
    title: backdrop ? "PA projection of the model over the radiograph, with the landmarks and residuals" : "PA projection of the model with the landmarks and residuals (detector mm)",
    view: payload.pa,
    projection: result.fit.pa,
    orientation: (payload.pa.patient_orientation as [string, string] | undefined) ?? ["L", "F"],
    across: 0,
    backdrop,
  });
  const lat = payload.lateral;
  if (lat && lat.landmarks.length && result.fit.lateral) {
    drawView(lateral, result, {
      title: "Lateral projection of the model with the lateral landmarks and residuals (detector mm)",
      view: lat,
      projection: result.fit.lateral,
      orientation: (lat.patient_orientation as [string, string] | undefined) ?? LATERAL_ORIENTATION,
      across: 1,
      backdrop: null,
    });
    return { lateralFromImage: true };
  }
  // No lateral image: the model seen from the patient's right (anterior to the left), rows as on PA.
  const s = result.fit.pa.scale;
  const rows = result.fit.pa.translation[1];
  drawView(lateral, result, {
    title: "Lateral projection of the model, anterior to the right",
    view: null,
    projection: { scale: s, translation: [0, rows] },
    orientation: LATERAL_ORIENTATION,
    across: 1,
    backdrop: null,
  });
  return { lateralFromImage: false };
}

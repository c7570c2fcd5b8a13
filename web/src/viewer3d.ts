// The reconstructed spine in 3D (three.js): vertebral bodies posed by their directors and coloured
// by lateral bending, the centreline, and the patient axes. WebGL when the browser has it, else
// three's SVG renderer (same scene, drawn as SVG; also with ?renderer=svg). Rendered on demand.
// Mouse: drag rotates, wheel zooms. Keyboard: arrows rotate, + and − zoom, 0 resets.
import {
  AmbientLight,
  BoxGeometry,
  BufferGeometry,
  Color,
  DirectionalLight,
  EdgesGeometry,
  Float32BufferAttribute,
  Group,
  Line,
  LineBasicMaterial,
  LineSegments,
  Matrix4,
  Mesh,
  MeshLambertMaterial,
  PerspectiveCamera,
  Scene,
  Vector3,
  WebGLRenderer,
} from "three";
import { SVGRenderer } from "three/examples/jsm/renderers/SVGRenderer.js";
import { bendingColour, bendingLimit } from "./colors";
import { add, BODY_DEPTH, BODY_HEIGHT, BODY_WIDTH, mul, segmentLengths } from "./geometry";
import { frontalBending, type RegistrationResult, type Vec3 } from "./types";

type Renderer = { render(scene: Scene, camera: PerspectiveCamera): void; setSize(w: number, h: number): void; domElement: Element };

const DEG = Math.PI / 180;
const DEFAULT_VIEW = { azimuth: -35, elevation: 15, zoom: 1 };

export class SpineViewer {
  readonly scene = new Scene();
  readonly camera = new PerspectiveCamera(35, 1, 1, 10000);
  readonly renderer: Renderer;
  readonly kind: "webgl" | "svg";
  private spine = new Group();
  private axes = axes();
  /** The axes' names, HTML over the drawing at the projected tips (both renderers; hidden from
   * assistive technology, which reads the camera's position in words instead). */
  private axisLabels: HTMLSpanElement[] = AXIS_ENDS.map(([, , name, colour]) => {
    const span = document.createElement("span");
    span.className = "axis-label";
    span.textContent = name;
    span.style.color = colour;
    span.setAttribute("aria-hidden", "true");
    return span;
  });
  private target = new Vector3();
  private radius = 300;
  private halfHeight = 250;
  private halfWidth = 80;
  private view = { ...DEFAULT_VIEW };
  private drag: { x: number; y: number; azimuth: number; elevation: number } | null = null;

  constructor(
    private readonly container: HTMLElement,
    private readonly orientationLabel: HTMLElement,
  ) {
    let renderer: Renderer;
    let kind: "webgl" | "svg";
    const forceSvg = new URLSearchParams(window.location.search).get("renderer") === "svg";
    try {
      if (forceSvg) throw new Error("SVG renderer asked for");
      const probe = document.createElement("canvas");
      if (!probe.getContext("webgl2") && !probe.getContext("webgl")) throw new Error("no WebGL");
      const gl = new WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
      gl.setPixelRatio(Math.min(2, window.devicePixelRatio || 1));
      gl.setClearColor(0xf7f8fa);
      renderer = gl;
      kind = "webgl";
    } catch {
      const svg = new SVGRenderer();
      svg.setClearColor(new Color(0xf7f8fa), 1);
      svg.setQuality("high");
      renderer = svg;
      kind = "svg";
    }
    this.renderer = renderer;
    this.kind = kind;
    container.dataset.renderer = kind;
    container.append(renderer.domElement, ...this.axisLabels);
    renderer.domElement.setAttribute("aria-hidden", "true");
    this.camera.up.set(0, 0, 1);
    this.scene.background = new Color(0xf7f8fa);
    // The SVG renderer adds light intensities without WebGL's physically based scaling.
    const [ambient, keyLight, fillLight] = kind === "webgl" ? [1.2, 1.6, 0.7] : [0.55, 0.45, 0.15];
    this.scene.add(new AmbientLight(0xffffff, ambient));
    const key = new DirectionalLight(0xffffff, keyLight);
    key.position.set(-0.6, -1, 0.8);
    const fill = new DirectionalLight(0xffffff, fillLight);
    fill.position.set(0.8, 1, -0.2);
    this.scene.add(key, fill, this.spine, this.axes);

    container.addEventListener("pointerdown", (e) => {
      this.drag = { x: e.clientX, y: e.clientY, azimuth: this.view.azimuth, elevation: this.view.elevation };
      container.setPointerCapture(e.pointerId);
      container.focus({ preventScroll: true });
    });
    container.addEventListener("pointermove", (e) => {
      if (!this.drag) return;
      this.view.azimuth = this.drag.azimuth - (e.clientX - this.drag.x) * 0.5;
      this.view.elevation = clamp(this.drag.elevation + (e.clientY - this.drag.y) * 0.5, -89, 89);
      this.render();
    });
    const end = (): void => {
      this.drag = null;
    };
    container.addEventListener("pointerup", end);
    container.addEventListener("pointercancel", end);
    container.addEventListener(
      "wheel",
      (e) => {
        e.preventDefault();
        this.zoomBy(e.deltaY > 0 ? 1.1 : 1 / 1.1);
      },
      { passive: false },
    );
    container.addEventListener("keydown", (e) => this.onKey(e));
    new ResizeObserver(() => this.resize()).observe(container);
  }

  show(result: RegistrationResult): void {
    this.spine.clear();
    const vertebrae = result.vertebrae;
    const segs = segmentLengths(vertebrae);
    const limit = bendingLimit(vertebrae.map(frontalBending));
    const edges = new LineBasicMaterial({ color: 0x333333 });
    vertebrae.forEach((v, i) => {
      const seg = segs[i];
      const [w, d, h] = [BODY_WIDTH * seg, BODY_DEPTH * seg, BODY_HEIGHT * seg];
      const geometry = new BoxGeometry(w, d, h);
      const centre = add(v.position, mul(v.directors[2], h / 2));
      const [d1, d2, d3] = v.directors.map((r) => new Vector3(...r));
      const pose = new Matrix4().makeBasis(d1, d2, d3).setPosition(...centre);
      const material = new MeshLambertMaterial({ color: new Color(bendingColour(frontalBending(v), limit)) });
      const body = new Mesh(geometry, material);
      body.applyMatrix4(pose);
      body.name = v.level;
      const outline = new LineSegments(new EdgesGeometry(geometry), edges);
      outline.applyMatrix4(pose);
      this.spine.add(body, outline);
    });
    const line = new BufferGeometry().setAttribute(
      "position",
      new Float32BufferAttribute(vertebrae.flatMap((v) => v.position), 3),
    );
    this.spine.add(new Line(line, new LineBasicMaterial({ color: 0x111111 })));

    const lo = new Vector3(Infinity, Infinity, Infinity);
    const hi = new Vector3(-Infinity, -Infinity, -Infinity);
    for (const v of vertebrae) {
      lo.min(new Vector3(...v.position));
      hi.max(new Vector3(...v.position));
    }
    this.target = lo.clone().add(hi).multiplyScalar(0.5);
    this.radius = Math.max(100, hi.distanceTo(lo) * 0.5 + 40);
    this.halfHeight = (hi.z - lo.z) / 2 + 30;
    this.halfWidth = Math.max(...vertebrae.map((v) => Math.hypot(v.position[0] - this.target.x, v.position[1] - this.target.y))) + 40;
    this.axes.position.set(lo.x - 80, this.target.y, lo.z);
    this.container.setAttribute(
      "aria-label",
      `3D view of the reconstructed spine, ${vertebrae.length} vertebrae from ${vertebrae[0].level} to ` +
        `${vertebrae[vertebrae.length - 1].level}, coloured by lateral bending (blue negative, red positive).`,
    );
    this.resize();
  }

  setView(name: "front" | "side" | "reset"): void {
    if (name === "front") this.view = { ...this.view, azimuth: 0, elevation: 0 };
    else if (name === "side") this.view = { ...this.view, azimuth: -90, elevation: 0 };
    else this.view = { ...DEFAULT_VIEW };
    this.render();
  }

  zoomBy(factor: number): void {
    this.view.zoom = clamp(this.view.zoom * factor, 0.25, 6);
    this.render();
  }

  private onKey(event: KeyboardEvent): void {
    const step = event.shiftKey ? 15 : 5;
    switch (event.key) {
      case "ArrowLeft": this.view.azimuth += step; break;
      case "ArrowRight": this.view.azimuth -= step; break;
      case "ArrowUp": this.view.elevation = clamp(this.view.elevation + step, -89, 89); break;
      case "ArrowDown": this.view.elevation = clamp(this.view.elevation - step, -89, 89); break;
      case "+": case "=": this.view.zoom = clamp(this.view.zoom / 1.15, 0.25, 6); break;
      case "-": case "_": this.view.zoom = clamp(this.view.zoom * 1.15, 0.25, 6); break;
      case "0": case "Home": this.view = { ...DEFAULT_VIEW }; break;
      default: return;
    }
    event.preventDefault();
    this.render();
  }

  private resize(): void {
    const w = Math.max(100, this.container.clientWidth);
    const h = Math.max(100, this.container.clientHeight);
    this.renderer.setSize(w, h);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  render(): void {
    const az = this.view.azimuth * DEG;
    const el = this.view.elevation * DEG;
    // Fit the spine's height, and its width in a narrow view (seen from any side, elevation aside).
    const tilt = Math.abs(Math.sin(el)) * this.halfHeight + Math.abs(Math.cos(el)) * this.halfWidth;
    const half = Math.max(Math.abs(Math.cos(el)) * this.halfHeight + Math.abs(Math.sin(el)) * this.halfWidth, tilt / this.camera.aspect);
    const distance = ((half * 1.08) / Math.tan((this.camera.fov * DEG) / 2) + this.halfWidth) * this.view.zoom;
    const direction = new Vector3(Math.sin(az) * Math.cos(el), -Math.cos(az) * Math.cos(el), Math.sin(el));
    this.camera.position.copy(this.target).addScaledVector(direction, distance);
    this.camera.lookAt(this.target);
    this.camera.near = Math.max(1, distance - this.radius * 3);
    this.camera.far = distance + this.radius * 3;
    this.camera.updateProjectionMatrix();
    this.renderer.render(this.scene, this.camera);
    const w = this.container.clientWidth;
    const h = this.container.clientHeight;
    AXIS_ENDS.forEach(([end], i) => {
      const p = new Vector3(...end).multiplyScalar(1.25).add(this.axes.position).project(this.camera);
      const label = this.axisLabels[i];
      label.hidden = p.z > 1 || Math.abs(p.x) > 1 || Math.abs(p.y) > 1;
      label.style.left = `${((p.x + 1) / 2) * w}px`;
      label.style.top = `${((1 - p.y) / 2) * h}px`;
    });
    this.orientationLabel.textContent = describe(this.view.azimuth, this.view.elevation);
  }
}

function clamp(x: number, lo: number, hi: number): number {
  return Math.min(hi, Math.max(lo, x));
}

/** Where the camera is: "Camera 35° from the front toward the patient's right, 15° above." */
export function describe(azimuthDeg: number, elevationDeg: number): string {
  const az = Math.round(((((azimuthDeg + 180) % 360) + 360) % 360) - 180); // 0 = anterior, + = toward patient left
  const where =
    az === 0 ? "in front of the patient (the PA radiograph's view)"
    : Math.abs(az) === 180 ? "behind the patient"
    : `${Math.abs(az)}° from the front toward the patient's ${az > 0 ? "left" : "right"}`;
  const el = Math.round(elevationDeg);
  return `Camera ${where}${el === 0 ? "" : `, ${Math.abs(el)}° ${el > 0 ? "above" : "below"}`}.`;
}

/** Patient axes (DICOM LPS, DESIGN.md), 60 mm long: tip, line colour, label, label colour. */
const AXIS_ENDS: [Vec3, number, string, string][] = [
  [[60, 0, 0], 0xcc2222, "x left", "#a31515"],
  [[0, 60, 0], 0x229922, "y posterior", "#17661a"],
  [[0, 0, 60], 0x2244cc, "z head", "#1f3fb0"],
];

/** Patient axes, 60 mm long: x left (red), y posterior (green), z head (blue); placed beside L5. */
function axes(): Group {
  const group = new Group();
  for (const [end, colour] of AXIS_ENDS) {
    const geometry = new BufferGeometry().setAttribute("position", new Float32BufferAttribute([0, 0, 0, ...end], 3));
    group.add(new Line(geometry, new LineBasicMaterial({ color: colour })));
  }
  return group;
}

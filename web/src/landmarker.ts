// Clicking the vertebra landmarks on a PA radiograph, level by level (T1..L5), with undo.
// Mouse: click places the current level's landmark. Keyboard: arrows move a crosshair
// (Shift: ten times faster), Enter or Space places, Backspace or Ctrl+Z undoes.
import { LEVELS, type Level, type Vec2 } from "./types";

type Action = { kind: "place"; level: Level; point: Vec2 } | { kind: "skip"; level: Level };

const MAX_CANVAS_PIXELS = 24_000_000;

export interface LoadedImage {
  url: string;
  name: string;
  width: number;
  height: number;
  element: HTMLImageElement;
}

export class Landmarker {
  image: LoadedImage | null = null;
  private history: Action[] = [];
  private cursor: Vec2 | null = null;
  private zoom: "fit" | number = "fit";
  private displayScale = 1; // CSS px per image px

  constructor(
    private readonly canvas: HTMLCanvasElement,
    private readonly frame: HTMLElement,
    private readonly onChange: () => void,
  ) {
    canvas.addEventListener("click", (e) => this.onClick(e));
    canvas.addEventListener("mousemove", (e) => {
      this.cursor = this.toImage(e);
      this.draw();
    });
    canvas.addEventListener("keydown", (e) => this.onKey(e));
    new ResizeObserver(() => this.layout()).observe(frame);
  }

  async load(file: File): Promise<void> {
    if (!/^image\/(png|jpeg)$/.test(file.type)) throw new Error(`${file.name} is not a PNG or JPEG image`);
    const url = URL.createObjectURL(file);
    const element = new Image();
    element.alt = `PA radiograph ${file.name}`;
    element.src = url;
    try {
      await element.decode();
    } catch {
      URL.revokeObjectURL(url);
      throw new Error(`${file.name} could not be read as an image`);
    }
    if (this.image) URL.revokeObjectURL(this.image.url);
    this.image = { url, name: file.name, width: element.naturalWidth, height: element.naturalHeight, element };
    this.history = [];
    this.cursor = [element.naturalWidth / 2, element.naturalHeight * 0.1];
    this.canvas.setAttribute("aria-label", `Radiograph ${file.name}, ${element.naturalWidth} by ${element.naturalHeight} pixels.`);
    this.layout();
    this.onChange();
  }

  get landmarks(): { level: Level; point: Vec2 }[] {
    return this.history.flatMap((a) => (a.kind === "place" ? [{ level: a.level, point: a.point }] : []));
  }

  /** The level the next click places, or null when every level is placed or skipped. */
  get nextLevel(): Level | null {
    return this.history.length < LEVELS.length ? LEVELS[this.history.length] : null;
  }

  get skipped(): Level[] {
    return this.history.flatMap((a) => (a.kind === "skip" ? [a.level] : []));
  }

  place(point: Vec2): void {
    const level = this.nextLevel;
    if (!this.image || !level) return;
    const p: Vec2 = [
      Math.round(Math.min(this.image.width, Math.max(0, point[0])) * 10) / 10,
      Math.round(Math.min(this.image.height, Math.max(0, point[1])) * 10) / 10,
    ];
    this.history.push({ kind: "place", level, point: p });
    this.changed();
  }

  skip(): void {
    const level = this.nextLevel;
    if (!this.image || !level) return;
    this.history.push({ kind: "skip", level });
    this.changed();
  }

  undo(): void {
    if (this.history.pop()) this.changed();
  }

  clear(): void {
    this.history = [];
    this.changed();
  }

  setZoom(zoom: "fit" | number): void {
    this.zoom = zoom;
    this.layout();
  }

  private changed(): void {
    this.draw();
    this.onChange();
  }

  private onClick(event: MouseEvent): void {
    const p = this.toImage(event);
    if (p) this.place(p);
    this.canvas.focus({ preventScroll: true });
  }

  private onKey(event: KeyboardEvent): void {
    if (!this.image) return;
    const step = Math.max(1, Math.round(this.image.height / 400)) * (event.shiftKey ? 10 : 1);
    const c = this.cursor ?? [this.image.width / 2, this.image.height / 2];
    const moves: Record<string, Vec2> = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowUp: [0, -step], ArrowDown: [0, step] };
    if (event.key in moves) {
      const [dx, dy] = moves[event.key];
      this.cursor = [Math.min(this.image.width, Math.max(0, c[0] + dx)), Math.min(this.image.height, Math.max(0, c[1] + dy))];
      this.draw();
      this.scrollCursorIntoView();
    } else if (event.key === "Enter" || event.key === " ") {
      this.place(c);
    } else if (event.key === "Backspace" || (event.key.toLowerCase() === "z" && (event.ctrlKey || event.metaKey))) {
      this.undo();
    } else {
      return;
    }
    event.preventDefault();
  }

  private toImage(event: MouseEvent): Vec2 | null {
    if (!this.image) return null;
    const rect = this.canvas.getBoundingClientRect();
    return [
      ((event.clientX - rect.left) / rect.width) * this.image.width,
      ((event.clientY - rect.top) / rect.height) * this.image.height,
    ];
  }

  private scrollCursorIntoView(): void {
    if (!this.cursor) return;
    const y = this.cursor[1] * this.displayScale;
    const x = this.cursor[0] * this.displayScale;
    const f = this.frame;
    if (y < f.scrollTop + 20 || y > f.scrollTop + f.clientHeight - 20) f.scrollTop = y - f.clientHeight / 2;
    if (x < f.scrollLeft + 20 || x > f.scrollLeft + f.clientWidth - 20) f.scrollLeft = x - f.clientWidth / 2;
  }

  private layout(): void {
    const image = this.image;
    if (!image) {
      this.canvas.width = 0;
      this.canvas.height = 0;
      return;
    }
    const available = Math.max(50, this.frame.clientWidth);
    this.displayScale = this.zoom === "fit" ? available / image.width : this.zoom;
    const cssW = image.width * this.displayScale;
    const cssH = image.height * this.displayScale;
    let ratio = window.devicePixelRatio || 1;
    if (cssW * cssH * ratio * ratio > MAX_CANVAS_PIXELS) ratio = Math.sqrt(MAX_CANVAS_PIXELS / (cssW * cssH));
    this.canvas.style.width = `${cssW}px`;
    this.canvas.style.height = `${cssH}px`;
    this.canvas.width = Math.max(1, Math.round(cssW * ratio));
    this.canvas.height = Math.max(1, Math.round(cssH * ratio));
    this.draw();
  }

  draw(): void {
    const image = this.image;
    const ctx = this.canvas.getContext("2d");
    if (!ctx || !image) return;
    const k = this.canvas.width / image.width; // backing pixels per image pixel
    const unit = this.canvas.width / parseFloat(this.canvas.style.width || "1"); // backing px per CSS px
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.clearRect(0, 0, this.canvas.width, this.canvas.height);
    ctx.drawImage(image.element, 0, 0, this.canvas.width, this.canvas.height);
    ctx.lineWidth = 2 * unit;
    ctx.font = `${Math.round(12 * unit)}px system-ui, sans-serif`;
    ctx.textBaseline = "middle";
    const marks = this.landmarks;
    if (marks.length > 1) {
      ctx.strokeStyle = "rgba(255, 200, 0, 0.8)";
      ctx.beginPath();
      marks.forEach((m, i) => (i ? ctx.lineTo(m.point[0] * k, m.point[1] * k) : ctx.moveTo(m.point[0] * k, m.point[1] * k)));
      ctx.stroke();
    }
    for (const m of marks) {
      const [x, y] = [m.point[0] * k, m.point[1] * k];
      ctx.fillStyle = "#ffd000";
      ctx.strokeStyle = "#000";
      ctx.beginPath();
      ctx.arc(x, y, 4 * unit, 0, 2 * Math.PI);
      ctx.fill();
      ctx.stroke();
      this.label(ctx, m.level, x + 8 * unit, y);
    }
    const next = this.nextLevel;
    if (this.cursor && next) {
      const [x, y] = [this.cursor[0] * k, this.cursor[1] * k];
      const r = 10 * unit;
      ctx.strokeStyle = "#00e5ff";
      ctx.beginPath();
      ctx.moveTo(x - r, y);
      ctx.lineTo(x + r, y);
      ctx.moveTo(x, y - r);
      ctx.lineTo(x, y + r);
      ctx.stroke();
      this.label(ctx, next, x + r + 4 * unit, y, "#00e5ff");
    }
  }

  private label(ctx: CanvasRenderingContext2D, text: string, x: number, y: number, colour = "#ffd000"): void {
    ctx.lineWidth = 3 * (this.canvas.width / parseFloat(this.canvas.style.width || "1"));
    ctx.strokeStyle = "#000";
    ctx.strokeText(text, x, y);
    ctx.fillStyle = colour;
    ctx.fillText(text, x, y);
    ctx.lineWidth = 2 * (this.canvas.width / parseFloat(this.canvas.style.width || "1"));
  }
}

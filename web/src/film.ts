// One film (PA or lateral) and its landmarks: rendering with window/level, zoom and pan on a
// full-size film, three click modes (top endplate midpoint, four corners, two pedicles). A click
// always places the next landmark, whatever lies under it; a point moves only by a drag (press and
// move past DRAG_PX) or by the keyboard (arrows move a crosshair, Enter places, Alt+arrows move the
// selected point). Ctrl+Z / Ctrl+Shift+Z undo and redo. A complete vertebra moves on to the next
// level below it that has no mark of the click mode yet (none: it stays, complete). What is wrong with
// the marks (checks.ts) is drawn in place, in red; landmarks the service refused are ringed in red.
// Coordinates are image pixels (column, row).
import { filmProblems, type MarkProblem } from "./checks";
import { windowToGrey, type DicomFilm } from "./dicom";
import { LEVELS, type Landmark, type Level, type Vec2 } from "./types";

export type Mode = "point" | "corners" | "pedicles";
export const MODE_PARTS: Record<Mode, number> = { point: 1, corners: 4, pedicles: 2 };
export const CORNER_NAMES = ["top-left", "top-right", "bottom-left", "bottom-right"];
export const PEDICLE_NAMES = ["image-left pedicle", "image-right pedicle"];

/** A vertebra's marks on one film while they are being placed (corners and pedicles may be partial). */
export interface Mark {
  point?: Vec2;
  corners?: Vec2[];
  pedicles?: Vec2[];
}

interface Handle {
  level: Level;
  kind: Mode;
  index: number;
}

export interface FilmSource {
  name: string;
  width: number;
  height: number;
  dicom: DicomFilm | null;
  /** A PNG/JPEG element, when not DICOM. */
  element: HTMLImageElement | null;
}

const HIT_PX = 9; // CSS px around a point that a drag grabs
const DRAG_PX = 4; // CSS px a press must move to be a drag (a pan, or moving the point under it)
const HISTORY = 200; // undo steps kept
/** The ring around a landmark the service refused. */
export const REFUSED_RED = "#ff1f1f";

interface Snapshot {
  marks: [Level, Mark][];
  level: Level;
  finished: boolean;
}

/** An edit of the panel beyond the marks (closing the film): undone after the editor's own history
 * (Undo, Ctrl+Z, once the marks' history is empty), and redone likewise. */
export interface OuterEdit {
  undo(): void;
  redo(): void;
}

/** Everything the editor shows: the film, its landmarks and their undo history (closing a film keeps it, for Undo). */
export interface EditorState {
  source: FilmSource | null;
  raster: HTMLCanvasElement | null;
  extent: { width: number; height: number } | null;
  marks: Map<Level, Mark>;
  undoStack: Snapshot[];
  level: Level;
  finished: boolean;
  window: { center: number; width: number };
  invert: boolean;
  blankNote: string | null;
  refused: Map<Level, string>;
  cursor: Vec2 | null;
}

/** The level `by` levels below `level` (−1: above), or null outside T1–L5. */
export const shiftedLevel = (level: Level, by: number): Level | null => LEVELS[LEVELS.indexOf(level) + by] ?? null;
const copyMark = (m: Mark): Mark => ({
  ...(m.point ? { point: [...m.point] as Vec2 } : {}),
  ...(m.corners ? { corners: m.corners.map((p) => [...p] as Vec2) } : {}),
  ...(m.pedicles ? { pedicles: m.pedicles.map((p) => [...p] as Vec2) } : {}),
});
const round1 = (x: number): number => Math.round(x * 10) / 10;
/** A mark's points in a fixed order, to tell whether it changed. */
const markKey = (m: Mark | undefined): string => JSON.stringify([m?.point ?? null, m?.corners ?? null, m?.pedicles ?? null]);

export class FilmEditor {
  source: FilmSource | null = null;
  marks = new Map<Level, Mark>();
  mode: Mode = "point";
  level: Level = "T1";
  selected: Handle | null = null;
  cursor: Vec2 | null = null;
  /** Set when the last level (L5) was completed: a click then places nothing until a level is chosen. */
  finished = false;
  /** The film's head-to-feet axis runs toward the patient's head: "down the spine" is −row (or −column). */
  towardHead = false;
  /** The film's head-to-feet axis: 1 when its rows run toward H or F, 0 when its columns do (a film turned a
   * quarter), null when neither; the levels' order down the spine is judged along it, as the service does. */
  headAxis: 0 | 1 | null = 1;
  /** Called when the keyboard moves the crosshair (the arrow keys; not the mouse): the panel says where it is. */
  onCrosshair: (() => void) | null = null;
  /** Drawn in the blank frame of landmarks without their film: why the film is not there. */
  blankNote: string | null = null;
  /** Levels the service refused (its 422 named their landmarks), each with its mark as it was then: ringed
   * in red while the mark is unchanged. */
  private refused = new Map<Level, string>();
  /** Said once, at the cursor, after a click that placed nothing. */
  private notice: string | null = null;
  /** The name of a film being read to replace this one: a click places nothing meanwhile (the
   * landmark would belong to the film that is about to go). */
  loading: string | null = null;
  private undoStack: Snapshot[] = [];
  private redoStack: Snapshot[] = [];
  /** The panel's edit undone when the marks' own undo history is empty (closing the film), and the one redone after it. */
  private outerUndo: OuterEdit | null = null;
  private outerRedo: OuterEdit | null = null;
  window = { center: 0, width: 1 };
  invert = false;
  /** CSS px per image px, and the image point at the canvas's top-left corner. */
  private scale = 1;
  private origin: Vec2 = [0, 0];
  private fitted = true;
  private raster: HTMLCanvasElement | null = null;
  private extent: { width: number; height: number } | null = null;
  private drag: { handle: Handle | null; start: Vec2; origin: Vec2; moved: boolean; shift: boolean } | null = null;

  constructor(
    readonly canvas: HTMLCanvasElement,
    private readonly onChange: (what: "marks" | "view" | "level") => void,
  ) {
    canvas.addEventListener("pointerdown", (e) => this.onDown(e));
    canvas.addEventListener("pointermove", (e) => this.onMove(e));
    canvas.addEventListener("pointerup", (e) => this.onUp(e));
    canvas.addEventListener("pointerleave", () => {
      if (!this.drag) this.draw();
    });
    canvas.addEventListener("wheel", (e) => this.onWheel(e), { passive: false });
    canvas.addEventListener("keydown", (e) => this.onKey(e));
    new ResizeObserver(() => this.layout()).observe(canvas);
  }

  // ---------------------------------------------------------------- the film

  /** Show a film. A new film starts with no landmarks: those placed on another film (and their undo
   * history) are dropped from the editor (the panel keeps them for Undo, `saveState`), unless ``keepLandmarks`` (a reopened job's landmarks, shown over their
   * own film once it is opened). Returns how many vertebrae were dropped. */
  setSource(source: FilmSource, keepLandmarks = false): number {
    const dropped = keepLandmarks ? 0 : this.marks.size;
    if (!keepLandmarks) this.forget();
    this.source = source;
    this.blankNote = null;
    this.extent = { width: source.width, height: source.height };
    if (source.dicom) {
      this.window = { center: source.dicom.window.center, width: source.dicom.window.width };
      this.invert = source.dicom.monochrome1;
    }
    this.raster = null;
    this.render();
    this.cursor = [source.width / 2, source.height * 0.1];
    this.fit();
    if (dropped) this.onChange("marks");
    return dropped;
  }

  /** Ring the landmarks of `levels` in red: the service refused them (until they are moved or placed again). */
  setRefused(levels: Level[]): void {
    this.refused = new Map(levels.filter((lv) => this.marks.has(lv)).map((lv) => [lv, markKey(this.marks.get(lv))]));
    this.draw();
  }

  /** The refused levels whose marks are still as they were refused. */
  refusedLevels(): Level[] {
    return [...this.refused].filter(([lv, key]) => markKey(this.marks.get(lv)) === key).map(([lv]) => lv);
  }

  /** No landmarks, no undo history, back to T1. */
  private forget(): void {
    this.refused.clear();
    this.marks.clear();
    this.undoStack = [];
    this.redoStack = [];
    this.outerUndo = null;
    this.outerRedo = null;
    this.selected = null;
    this.finished = false;
    this.notice = null;
    this.level = "T1";
  }

  /** No film and no landmarks: the editor as the page first shows it. */
  reset(): void {
    this.forget();
    this.source = null;
    this.raster = null;
    this.extent = null;
    this.blankNote = null;
    this.cursor = null;
    this.draw();
    this.onChange("marks");
  }

  /** The film, its landmarks and their undo history, as they are now (the redo history is not kept:
   * the edit that saves them, closing the film, ends it as any edit does). */
  saveState(): EditorState {
    return {
      source: this.source, raster: this.raster, extent: this.extent,
      marks: new Map([...this.marks].map(([lv, m]) => [lv, copyMark(m)])), undoStack: [...this.undoStack],
      level: this.level, finished: this.finished, window: { ...this.window }, invert: this.invert,
      blankNote: this.blankNote, refused: new Map(this.refused), cursor: this.cursor,
    };
  }

  /** Show a saved film with its landmarks and undo history again (Undo of "Close film"). */
  loadState(s: EditorState): void {
    this.source = s.source;
    this.raster = s.raster;
    this.extent = s.extent;
    this.marks = new Map([...s.marks].map(([lv, m]) => [lv, copyMark(m)]));
    this.undoStack = [...s.undoStack];
    this.redoStack = [];
    this.level = s.level;
    this.finished = s.finished;
    this.window = { ...s.window };
    this.invert = s.invert;
    this.blankNote = s.blankNote;
    this.refused = new Map(s.refused);
    this.cursor = s.cursor;
    this.selected = null;
    this.notice = null;
    this.loading = null;
    this.fit();
    this.onChange("marks");
  }

  /** Record an edit of the panel beyond the marks (closing the film) as the next one Undo takes back. */
  pushOuter(edit: OuterEdit): void {
    this.outerUndo = edit;
    this.outerRedo = null;
    this.onChange("view");
  }

  /** Forget the film (the landmarks stay, on a blank frame). */
  clearSource(): void {
    this.source = null;
    this.raster = null;
    this.extent = this.landmarkExtent();
  }

  setWindow(center: number, width: number, invert: boolean): void {
    this.window = { center, width: Math.max(1, width) };
    this.invert = invert;
    this.render();
    this.draw();
    this.onChange("view");
  }

  /** Re-draw the film's raster through the current window (DICOM) or from the image element. */
  private render(): void {
    const s = this.source;
    if (!s) return;
    const raster = this.raster ?? document.createElement("canvas");
    raster.width = s.width;
    raster.height = s.height;
    const ctx = raster.getContext("2d");
    if (!ctx) return;
    if (s.dicom) {
      const data = ctx.createImageData(s.width, s.height);
      windowToGrey(s.dicom.pixels, this.window.center, this.window.width, this.invert, data.data);
      ctx.putImageData(data, 0, 0);
    } else if (s.element) {
      ctx.drawImage(s.element, 0, 0);
    }
    this.raster = raster;
  }

  /** The film's raster (window applied) as a PNG blob. */
  rasterBlob(): Promise<Blob | null> {
    const raster = this.raster;
    return raster ? new Promise((resolve) => raster.toBlob((b) => resolve(b), "image/png")) : Promise.resolve(null);
  }

  // ---------------------------------------------------------------- landmarks

  /** Landmarks of the payload: complete point or corners, with pedicles when both are placed. */
  landmarks(): Landmark[] {
    const out: Landmark[] = [];
    for (const level of LEVELS) {
      const m = this.marks.get(level);
      if (!m) continue;
      const lm: Landmark = { level };
      if (m.point) lm.point = m.point;
      else if (m.corners?.length === 4) lm.corners = m.corners.map((p) => [...p]) as [Vec2, Vec2, Vec2, Vec2];
      else continue;
      if (m.pedicles?.length === 2) lm.pedicles = m.pedicles.map((p) => [...p]);
      out.push(lm);
    }
    return out;
  }

  /** The levels with a point outside the film (its width and height in px), in level order. */
  landmarksOffFilm(): Level[] {
    const s = this.source;
    if (!s) return [];
    const off = (p: Vec2): boolean => !(p[0] >= 0 && p[0] <= s.width && p[1] >= 0 && p[1] <= s.height);
    return LEVELS.filter((lv) => {
      const m = this.marks.get(lv);
      return !!m && [m.point, ...(m.corners ?? []), ...(m.pedicles ?? [])].some((p) => p && off(p));
    });
  }

  /** What is wrong with the complete marks (crossed or non-convex corners, order, overlaps). */
  problems(): MarkProblem[] {
    return filmProblems(this.marks, this.towardHead, this.headAxis);
  }

  private snapshot(): Snapshot {
    return { marks: [...this.marks].map(([lv, m]) => [lv, copyMark(m)]), level: this.level, finished: this.finished };
  }

  /** Keep the marks as they are now for Undo; call before each change of the marks. */
  private remember(): void {
    this.undoStack.push(this.snapshot());
    if (this.undoStack.length > HISTORY) this.undoStack.shift();
    this.redoStack = [];
    this.outerRedo = null;
  }

  private restoreSnapshot(s: Snapshot): void {
    this.marks = new Map(s.marks.map(([lv, m]) => [lv, copyMark(m)]));
    this.level = s.level;
    this.finished = s.finished;
    this.selected = null;
    this.notice = null;
    this.draw();
    this.onChange("marks");
  }

  get canUndo(): boolean {
    return this.undoStack.length > 0 || !!this.outerUndo;
  }

  get canRedo(): boolean {
    return this.redoStack.length > 0 || !!this.outerRedo;
  }

  undo(): void {
    const s = this.undoStack.pop();
    if (!s) {
      const outer = this.outerUndo;
      if (!outer) return;
      this.outerUndo = null;
      outer.undo();
      this.outerRedo = outer;
      this.onChange("view");
      return;
    }
    this.redoStack.push(this.snapshot());
    this.restoreSnapshot(s);
  }

  redo(): void {
    const s = this.redoStack.pop();
    if (!s) {
      const outer = this.outerRedo;
      this.outerRedo = null;
      outer?.redo();
      return;
    }
    this.undoStack.push(this.snapshot());
    this.restoreSnapshot(s);
  }

  /** Relabel every landmark of the film `by` levels down the spine (+1: T1's become T2's; −1: up), as one
   * edit that Undo takes back. Refused, nothing changed, when a level would leave T1–L5 (the payload's
   * levels): returns why in words, or null when done. */
  shiftLevels(by: 1 | -1): string | null {
    const placed = LEVELS.filter((lv) => this.marks.has(lv));
    if (!placed.length) return "Nothing relabelled: no landmark is placed on this film.";
    const edge = by > 0 ? placed[placed.length - 1] : placed[0];
    if (!shiftedLevel(edge, by)) {
      return `Not relabelled: ${edge}'s landmarks would become the level ${by > 0 ? "below L5" : "above T1"}, and landmarks are of T1–L5 only. ` +
        `If ${edge}'s landmarks are not of a vertebra of T1–L5, delete them first.`;
    }
    this.remember();
    const to = (lv: Level): Level | null => shiftedLevel(lv, by);
    this.marks = new Map(placed.map((lv) => [to(lv) as Level, this.marks.get(lv) as Mark]));
    this.refused = new Map([...this.refused].flatMap(([lv, key]) => (to(lv) ? [[to(lv) as Level, key]] : [])));
    this.level = to(this.level) ?? this.level;
    this.selected = this.selected && to(this.selected.level) ? { ...this.selected, level: to(this.selected.level) as Level } : null;
    this.notice = null;
    this.draw();
    this.onChange("marks");
    return null;
  }

  /** What is placed only in part, in words (e.g. "T3: 2 of 4 corners"). */
  incomplete(): string[] {
    const out: string[] = [];
    for (const level of LEVELS) {
      const m = this.marks.get(level);
      if (!m) continue;
      if (m.corners && m.corners.length < 4) out.push(`${level}: ${m.corners.length} of 4 corners placed`);
      if (m.pedicles && m.pedicles.length < 2) out.push(`${level}: 1 of 2 pedicles placed`);
      if (m.pedicles && !m.point && !(m.corners?.length === 4)) out.push(`${level}: pedicles without the endplate midpoint or corners`);
    }
    return out;
  }

  setLandmarks(landmarks: Landmark[], spacing?: Vec2 | null, units?: string): void {
    // Reopened payloads in mm are shown in mm (1 "pixel" = 1 mm) unless a spacing brings them to px.
    this.refused.clear();
    this.marks.clear();
    this.undoStack = [];
    this.redoStack = [];
    this.outerUndo = null;
    this.outerRedo = null;
    this.finished = false;
    const k = units === "mm" && spacing ? [1 / spacing[1], 1 / spacing[0]] : [1, 1];
    // not rounded: a reopened job is sent again with exactly its coordinates
    const px = (p: Vec2): Vec2 => [p[0] * k[0], p[1] * k[1]];
    for (const lm of landmarks) {
      const m: Mark = {};
      if (lm.point) m.point = px(lm.point);
      if (lm.corners) m.corners = lm.corners.map(px);
      if (Array.isArray(lm.pedicles)) m.pedicles = (lm.pedicles as Vec2[]).map(px);
      this.marks.set(lm.level, m);
    }
    if (!this.source) this.extent = this.landmarkExtent();
    this.selected = null;
    this.fit();
    this.onChange("marks");
  }

  clear(): void {
    if (this.marks.size) this.remember();
    this.marks.clear();
    this.selected = null;
    this.finished = false;
    this.level = "T1";
    this.draw();
    this.onChange("marks");
  }

  setMode(mode: Mode): void {
    this.mode = mode;
    this.finished = false;
    this.draw();
    this.onChange("level");
  }

  /** Choose the level the next click places: its landmark (if any) becomes the selection, so that
   * Delete removes the chosen level's landmark, or nothing. */
  setLevel(level: Level): void {
    this.level = level;
    this.finished = false;
    this.notice = null;
    const m = this.marks.get(level);
    const kinds: Mode[] = [this.mode, "point", "corners", "pedicles"];
    const kind = m && kinds.find((k) => (k === "point" ? !!m.point : !!m[k]?.length));
    this.selected = kind ? { level, kind, index: 0 } : null;
    this.draw();
    this.onChange("level");
  }

  /** What the next click removes from the current level's mark, in a few words ("midpoint", "four
   * corners", "2 corners"), or null: a midpoint replaces the level's corners and four corners its
   * midpoint (the payload takes one or the other), a complete set of the mode's points is started again. */
  private replaces(): string | null {
    const m = this.marks.get(this.level);
    if (this.finished || !m) return null;
    const corners = (n: number): string => (n === 4 ? "four corners" : `${n} corner${n === 1 ? "" : "s"}`);
    if (this.mode === "point") return m.point ? "midpoint" : m.corners?.length ? corners(m.corners.length) : null;
    const list = m[this.mode];
    const full = MODE_PARTS[this.mode];
    if (list && list.length > 0 && list.length < full) return null; // the next point of an unfinished set
    const gone = [list?.length === full ? (this.mode === "corners" ? "four corners" : "pedicles") : null,
      this.mode === "corners" && m.point ? "midpoint" : null].filter(Boolean);
    return gone.length ? gone.join(" and ") : null;
  }

  /** What the next click places, in words. */
  nextPart(): string {
    if (this.finished) return `nothing: ${this.level} is complete (choose a level to place again)`;
    const m = this.marks.get(this.level);
    const gone = this.replaces();
    const again = gone ? `, replacing ${this.level}'s ${gone}` : "";
    if (this.mode === "point") return `the top endplate midpoint of ${this.level}${again}`;
    const list = this.mode === "corners" ? m?.corners : m?.pedicles;
    const names = this.mode === "corners" ? CORNER_NAMES : PEDICLE_NAMES;
    const i = list && list.length < names.length ? list.length : 0;
    return `the ${names[i]}${this.mode === "corners" ? " corner" : ""} of ${this.level}${again}`;
  }

  /** The role of the next click in a few words, drawn at the cursor (e.g. "T3 top-right", "T3 midpoint,
   * replaces its four corners"). */
  role(): string {
    return this.nextRole();
  }

  private nextRole(): string {
    if (this.finished) return `${this.level} complete`;
    const gone = this.replaces();
    const role = this.mode === "point" ? `${this.level} midpoint`
      : this.nextPart().split(" of ")[0].replace("the ", `${this.level} `).replace(" corner", "");
    return gone ? `${role}, replaces its ${gone}` : role;
  }

  /** Why the last click placed nothing (said at the cursor and in the panel's prompt), or null. */
  get placedNothing(): string | null {
    return this.notice;
  }

  /** Say, at the cursor, why a click placed nothing. */
  private refuse(words: string): void {
    this.notice = words;
    this.draw();
    this.onChange("level");
  }

  place(p: Vec2): void {
    if (!this.extent) return;
    if (this.loading) return this.refuse(`Nothing placed: ${this.loading} is still loading`);
    if (this.finished) return this.refuse(`Nothing placed: ${this.level} is complete`);
    const [w, h] = [this.extent.width, this.extent.height];
    if (!(p[0] >= 0 && p[0] <= w && p[1] >= 0 && p[1] <= h)) {
      // a click beside the film is not a landmark at its edge
      return this.refuse(`Nothing placed: the click is outside the ${this.source ? "film" : "frame"}`);
    }
    this.notice = null;
    this.remember();
    const q: Vec2 = [round1(Math.min(this.extent.width, Math.max(0, p[0]))), round1(Math.min(this.extent.height, Math.max(0, p[1])))];
    const m = this.marks.get(this.level) ?? {};
    let done = false;
    if (this.mode === "point") {
      m.point = q;
      delete m.corners;
      done = true;
      this.selected = { level: this.level, kind: "point", index: 0 };
    } else {
      const key = this.mode;
      const full = MODE_PARTS[key];
      const list = m[key] && m[key].length < full ? m[key] : [];
      list.push(q);
      m[key] = list;
      if (key === "corners") delete m.point;
      done = list.length === full;
      this.selected = { level: this.level, kind: key, index: list.length - 1 };
    }
    this.marks.set(this.level, m);
    if (done) {
      // On to the next level down that has nothing of this mode yet; when every level below is
      // placed (the last one, or a level placed again in the middle), stay: "complete".
      const next = this.nextUnplaced(this.level);
      if (next) this.level = next;
      else this.finished = true;
    }
    this.draw();
    this.onChange("marks");
  }

  /** Whether `level` has a complete mark of the current mode: its pedicles in pedicle mode, else its
   * endplate midpoint or four corners. */
  private placedInMode(level: Level): boolean {
    const m = this.marks.get(level);
    if (this.mode === "pedicles") return m?.pedicles?.length === 2;
    return !!m?.point || m?.corners?.length === 4;
  }

  /** The first level below `level` without a complete mark of the current mode, or null. */
  nextUnplaced(level: Level): Level | null {
    return LEVELS.slice(LEVELS.indexOf(level) + 1).find((lv) => !this.placedInMode(lv)) ?? null;
  }

  /** Remove the selected point's mark (a point, a set of corners or the pedicles); nothing when none is selected. */
  removeSelected(): void {
    const target = this.selected;
    if (!target) return;
    const m = this.marks.get(target.level);
    if (!m) return;
    this.remember();
    delete m[target.kind];
    if (!m.point && !m.corners && !m.pedicles) this.marks.delete(target.level);
    this.level = target.level;
    this.finished = false;
    this.selected = null;
    this.draw();
    this.onChange("marks");
  }

  private handles(): (Handle & { p: Vec2 })[] {
    const out: (Handle & { p: Vec2 })[] = [];
    for (const [level, m] of this.marks) {
      for (const kind of ["point", "corners", "pedicles"] as const) {
        const pts = kind === "point" ? (m.point ? [m.point] : []) : (m[kind] ?? []);
        pts.forEach((p, index) => out.push({ level, kind, index, p }));
      }
    }
    return out;
  }

  private pointOf(h: Handle): Vec2 | undefined {
    const m = this.marks.get(h.level);
    if (!m) return undefined;
    return h.kind === "point" ? m.point : m[h.kind]?.[h.index];
  }

  private movePoint(h: Handle, p: Vec2): void {
    const m = this.marks.get(h.level);
    if (!m || !this.extent) return;
    const q: Vec2 = [round1(Math.min(this.extent.width, Math.max(0, p[0]))), round1(Math.min(this.extent.height, Math.max(0, p[1])))];
    if (h.kind === "point") m.point = q;
    else if (m[h.kind]) m[h.kind]![h.index] = q;
  }

  // ---------------------------------------------------------------- view

  fit(): void {
    this.fitted = true;
    this.layout();
  }

  zoomBy(factor: number, at?: Vec2): void {
    if (!this.extent) return;
    const c = at ?? this.centre();
    const before = this.toScreen(c);
    this.scale = Math.min(16, Math.max(0.02, this.scale * factor));
    this.origin = [c[0] - before[0] / this.scale, c[1] - before[1] / this.scale];
    this.fitted = false;
    this.draw();
    this.onChange("view");
  }

  get zoomPercent(): number {
    return Math.round(this.scale * (window.devicePixelRatio || 1) * 100);
  }

  private centre(): Vec2 {
    const r = this.canvas.getBoundingClientRect();
    return [this.origin[0] + r.width / 2 / this.scale, this.origin[1] + r.height / 2 / this.scale];
  }

  private layout(): void {
    const rect = this.canvas.getBoundingClientRect();
    const ratio = window.devicePixelRatio || 1;
    this.canvas.width = Math.max(1, Math.round(rect.width * ratio));
    this.canvas.height = Math.max(1, Math.round(rect.height * ratio));
    if (this.fitted && this.extent) {
      this.scale = Math.min(rect.width / this.extent.width, rect.height / this.extent.height) || 1;
      this.origin = [
        -(rect.width / this.scale - this.extent.width) / 2,
        -(rect.height / this.scale - this.extent.height) / 2,
      ];
    }
    this.draw();
  }

  private landmarkExtent(): { width: number; height: number } | null {
    const pts = this.handles().map((h) => h.p);
    if (!pts.length) return null;
    return { width: Math.max(...pts.map((p) => p[0])) * 1.15 + 20, height: Math.max(...pts.map((p) => p[1])) * 1.08 + 20 };
  }

  toImage(clientX: number, clientY: number): Vec2 {
    const r = this.canvas.getBoundingClientRect();
    return [this.origin[0] + (clientX - r.left) / this.scale, this.origin[1] + (clientY - r.top) / this.scale];
  }

  /** CSS px inside the canvas of an image point. */
  toScreen(p: Vec2): Vec2 {
    return [(p[0] - this.origin[0]) * this.scale, (p[1] - this.origin[1]) * this.scale];
  }

  private hit(clientX: number, clientY: number): Handle | null {
    const r = this.canvas.getBoundingClientRect();
    const x = clientX - r.left;
    const y = clientY - r.top;
    let best: Handle | null = null;
    let bestD = HIT_PX;
    for (const h of this.handles()) {
      const s = this.toScreen(h.p);
      const d = Math.hypot(s[0] - x, s[1] - y);
      if (d < bestD) [best, bestD] = [h, d];
    }
    return best;
  }

  // ---------------------------------------------------------------- input

  private onDown(e: PointerEvent): void {
    if (!this.extent || e.button !== 0) return;
    this.canvas.focus({ preventScroll: true });
    this.canvas.setPointerCapture(e.pointerId);
    // A press only says what a drag would move; a click (no drag) always places the next landmark.
    const handle = this.hit(e.clientX, e.clientY);
    this.drag = { handle, start: [e.clientX, e.clientY], origin: [...this.origin], moved: false, shift: e.shiftKey };
    this.draw();
  }

  private onMove(e: PointerEvent): void {
    if (!this.extent) return;
    this.cursor = this.toImage(e.clientX, e.clientY);
    const d = this.drag;
    if (d) {
      const dx = e.clientX - d.start[0];
      const dy = e.clientY - d.start[1];
      if (!d.moved && Math.hypot(dx, dy) > DRAG_PX) {
        d.moved = true;
        if (d.handle) {
          this.remember();
          this.selected = d.handle;
        }
      }
      if (d.moved && d.handle) this.movePoint(d.handle, this.cursor);
      else if (d.moved) {
        this.origin = [d.origin[0] - dx / this.scale, d.origin[1] - dy / this.scale];
        this.fitted = false;
      }
    }
    this.draw();
  }

  private onUp(e: PointerEvent): void {
    const d = this.drag;
    this.drag = null;
    if (!d || !this.extent) return;
    if (d.moved && d.handle) this.onChange("marks");
    else if (d.moved) this.onChange("view");
    else if (d.shift) {
      // Shift+click selects the point under the cursor (for Alt+arrows or Delete), placing nothing.
      this.selected = d.handle;
      this.draw();
    } else this.place(this.toImage(e.clientX, e.clientY));
  }

  private onWheel(e: WheelEvent): void {
    if (!this.extent) return;
    e.preventDefault();
    this.zoomBy(e.deltaY < 0 ? 1.25 : 0.8, this.toImage(e.clientX, e.clientY));
  }

  /** Arrow step in image px: about one CSS px at fit, ten with Shift. */
  step(shift: boolean): number {
    const h = this.extent?.height ?? 400;
    return Math.max(1, Math.round(h / 400)) * (shift ? 10 : 1);
  }

  private onKey(e: KeyboardEvent): void {
    // Undo and redo work without a film too: Undo after "Close film" brings the film back.
    if ((e.ctrlKey || e.metaKey) && (e.key.toLowerCase() === "z" || e.key.toLowerCase() === "y")) {
      if (e.shiftKey || e.key.toLowerCase() === "y") this.redo();
      else this.undo();
      e.preventDefault();
      return;
    }
    if (!this.extent) return;
    const step = this.step(e.shiftKey);
    const moves: Record<string, Vec2> = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowUp: [0, -step], ArrowDown: [0, step] };
    const c = this.cursor ?? [this.extent.width / 2, this.extent.height / 2];
    if (e.key in moves) {
      const [dx, dy] = moves[e.key];
      if (e.altKey && this.selected) {
        const p = this.pointOf(this.selected);
        if (p) {
          if (!e.repeat) this.remember();
          this.movePoint(this.selected, [p[0] + dx, p[1] + dy]);
        }
        this.onChange("marks");
      } else {
        this.cursor = [Math.min(this.extent.width, Math.max(0, c[0] + dx)), Math.min(this.extent.height, Math.max(0, c[1] + dy))];
        this.keepInView(this.cursor);
        this.onCrosshair?.();
      }
      this.draw();
    } else if (e.key === "Enter" || e.key === " ") {
      this.place(c);
    } else if (e.key === "Delete" || e.key === "Backspace") {
      this.removeSelected();
    } else if (e.key === "PageDown" || e.key === "]") {
      this.setLevel(LEVELS[Math.min(LEVELS.length - 1, LEVELS.indexOf(this.level) + 1)]);
    } else if (e.key === "PageUp" || e.key === "[") {
      this.setLevel(LEVELS[Math.max(0, LEVELS.indexOf(this.level) - 1)]);
    } else if (e.key === "+" || e.key === "=") {
      this.zoomBy(1.25, c);
    } else if (e.key === "-") {
      this.zoomBy(0.8, c);
    } else if (e.key === "0") {
      this.fit();
      this.onChange("view");
    } else if (e.key === "," || e.key === ".") {
      this.cycleSelection(e.key === "." ? 1 : -1);
    } else if (e.key === "Escape") {
      this.selected = null;
      this.draw();
    } else {
      return;
    }
    e.preventDefault();
  }

  /** Select the next (+1) or previous (−1) point, in level order, and bring it into view. */
  private cycleSelection(step: number): void {
    const order: Record<Mode, number> = { point: 0, corners: 1, pedicles: 2 };
    const all = this.handles().sort((a, b) => LEVELS.indexOf(a.level) - LEVELS.indexOf(b.level) || order[a.kind] - order[b.kind] || a.index - b.index);
    if (!all.length) return;
    const at = all.findIndex((h) => this.isSelected(h.level, h.kind, h.index));
    const next = all[at < 0 ? (step > 0 ? 0 : all.length - 1) : (at + step + all.length) % all.length];
    this.selected = { level: next.level, kind: next.kind, index: next.index };
    this.keepInView(next.p);
    this.draw();
  }

  private keepInView(p: Vec2): void {
    const r = this.canvas.getBoundingClientRect();
    const s = this.toScreen(p);
    const margin = 30;
    if (s[0] < margin || s[0] > r.width - margin || s[1] < margin || s[1] > r.height - margin) {
      this.origin = [p[0] - r.width / 2 / this.scale, p[1] - r.height / 2 / this.scale];
      this.fitted = false;
    }
  }

  // ---------------------------------------------------------------- drawing

  draw(): void {
    const ctx = this.canvas.getContext("2d");
    if (!ctx) return;
    const ratio = this.canvas.width / Math.max(1, this.canvas.getBoundingClientRect().width);
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.fillStyle = "#111";
    ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
    if (!this.extent) return;
    // CSS px per image px and the image point at the top-left corner (read by the browser tests)
    this.canvas.dataset.view = `${this.scale.toFixed(4)} ${this.origin[0].toFixed(1)} ${this.origin[1].toFixed(1)}`;
    this.canvas.dataset.cursor = this.cursor ? `${this.cursor[0]} ${this.cursor[1]}` : "";
    this.canvas.dataset.next = this.notice ?? this.nextRole();
    const s = this.selected;
    this.canvas.dataset.selected = s ? `${s.level} ${s.kind === "corners" ? CORNER_NAMES[s.index] : s.kind === "pedicles" ? PEDICLE_NAMES[s.index] : "midpoint"}` : "";
    const k = this.scale * ratio;
    ctx.setTransform(k, 0, 0, k, -this.origin[0] * k, -this.origin[1] * k);
    if (this.raster) {
      ctx.imageSmoothingEnabled = this.scale < 2;
      ctx.drawImage(this.raster, 0, 0);
    } else {
      ctx.fillStyle = "#2a2f36";
      ctx.fillRect(0, 0, this.extent.width, this.extent.height);
    }
    ctx.setTransform(ratio, 0, 0, ratio, 0, 0);
    this.canvas.dataset.blank = this.raster ? "" : (this.blankNote ?? "");
    if (!this.raster && this.blankNote) this.note(ctx, this.blankNote);
    ctx.lineWidth = 1.5;
    ctx.font = "600 12px system-ui, sans-serif";
    ctx.textBaseline = "middle";
    const S = (p: Vec2): Vec2 => this.toScreen(p);
    // the centreline through the midpoints
    const mids = LEVELS.flatMap((lv) => {
      const m = this.marks.get(lv);
      const p = m?.point ?? (m?.corners && m.corners.length >= 2 ? [(m.corners[0][0] + m.corners[1][0]) / 2, (m.corners[0][1] + m.corners[1][1]) / 2] as Vec2 : null);
      return p ? [S(p)] : [];
    });
    if (mids.length > 1) {
      ctx.strokeStyle = "rgba(255, 208, 0, 0.7)";
      ctx.beginPath();
      mids.forEach((p, i) => (i ? ctx.lineTo(p[0], p[1]) : ctx.moveTo(p[0], p[1])));
      ctx.stroke();
    }
    const problems = new Map<Level, string[]>();
    for (const p of this.problems()) problems.set(p.level, [...(problems.get(p.level) ?? []), p.short]);
    this.canvas.dataset.problems = [...problems.keys()].join(" ");
    for (const [level, m] of this.marks) {
      const current = level === this.level;
      const wrong = problems.get(level);
      if (m.corners?.length) {
        const c = m.corners.map(S);
        ctx.strokeStyle = wrong ? "#ff3b3b" : current ? "#00e5ff" : "#ffd000";
        ctx.lineWidth = wrong ? 3 : 1.5;
        ctx.beginPath();
        const order = [0, 1, 3, 2].filter((i) => i < c.length);
        order.forEach((i, j) => (j ? ctx.lineTo(c[i][0], c[i][1]) : ctx.moveTo(c[i][0], c[i][1])));
        if (c.length === 4) ctx.closePath();
        ctx.stroke();
        c.forEach((p, i) => this.dot(ctx, p, "#ffd000", this.isSelected(level, "corners", i)));
        const at: Vec2 = [Math.max(...c.map((p) => p[0])) + 8, c[0][1]];
        this.label(ctx, level, at);
        if (wrong) this.label(ctx, `⚠ ${wrong.join("; ")}`, [at[0] + 30, at[1]], "#ff6b6b");
      }
      if (m.point) {
        const p = S(m.point);
        this.dot(ctx, p, "#ffd000", this.isSelected(level, "point", 0));
        this.label(ctx, level, [p[0] + 9, p[1]]);
        if (wrong && !m.corners) this.label(ctx, `⚠ ${wrong.join("; ")}`, [p[0] + 39, p[1]], "#ff6b6b");
      }
      (m.pedicles ?? []).forEach((q, i) => {
        const p = S(q);
        this.dot(ctx, p, "#7CFC00", this.isSelected(level, "pedicles", i), true);
      });
    }
    // landmarks the service refused: a red ring around each, with a word beside it
    const refused = this.refusedLevels();
    this.canvas.dataset.refused = refused.join(" ");
    for (const level of refused) {
      const m = this.marks.get(level);
      const pts = [m?.point, ...(m?.corners ?? []), ...(m?.pedicles ?? [])].filter((p): p is Vec2 => !!p).map(S);
      if (!pts.length) continue;
      const c: Vec2 = [pts.reduce((a, p) => a + p[0], 0) / pts.length, pts.reduce((a, p) => a + p[1], 0) / pts.length];
      const r = Math.max(14, ...pts.map((p) => Math.hypot(p[0] - c[0], p[1] - c[1]) + 9));
      ctx.strokeStyle = REFUSED_RED;
      ctx.lineWidth = 3;
      ctx.beginPath();
      ctx.arc(c[0], c[1], r, 0, 2 * Math.PI);
      ctx.stroke();
      this.label(ctx, `✖ ${level} refused by the service`, [c[0] - r, c[1] - r - 9], "#ff6b6b");
    }
    if (this.cursor) {
      const [x, y] = S(this.cursor);
      const r = 11;
      ctx.strokeStyle = "#00e5ff";
      ctx.lineWidth = 1.5;
      ctx.beginPath();
      ctx.moveTo(x - r, y);
      ctx.lineTo(x + r, y);
      ctx.moveTo(x, y - r);
      ctx.lineTo(x, y + r);
      ctx.stroke();
      this.label(ctx, this.notice ?? this.nextRole(), [x + r + 4, y - 10], this.notice ? "#ff6b6b" : "#00e5ff");
    }
  }

  /** A few lines of text at the top of the canvas, wrapped to its width. */
  private note(ctx: CanvasRenderingContext2D, text: string): void {
    const width = this.canvas.getBoundingClientRect().width - 24;
    ctx.font = "500 13px system-ui, sans-serif";
    const lines: string[] = [];
    for (const word of text.split(" ")) {
      const last = lines[lines.length - 1];
      if (last !== undefined && ctx.measureText(`${last} ${word}`).width <= width) lines[lines.length - 1] = `${last} ${word}`;
      else lines.push(word);
    }
    lines.forEach((line, i) => this.label(ctx, line, [12, 18 + i * 17], "#ffffff"));
    ctx.font = "600 12px system-ui, sans-serif";
  }

  private isSelected(level: Level, kind: Mode, index: number): boolean {
    const s = this.selected;
    return !!s && s.level === level && s.kind === kind && s.index === index;
  }

  private dot(ctx: CanvasRenderingContext2D, p: Vec2, fill: string, selected: boolean, square = false): void {
    ctx.fillStyle = fill;
    ctx.strokeStyle = "#000";
    ctx.lineWidth = 1.5;
    ctx.beginPath();
    if (square) ctx.rect(p[0] - 4, p[1] - 4, 8, 8);
    else ctx.arc(p[0], p[1], 4.5, 0, 2 * Math.PI);
    ctx.fill();
    ctx.stroke();
    if (selected) {
      ctx.strokeStyle = "#ff4fd8";
      ctx.lineWidth = 2;
      ctx.beginPath();
      ctx.arc(p[0], p[1], 8, 0, 2 * Math.PI);
      ctx.stroke();
    }
  }

  private label(ctx: CanvasRenderingContext2D, text: string, at: Vec2, colour = "#ffd000"): void {
    ctx.lineWidth = 3;
    ctx.strokeStyle = "#000";
    ctx.strokeText(text, at[0], at[1]);
    ctx.fillStyle = colour;
    ctx.fillText(text, at[0], at[1]);
    ctx.lineWidth = 1.5;
  }
}

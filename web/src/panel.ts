// The controls of one film (PA or lateral): open a DICOM, PNG or JPEG file, what its header says,
// the pixel spacing (asked for when the file has none), window/level, click mode, level, and the
// landmark editor. Builds its own DOM into a container; ids are prefixed with the view's name.
import { DicomError, GEOMETRY_KEYS, filmSpacing, parseFilm, personName, viewAcquisition, withoutGeometry, type Acquisition, type DicomFilm } from "./dicom";
import { DIRECTION_WORDS, ORIENTATION_LABELS, orderAlongAnother, orientationFromOrder, orientationProblems, type OrientationProblem } from "./checks";
import { FilmEditor, type EditorState, type Mark, type Mode, type OuterEdit } from "./film";
import { LEVELS, type Level, type Vec2, type ViewPayload } from "./types";

export type ViewName = "pa" | "lateral";
const TITLES: Record<ViewName, string> = { pa: "PA (frontal) film", lateral: "Lateral film" };
const DEFAULT_ORIENTATION: Record<ViewName, [string, string]> = { pa: ["L", "F"], lateral: ["A", "F"] };
export { DIRECTION_WORDS, ORIENTATION_LABELS };
/** View Position (0018,5101) defined terms, PS3.3 §C.8.11.5.1.1: frontal and lateral projections. */
const FRONTAL_POSITIONS = new Set(["PA", "AP"]);
const LATERAL_POSITIONS = new Set(["LL", "RL", "LATERAL"]);

/** A header's spacing as the field shows it: six significant digits (IPS/ERMF reads 0.333333, not
 * 0.33333333333333337). */
const spacingText = (mm: number): string => String(Number(mm.toPrecision(6)));
/** A typed spacing this close to the header's, relative, is the header's (its six digits as shown): the
 * header's exact value is sent. */
const SPACING_SHOWN_TOLERANCE = 1e-5;

/** When a DICOM film's header says it is the other view than the panel it was opened in: the words of
 * a warning (View Position, else Patient Orientation's column direction), or null. Not a refusal:
 * View Position is often missing or wrong. */
export function viewMismatch(view: ViewName, film: DicomFilm): string | null {
  const position = (film.viewPosition ?? "").trim().toUpperCase();
  const column = film.orientation?.[0];
  const other = view === "pa" ? "lateral" : "PA (frontal)";
  const here = view === "pa" ? "PA (frontal)" : "lateral";
  let says: string | null = null;
  if (view === "pa" && LATERAL_POSITIONS.has(position)) says = `View Position ${position} (a lateral film)`;
  else if (view === "lateral" && FRONTAL_POSITIONS.has(position)) says = `View Position ${position} (a frontal film)`;
  else if (!position && view === "pa" && (column === "A" || column === "P")) says = `columns toward ${column} (a lateral film)`;
  else if (!position && view === "lateral" && (column === "L" || column === "R")) says = `columns toward ${column} (a frontal film)`;
  return says
    ? `Check the film: its header says ${says}, but it is open as the ${here} film. If it is the ${other} film, open it there instead; if the header is wrong, carry on.`
    : null;
}

function el<K extends keyof HTMLElementTagNameMap>(tag: K, attrs: Record<string, string> = {}, text?: string): HTMLElementTagNameMap[K] {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) node.setAttribute(k, v);
  if (text !== undefined) node.textContent = text;
  return node;
}

function labelled(id: string, label: string, input: HTMLElement, help?: string): HTMLElement {
  const row = el("div", { class: "row" });
  row.append(el("label", { for: id }, label), input);
  if (help) {
    input.setAttribute("aria-describedby", `${id}-help`);
    row.append(el("span", { id: `${id}-help`, class: "help" }, help));
  }
  return row;
}

/** Whether a key event's target takes typed text (its own Ctrl+Z undoes its typing). */
function typesText(target: EventTarget | null): boolean {
  if (target instanceof HTMLTextAreaElement) return true;
  if (target instanceof HTMLElement && target.isContentEditable) return true;
  return target instanceof HTMLInputElement && !["button", "checkbox", "radio", "file", "submit", "reset", "range", "color"].includes(target.type);
}

export class FilmPanel {
  readonly editor: FilmEditor;
  dicom: DicomFilm | null = null;
  fileName: string | null = null;
  private readonly spacing: HTMLInputElement;
  private readonly header: HTMLElement;
  private readonly wlCenter: HTMLInputElement;
  private readonly wlWidth: HTMLInputElement;
  private readonly invert: HTMLInputElement;
  private readonly wlRow: HTMLElement;
  private readonly levelSelect: HTMLSelectElement;
  private readonly prompt: HTMLElement;
  private readonly status: HTMLElement;
  /** The crosshair's place in words (a polite live region, visually hidden). */
  private readonly crosshair: HTMLElement;
  private crosshairTimer: number | undefined;
  /** When the crosshair's place was last said (ms, performance.now()). */
  private crosshairSaid = -Infinity;
  private readonly error: HTMLElement;
  private readonly warning: HTMLElement;
  private readonly fileInput: HTMLInputElement;
  private readonly ignoreGeometry: HTMLInputElement;
  private readonly ignoreRow: HTMLElement;
  /** The orientation controls: the patient direction toward the image's right, and toward its bottom. */
  private readonly orient: [HTMLSelectElement, HTMLSelectElement];
  private readonly orientHelp: HTMLElement;
  private readonly orientError: HTMLElement;
  /** What the service would refuse in the orientation, found before sending (checks.ts orientationProblems). */
  private readonly orientCheck: HTMLElement;
  /** The landmarks in order along another direction than the orientation's: the orientation likely wrong
   * (checks.ts orientationFromOrder), said here rather than blaming their order. */
  private readonly orientOrder: HTMLElement;
  /** The service's refusal of the orientation sent, in words, while it stands; null: none. */
  private refusal: string | null = null;
  /** The orientation chosen on the page (the controls), over the header's or the reopened job's; null: not chosen. */
  private chosen: [string, string] | null = null;
  /** Said in the status until the next change of the landmarks: landmarks dropped with the film they were
   * placed on, a closed film (and how to bring it back), a relabelling done or refused. */
  private dropNote: string | null = null;
  /** The landmarks are a reopened job's (on a blank frame, or on the job's film opened under them). */
  fromJob = false;
  /** The level a film opened in this panel starts at (null: as the editor left it); unset: T1. */
  startLevel: (() => Level | null) | null = null;
  private readonly zoomOut: HTMLOutputElement;
  private readonly undoButton: HTMLButtonElement;
  private readonly redoButton: HTMLButtonElement;
  /** Set when a job is reopened without its film: the spacing and units of its payload. */
  reopened: ViewPayload | null = null;
  /** The reopened job's film as its `study` names it (this view's SOP Instance UID, the Study Instance
   * UID, the Patient ID): a DICOM film opened under the job's landmarks that says it is another is warned
   * about, and one of another patient is not sent with them. */
  private jobFilm: JobFilm | null = null;
  /** Set when the reopened job's landmarks were kept over a film of another patient: why, in words, and
   * those landmarks; not sent while any of them is still there unchanged. */
  private otherPatient: { words: string; marks: Set<string> } | null = null;

  constructor(readonly view: ViewName, container: HTMLElement, private readonly onChange: () => void) {
    const id = (s: string): string => `${view}-${s}`;
    const title = TITLES[view];
    const file = el("input", { id: id("file"), type: "file", accept: ".dcm,application/dicom,image/png,image/jpeg,*/*" });
    this.spacing = el("input", { id: id("spacing"), type: "number", min: "0.001", max: "10", step: "any", placeholder: "required" });
    this.header = el("dl", { id: id("header"), class: "dicom-header" });
    this.error = el("p", { id: id("error"), class: "error", role: "alert" });
    this.error.hidden = true;
    this.warning = el("p", { id: id("warning"), class: "warning", role: "status" });
    this.warning.hidden = true;
    this.fileInput = file;
    this.ignoreGeometry = el("input", { id: id("ignore-geometry"), type: "checkbox" });
    this.ignoreRow = el("div", { class: "row inline-check" });
    this.ignoreRow.append(this.ignoreGeometry, el("label", { for: id("ignore-geometry") }, "Ignore header geometry"),
      el("span", { id: id("ignore-geometry-help"), class: "help" },
        "When the header's magnification (ERMF), SID or SOD is wrong: the film is then sent without them, as a film whose header gives none (an uncalibrated film's scale estimated)."));
    this.ignoreGeometry.setAttribute("aria-describedby", id("ignore-geometry-help"));
    this.ignoreRow.hidden = true;
    this.wlCenter = el("input", { id: id("wl-center"), type: "number", step: "any" });
    this.wlWidth = el("input", { id: id("wl-width"), type: "number", step: "any", min: "1" });
    this.invert = el("input", { id: id("wl-invert"), type: "checkbox" });
    const wlAuto = el("button", { type: "button", id: id("wl-auto") }, "Full range");
    const wlHeader = el("button", { type: "button", id: id("wl-header") }, "Header window");
    this.wlRow = el("fieldset", { class: "wl" });
    this.wlRow.append(
      el("legend", {}, "Window / level"),
      labelled(id("wl-center"), "Level (centre)", this.wlCenter),
      labelled(id("wl-width"), "Window (width)", this.wlWidth),
      (() => {
        const r = el("div", { class: "row" });
        r.append(this.invert, el("label", { for: id("wl-invert") }, "Invert (white is low)"), wlAuto, wlHeader);
        return r;
      })(),
    );
    this.wlRow.hidden = true;

    // The film's orientation, as its header says or the default, changed here (the landmarks stay where
    // they are): a film displayed mirrored is sent with the other depth label, not clicked again.
    this.orient = (["column", "row"] as const).map((axis) => {
      const select = el("select", { id: id(`orientation-${axis}`), "aria-describedby": id("orientation-help") });
      for (const d of "LRAPHF") select.append(el("option", { value: d }, `${d} (${DIRECTION_WORDS[d]})`));
      select.addEventListener("change", () => {
        this.chosen = [this.orient[0].value, this.orient[1].value];
        this.refuseOrientation(null); // the refusal was of the orientation sent
        if (this.dicom) this.fillHeader();
        this.update();
        this.onChange();
      });
      return select;
    }) as [HTMLSelectElement, HTMLSelectElement];
    this.orientHelp = el("p", { id: id("orientation-help"), class: "help" });
    this.orientError = el("p", { id: id("orientation-error"), class: "error", role: "alert" });
    this.orientError.hidden = true;
    this.orientCheck = el("p", { id: id("orientation-check"), class: "error", "aria-live": "polite" });
    this.orientCheck.hidden = true;
    this.orientOrder = el("p", { id: id("orientation-order"), class: "error", "aria-live": "polite" });
    this.orientOrder.hidden = true;
    const orientation = el("fieldset", { id: id("orientation"), class: "orientation" });
    orientation.append(el("legend", {}, "Orientation (DICOM Patient Orientation)"),
      labelled(id("orientation-column"), ORIENTATION_LABELS[0], this.orient[0]),
      labelled(id("orientation-row"), ORIENTATION_LABELS[1], this.orient[1]), this.orientHelp, this.orientCheck, this.orientOrder, this.orientError);

    const modes = el("fieldset", { class: "modes" });
    modes.append(el("legend", {}, "Click mode"));
    const modeNames: [Mode, string][] = [["point", "Endplate midpoint"], ["corners", "Four corners"], ["pedicles", "Pedicles"]];
    for (const [mode, label] of modeNames) {
      if (mode === "pedicles" && view !== "pa") continue; // the engine takes pedicles on the PA view only
      const r = el("input", { type: "radio", name: id("mode"), id: id(`mode-${mode}`), value: mode });
      if (mode === "point") r.setAttribute("checked", "");
      r.addEventListener("change", () => this.editor.setMode(mode));
      modes.append(r, el("label", { for: id(`mode-${mode}`), class: "inline" }, label));
    }
    this.levelSelect = el("select", { id: id("level") });
    for (const lv of LEVELS) this.levelSelect.append(el("option", { value: lv }, lv));
    this.levelSelect.addEventListener("change", () => this.editor.setLevel(this.levelSelect.value as Level));

    const canvas = el("canvas", {
      id: id("canvas"), tabindex: "0", role: "application", "aria-roledescription": "landmark editor",
      "aria-label": `${title}: no film open`, "aria-describedby": id("keys"), class: "film-canvas",
    });
    this.prompt = el("p", { id: id("prompt"), class: "prompt", "aria-live": "polite" }, `Open the ${view === "pa" ? "PA" : "lateral"} film to start.`);
    this.status = el("p", { id: id("status"), class: "summary", "aria-live": "polite" });
    // Where the keyboard's crosshair is, for a screen reader (the canvas itself says nothing): updated as it
    // moves by the arrow keys, at most every CROSSHAIR_SAY_MS (and once more where it stops), not by the mouse.
    this.crosshair = el("p", { id: id("crosshair"), class: "visually-hidden", "aria-live": "polite", "aria-atomic": "true" });
    const keys = el("p", { id: id("keys"), class: "help" },
      "Mouse: a click always places the next point (its role is shown at the cursor), even on another point; " +
      "drag a point to move it, drag elsewhere to pan, Shift+click selects a point, wheel zooms. " +
      "Keyboard: arrow keys move the crosshair (Shift: ten times faster), Enter places, Delete removes the selected mark, " +
      "comma and period select the previous and next point, Alt+arrows move the selected point, Ctrl+Z undoes, Ctrl+Shift+Z redoes, [ and ] change level, + and − zoom, 0 fits the film.");
    const buttons = el("div", { class: "button-row" });
    const undo = (this.undoButton = el("button", { type: "button", id: id("undo"), "aria-keyshortcuts": "Control+Z" }, "Undo"));
    const redo = (this.redoButton = el("button", { type: "button", id: id("redo"), "aria-keyshortcuts": "Control+Shift+Z" }, "Redo"));
    const del = el("button", { type: "button", id: id("delete") }, "Delete selected");
    const clear = el("button", { type: "button", id: id("clear") }, "Clear all");
    const close = el("button", { type: "button", id: id("close"), "aria-describedby": id("status") }, "Close film");
    const fit = el("button", { type: "button", id: id("fit") }, "Fit film");
    const zin = el("button", { type: "button", id: id("zoom-in"), "aria-label": "Zoom in" }, "+");
    const zout = el("button", { type: "button", id: id("zoom-out"), "aria-label": "Zoom out" }, "−");
    this.zoomOut = el("output", { id: id("zoom"), "aria-live": "off" });
    buttons.append(undo, redo, del, clear, close, fit, zout, zin, this.zoomOut);

    // A radiographer who started one level off relabels every landmark of the film at once (undoable).
    const shiftUp = el("button", { type: "button", id: id("shift-up"), title: "Every landmark of this film one level up the spine: T2's become T1's, and so on (Undo takes it back)" }, "All levels up one (T2 → T1)");
    const shiftDown = el("button", { type: "button", id: id("shift-down"), title: "Every landmark of this film one level down the spine: T1's become T2's, and so on (Undo takes it back)" }, "All levels down one (T1 → T2)");
    const shifts = el("div", { class: "row shift-levels" });
    shifts.append(shiftUp, shiftDown);
    const tools = el("div", { class: "film-tools" });
    tools.append(modes, labelled(id("level"), "Level", this.levelSelect), shifts);
    container.append(
      labelled(id("file"), `${title} (DICOM, PNG or JPEG)`, file),
      this.error,
      this.warning,
      this.header,
      this.ignoreRow,
      labelled(id("spacing"), "Pixel spacing (mm per pixel)", this.spacing,
        "Read from the DICOM header when it has one; a PNG or JPEG does not carry it: enter it (e.g. from the PACS)."),
      orientation, this.wlRow, tools, this.prompt, canvas, this.crosshair, keys, buttons, this.status,
    );

    this.editor = new FilmEditor(canvas, (what) => {
      if (what !== "view") this.levelSelect.value = this.editor.level;
      if (what === "marks" && !this.settingSource) this.dropNote = null;
      this.update();
      if (what === "marks") this.onChange();
    });
    this.editor.onCrosshair = () => this.sayCrosshair();
    file.addEventListener("change", () => void this.open(file.files?.[0]));
    this.ignoreGeometry.addEventListener("change", () => {
      // the spacing field follows the header's reading it showed (its magnification taken out or not)
      const d = this.dicom;
      const shown = d && this.hasGeometry() ? filmSpacing(d, !this.ignoreGeometry.checked).value : null;
      if (d && shown && this.pixelSpacing(shown) === shown) {
        const now = filmSpacing(d, this.ignoreGeometry.checked).value;
        this.spacing.value = now ? spacingText(now[1]) : "";
      }
      this.fillHeader();
      this.update();
      this.onChange();
    });
    this.spacing.addEventListener("input", () => {
      this.update();
      this.onChange();
    });
    const applyWl = (): void => this.editor.setWindow(Number(this.wlCenter.value), Number(this.wlWidth.value), this.invert.checked);
    for (const i of [this.wlCenter, this.wlWidth]) i.addEventListener("input", applyWl);
    this.invert.addEventListener("change", applyWl);
    wlAuto.addEventListener("click", () => {
      if (!this.dicom) return;
      this.wlCenter.value = String(round((this.dicom.min + this.dicom.max) / 2));
      this.wlWidth.value = String(round(Math.max(1, this.dicom.max - this.dicom.min)));
      applyWl();
    });
    wlHeader.addEventListener("click", () => {
      if (!this.dicom) return;
      this.wlCenter.value = String(round(this.dicom.window.center));
      this.wlWidth.value = String(round(this.dicom.window.width));
      applyWl();
    });
    undo.addEventListener("click", () => this.editor.undo());
    redo.addEventListener("click", () => this.editor.redo());
    // Ctrl+Z anywhere in the film's panel undoes its landmarks (the canvas handles its own keys): on a
    // button or a list the browser's own undo would otherwise edit the text field typed in last, out of
    // sight (the pixel spacing, the API key). In a text field it undoes that field's typing, as usual.
    container.addEventListener("keydown", (e) => {
      const key = e.key.toLowerCase();
      if (!(e.ctrlKey || e.metaKey) || (key !== "z" && key !== "y") || e.target === canvas || typesText(e.target)) return;
      if (e.shiftKey || key === "y") this.editor.redo();
      else this.editor.undo();
      e.preventDefault();
    });
    del.addEventListener("click", () => this.editor.removeSelected());
    clear.addEventListener("click", () => this.editor.clear());
    close.addEventListener("click", () => this.close());
    shiftUp.addEventListener("click", () => this.shiftLevels(-1));
    shiftDown.addEventListener("click", () => this.shiftLevels(1));
    fit.addEventListener("click", () => this.editor.fit());
    zin.addEventListener("click", () => this.editor.zoomBy(1.25));
    zout.addEventListener("click", () => this.editor.zoomBy(0.8));
    this.update();
  }

  /** Counts the films asked for: a film read after a newer one was asked for is dropped, not shown. */
  private opening = 0;

  async open(file: File | undefined): Promise<void> {
    if (!file) return;
    const ticket = ++this.opening;
    this.showError(null);
    this.editor.loading = file.name;
    this.update();
    try {
      await this.read(file, () => ticket !== this.opening);
    } finally {
      if (ticket === this.opening) {
        this.editor.loading = null;
        this.update();
        this.editor.draw();
      }
    }
  }

  /** Read and show `file`; `stale()` says that a newer film was asked for meanwhile (then nothing changes). */
  private async read(file: File, stale: () => boolean): Promise<void> {
    const bytes = new Uint8Array(await file.arrayBuffer());
    if (stale()) return;
    const isDicom = bytes.length > 132 && String.fromCharCode(...bytes.subarray(128, 132)) === "DICM";
    // A reopened job's landmarks stay over the film opened under them (its own film, by hand or from
    // the PACS); any other landmarks belong to the film they were placed on and go with it.
    // A reopened job's landmarks in mm without a pixel spacing have no known place on a film (1 px = 1 mm
    // only on the blank frame): they are not put over it as if they were pixels.
    const inMm = this.reopenedInMm();
    const keep = !!this.reopened && !this.editor.source && !inMm;
    // what the panel shows before the film is replaced: Undo brings it back, film and landmarks
    const before = keep ? null : this.capture();
    let dropped = 0;
    let warning: string | null = null;
    let notTheJobs: OtherFilm | null = null;
    try {
      if (isDicom || /\.dcm$/i.test(file.name) || file.type === "application/dicom") {
        const film = parseFilm(bytes, file.name);
        notTheJobs = keep ? otherFilm(this.jobFilm, film) : null;
        this.dicom = film;
        this.spacing.value = film.spacing.value ? spacingText(film.spacing.value[1]) : "";
        this.wlCenter.value = String(round(film.window.center));
        this.wlWidth.value = String(round(film.window.width));
        this.invert.checked = film.monochrome1;
        this.wlRow.hidden = false;
        warning = viewMismatch(this.view, film);
        dropped = this.setSource({ name: file.name, width: film.width, height: film.height, dicom: film, element: null }, keep);
        this.editor.canvas.setAttribute("aria-label",
          `${TITLES[this.view]} ${file.name}: DICOM ${film.photometric}, ${film.width} by ${film.height} pixels.`);
      } else if (/^image\/(png|jpeg)$/.test(file.type)) {
        const url = URL.createObjectURL(file);
        const element = new Image();
        element.src = url;
        try {
          await element.decode();
        } finally {
          URL.revokeObjectURL(url);
        }
        if (stale()) return;
        this.dicom = null;
        this.spacing.value = "";
        this.wlRow.hidden = true;
        dropped = this.setSource({ name: file.name, width: element.naturalWidth, height: element.naturalHeight, dicom: null, element }, keep);
        this.editor.canvas.setAttribute("aria-label",
          `${TITLES[this.view]} ${file.name}: ${file.type === "image/png" ? "PNG" : "JPEG"}, ${element.naturalWidth} by ${element.naturalHeight} pixels.`);
      } else {
        throw new DicomError(`${file.name} is neither DICOM nor a PNG or JPEG image.`);
      }
      this.fileName = file.name;
      this.reopened = null;
      this.chosen = null;
      const start = this.startLevel?.();
      if (start) this.editor.setLevel(start);
      this.refuseOrientation(null);
      this.ignoreGeometry.checked = false;
      if (!keep) this.fromJob = false;
      // the reopened job's landmarks kept over a film that says it is not theirs, or that they overhang
      this.otherPatient = notTheJobs?.patient
        ? { words: notTheJobs.words, marks: new Set(this.editor.landmarks().map(pointsKey)) }
        : null;
      const outside = keep ? this.editor.landmarksOffFilm() : [];
      warning = [
        warning,
        notTheJobs && `${file.name} is not the reopened job's film: its header says ${notTheJobs.words}. The landmarks over it were placed on the job's film: check each one${notTheJobs.patient ? "; the job is not sent with another patient's film" : ""}.`,
        outside.length ? `${outside.length === 1 ? "The landmark of" : "The landmarks of"} ${outside.join(", ")} of the reopened job lie${outside.length === 1 ? "s" : ""} outside this film (${this.editor.source?.width} × ${this.editor.source?.height} px): is it the film the job was made from?` : null,
      ].filter(Boolean).join(" ") || null;
      this.warning.hidden = !warning;
      this.warning.textContent = warning ?? "";
      const gone = before ? marksWords(before.editor.marks) : "";
      const was = before?.fileName ? `the film ${before.fileName}` : "the blank frame";
      const undoWords = `Undo (the button, or Ctrl+Z on the film) brings back ${was} and its landmarks.`;
      this.dropNote = dropped && inMm
        ? `The reopened job's landmarks of ${dropped} vertebra${dropped === 1 ? "" : "e"} are in mm without a pixel spacing, so where they lie on ${file.name} is unknown: they were removed, not guessed (${gone}). ${undoWords}`
        : dropped
        ? `The landmarks of ${dropped} vertebra${dropped === 1 ? "" : "e"} placed on the previous film were removed with it (${was}: ${gone}): landmarks belong to the film they were placed on. ${undoWords} Or place them again on ${file.name}.`
        : null;
      if (before && dropped) this.pushReplaced(before, file.name);
      this.fillHeader();
      this.update();
      this.onChange();
    } catch (error) {
      if (!stale()) this.showError(error instanceof Error ? error.message : `${file.name} could not be read.`);
    }
  }

  private settingSource = false;

  private setSource(source: Parameters<FilmEditor["setSource"]>[0], keep: boolean): number {
    this.settingSource = true;
    try {
      return this.editor.setSource(source, keep);
    } finally {
      this.settingSource = false;
    }
  }

  /** The reopened job's landmarks (on the blank frame) are in mm without a pixel spacing: no film can be put under them. */
  reopenedInMm(): boolean {
    return !!this.reopened && (this.reopened.units ?? "mm") === "mm" && !this.reopened.pixel_spacing;
  }

  /** "Close film": the panel as the page first shows it, as an edit that Undo (the button, Ctrl+Z) takes
   * back, film, landmarks and their undo history together; the status says what went with the film. */
  close(): void {
    const saved = this.capture();
    const gone = marksWords(saved.editor.marks);
    this.reset();
    if (!saved.fileName && !saved.reopened && !gone) return; // nothing was open: nothing to undo
    this.editor.pushOuter({ undo: () => this.bringBack(saved), redo: () => this.close() });
    this.dropNote = `Closed ${saved.fileName ? `the film ${saved.fileName}` : "the blank frame"}${gone ? `: the landmarks of ${gone} on it were removed with it` : " (no landmark was placed on it)"}. ` +
      "Undo (the button, or Ctrl+Z on the film) brings back the film and its landmarks.";
    this.update();
  }

  /** Record opening `name` over the film `before` (its landmarks removed) as an edit: Undo brings back
   * the film, its header and landmarks with their undo history; Redo shows `name` again as it was. */
  private pushReplaced(before: ClosedFilm, name: string): void {
    let after: ClosedFilm | null = null;
    const was = before.fileName ? `the film ${before.fileName}` : "the blank frame";
    const edit: OuterEdit = {
      undo: () => {
        after = this.capture();
        this.bringBack(before, `Undone: ${was} and the landmarks of ${marksWords(before.editor.marks)} are back in place of ${name}. Redo opens ${name} again.`);
      },
      redo: () => {
        if (!after) return;
        this.bringBack(after, `Redone: ${name} is open again; the landmarks of ${marksWords(before.editor.marks)} placed on ${was} were removed with it. Undo brings them back.`);
        this.editor.pushOuter(edit);
      },
    };
    this.editor.pushOuter(edit);
  }

  /** What the panel shows now, for Undo of "Close film". */
  private capture(): ClosedFilm {
    return {
      editor: this.editor.saveState(), dicom: this.dicom, fileName: this.fileName, reopened: this.reopened, fromJob: this.fromJob,
      jobFilm: this.jobFilm, otherPatient: this.otherPatient, spacing: this.spacing.value, ignoreGeometry: this.ignoreGeometry.checked,
      wl: [this.wlCenter.value, this.wlWidth.value, this.invert.checked], wlHidden: this.wlRow.hidden,
      warning: this.warning.hidden ? null : this.warning.textContent, header: [...this.header.childNodes],
      label: this.editor.canvas.getAttribute("aria-label") ?? "", chosen: this.chosen,
    };
  }

  /** Undo of "Close film": the film, its header and landmarks (with their undo history) back as they were. */
  private bringBack(s: ClosedFilm, note?: string): void {
    this.opening++; // a film chosen meanwhile and still being read is not shown over it
    this.dicom = s.dicom;
    this.fileName = s.fileName;
    this.reopened = s.reopened;
    this.fromJob = s.fromJob;
    this.jobFilm = s.jobFilm;
    this.otherPatient = s.otherPatient;
    this.chosen = s.chosen;
    this.refuseOrientation(null);
    this.spacing.value = s.spacing;
    this.ignoreGeometry.checked = s.ignoreGeometry;
    [this.wlCenter.value, this.wlWidth.value] = [s.wl[0], s.wl[1]];
    this.invert.checked = s.wl[2];
    this.wlRow.hidden = s.wlHidden;
    this.warning.hidden = !s.warning;
    this.warning.textContent = s.warning ?? "";
    this.header.replaceChildren(...s.header);
    this.ignoreRow.hidden = !this.hasGeometry();
    this.editor.canvas.setAttribute("aria-label", s.label);
    this.editor.loadState(s.editor);
    const back = marksWords(s.editor.marks);
    this.dropNote = note ?? `Undone: ${s.fileName ? `the film ${s.fileName}` : "the blank frame"}${back ? ` and the landmarks of ${back}` : ""} are back.`;
    this.update();
    this.onChange();
  }

  /** Relabel every landmark of this film one level down (+1) or up (−1) the spine; said in the status,
   * with the reason when refused (a level would leave T1–L5). */
  shiftLevels(by: 1 | -1): void {
    const before = this.editor.landmarks().map((lm) => lm.level);
    const refusal = this.editor.shiftLevels(by);
    const after = this.editor.landmarks().map((lm) => lm.level);
    const span = (lv: Level[]): string => (lv.length > 1 ? `${lv[0]}–${lv[lv.length - 1]}` : lv[0] ?? "none");
    this.dropNote = refusal ?? `Relabelled one level ${by > 0 ? "down" : "up"}: the landmarks of ${span(before)} are now of ${span(after)}. Undo takes it back.`;
    this.update();
  }

  /** Close the film: no film, no landmarks, no header, as the page first shows the panel. */
  reset(): void {
    this.opening++; // a film still being read is not shown once the panel is closed
    this.editor.loading = null;
    this.jobFilm = null;
    this.otherPatient = null;
    this.dicom = null;
    this.fileName = null;
    this.reopened = null;
    this.chosen = null;
    this.refuseOrientation(null);
    this.fromJob = false;
    this.dropNote = null;
    this.fileInput.value = "";
    this.ignoreGeometry.checked = false;
    this.ignoreRow.hidden = true;
    this.spacing.value = "";
    this.wlRow.hidden = true;
    this.showError(null);
    this.warning.hidden = true;
    this.warning.textContent = "";
    this.header.replaceChildren();
    this.prompt.textContent = `Open the ${this.view === "pa" ? "PA" : "lateral"} film to start.`;
    this.editor.canvas.setAttribute("aria-label", `${TITLES[this.view]}: no film open`);
    window.clearTimeout(this.crosshairTimer);
    this.crosshair.textContent = "";
    this.editor.reset();
    this.update();
  }

  /** The service's refusal of this film's orientation, in words, at its controls (null takes it away). */
  refuseOrientation(words: string | null): void {
    this.refusal = words;
    this.orientError.hidden = !words;
    this.orientError.textContent = words ?? "";
    this.markOrientation();
  }

  /** What the service would refuse in this film's orientation with its landmarks (checks.ts
   * `orientationProblems`, the service's rules), found before sending. */
  orientationProblems(): OrientationProblem[] {
    return this.hasFilm() ? orientationProblems(this.view, this.orientation(), this.editor.landmarks()) : [];
  }

  /** The landmarks in order along another direction than the orientation says (checks.ts `orderAlongAnother`):
   * the words saying the orientation is likely wrong and the controls to change; null when they are not. */
  orientationFromOrder(): { text: string; controls: (0 | 1)[] } | null {
    if (!this.hasFilm()) return null;
    this.syncOrientation();
    const placed = this.editor.landmarks();
    const tops = placed.map((lm): Vec2 => lm.point ?? [(lm.corners![0][0] + lm.corners![1][0]) / 2, (lm.corners![0][1] + lm.corners![1][1]) / 2]);
    const found = orderAlongAnother(tops, this.editor.headAxis, this.editor.towardHead);
    return found ? orientationFromOrder(this.view, this.orientation(), found, placed[0].level, placed[placed.length - 1].level) : null;
  }

  /** The orientation controls marked invalid (`aria-invalid`, the words in their description) while the page's
   * check or the service's refusal stands, or (only the control to change) while the landmarks' order says the
   * orientation is likely wrong; the check's words under them. */
  private markOrientation(): void {
    const found = this.orientationProblems();
    const words = found.map((p) => `${p.text.charAt(0).toUpperCase()}${p.text.slice(1)}.`).join(" ");
    this.orientCheck.hidden = !found.length;
    this.orientCheck.textContent = found.length ? `The service refuses this orientation: ${words} (Its words: ${found.map((p) => p.service).join("; ")}.)` : "";
    const order = this.orientationFromOrder();
    this.orientOrder.hidden = !order;
    this.orientOrder.textContent = order ? `${order.text.charAt(0).toUpperCase()}${order.text.slice(1)}.` : "";
    this.orient.forEach((select, k) => {
      const byOrder = !!order?.controls.includes(k as 0 | 1);
      const described = [`${this.view}-orientation-help`, ...(found.length ? [`${this.view}-orientation-check`] : []),
        ...(byOrder ? [`${this.view}-orientation-order`] : []), ...(this.refusal ? [`${this.view}-orientation-error`] : [])];
      select.setAttribute("aria-describedby", described.join(" "));
      if (found.length || this.refusal || byOrder) select.setAttribute("aria-invalid", "true");
      else select.removeAttribute("aria-invalid");
    });
  }

  /** Say where the crosshair is (moved by the keyboard): at once, unless it was said less than CROSSHAIR_SAY_MS
   * ago; then once that time is up, where it is by then (a held arrow key is not read out at every step). */
  private sayCrosshair(): void {
    window.clearTimeout(this.crosshairTimer);
    const wait = this.crosshairSaid + CROSSHAIR_SAY_MS - performance.now();
    const say = (): void => {
      this.crosshairSaid = performance.now();
      this.crosshair.textContent = this.crosshairWords();
    };
    if (wait <= 0) say();
    else this.crosshairTimer = window.setTimeout(say, wait);
  }

  /** The crosshair's place in the film's terms: what Enter places there, its column and row (px), and in mm
   * from the film's top-left corner when the pixel spacing is known. */
  crosshairWords(): string {
    const c = this.editor.cursor;
    if (!c) return "";
    const [col, row] = [Math.round(c[0]), Math.round(c[1])];
    // a reopened job's landmarks in mm without a spacing are on a blank frame of 1 px = 1 mm
    const inMm = !this.editor.source && this.reopenedInMm();
    const s = this.editor.source || !this.reopened ? this.pixelSpacing() : this.reopened.units === "px" ? (this.reopened.pixel_spacing as Vec2 | null | undefined) ?? null : null;
    const mm = s && !inMm ? ` (${(c[0] * s[1]).toFixed(1)} mm across, ${(c[1] * s[0]).toFixed(1)} mm down from the film's top-left corner)` : "";
    const frame = this.editor.source ? "film" : "frame";
    const enter = this.editor.finished ? "Enter places nothing until a level is chosen" : "Enter places it there";
    return `${this.editor.role()} next: crosshair at column ${col}, row ${row} ${inMm ? "mm" : "px"}${mm} of the ${frame}; ${enter}.`;
  }

  /** Bring the orientation controls into view and focus the first. */
  focusOrientation(): void {
    this.orient[0].scrollIntoView({ block: "center" });
    this.orient[0].focus();
  }

  private showError(message: string | null): void {
    this.error.hidden = !message;
    this.error.textContent = message ?? "";
  }

  private fillHeader(): void {
    const d = this.dicom;
    const rows: [string, string][] = [];
    if (d) {
      const s = d.study;
      rows.push(["Patient", [personName(s.patient_name), s.patient_id && `ID ${s.patient_id}`].filter(Boolean).join(", ") || "not given"]);
      rows.push(["Study", [s.study_date, s.accession_number && `accession ${s.accession_number}`].filter(Boolean).join(", ") || "not given"]);
      rows.push(["Study UID", s.study_instance_uid ?? "not given"]);
      rows.push(["Image", `${d.modality ?? "?"} ${d.viewPosition ?? ""} ${d.photometric}, ${d.width} × ${d.height} px`.replace(/\s+/g, " ")]);
      const spacing = filmSpacing(d, this.geometryIgnored());
      const spacingLeftOut = d.spacingLeftOut.length ? ` ${d.spacingLeftOut.join("; ")}.` : "";
      rows.push(["Spacing", `${spacing.explanation} Calibration: ${spacing.calibration}.${spacingLeftOut}`]);
      const stated = d.orientation ? `${d.orientation.join(", ")} (columns toward ${d.orientation[0]}, rows toward ${d.orientation[1]})`
        : `${d.orientationRaw ? `${d.orientationRaw}: not two single directions; ` : "not given; "}taken as ${DEFAULT_ORIENTATION[this.view].join(", ")}`;
      rows.push(["Orientation", `${stated}${this.chosen ? `; sent as ${this.chosen.join(", ")} (set under Orientation)` : ""}`]);
      const a = d.acquisition;
      const geo = [
        a.magnification && `magnification (ERMF) ${a.magnification}`,
        a.distance_source_to_detector_mm && `SID ${a.distance_source_to_detector_mm} mm`,
        a.distance_source_to_patient_mm && `SOD ${a.distance_source_to_patient_mm} mm`,
      ].filter(Boolean);
      const ignored = this.geometryIgnored() ? ` (ignored: sent as ${this.sentWithoutGeometry()})` : "";
      const calibrated = spacing.calibration === "calibrated";
      const leftOut = d.geometryLeftOut.length ? `. ${d.geometryLeftOut.join("; ")}.` : "";
      rows.push(["Geometry", (geo.length ? geo.join(", ") + ignored : calibrated ? "not given: the calibrated spacing gives the size" : "not given: the scale is estimated") + leftOut]);
    } else if (this.fileName) {
      rows.push(["Image", `${this.fileName}: no header, so no spacing, patient or study`]);
    }
    this.header.replaceChildren(...rows.flatMap(([k, v]) => [el("dt", {}, k), el("dd", {}, v)]));
    this.ignoreRow.hidden = !this.hasGeometry();
  }

  /** The film's payload would carry a magnification, SID or SOD: from its DICOM header (calibrated or not), or
   * from the reopened job's payload while its landmarks are on a blank frame. */
  hasGeometry(): boolean {
    const acq = this.dicom
      ? this.dicom.acquisition
      : this.reopened && !this.editor.source ? (this.reopened.acquisition as Acquisition | null | undefined) : null;
    return !!acq && GEOMETRY_KEYS.some((k) => acq[k] !== undefined && acq[k] !== null);
  }

  /** What the film is sent as with "Ignore header geometry" ticked, in words: its spacing read without the
   * header's geometry may still be calibrated (a calibration type, or Pixel Spacing below Imager Pixel Spacing). */
  private sentWithoutGeometry(): string {
    return this.dicom?.spacingWithoutGeometry.calibration === "calibrated" ? "a film without geometry, its calibrated spacing as it is" : "an uncalibrated film";
  }

  /** "Ignore header geometry" is ticked (and applies to this film). */
  geometryIgnored(): boolean {
    return this.ignoreGeometry.checked && this.hasGeometry();
  }

  /** What to do about a geometry the service would refuse, in words. */
  geometryRemedy(): string {
    const name = this.view === "pa" ? "PA" : "lateral";
    return this.hasGeometry()
      ? `tick “Ignore header geometry” under the ${name} film to send it without the header's ERMF, SID and SOD (as ${this.sentWithoutGeometry()}), or correct the header`
      : "correct the payload's acquisition";
  }

  /** The spacing the user confirmed or typed, mm per pixel [row, column]; null when missing or invalid. The
   * header's (`fromHeader`, by default as read with or without its geometry) when the field shows it. */
  pixelSpacing(fromHeader: Vec2 | null | undefined = this.dicom && filmSpacing(this.dicom, this.geometryIgnored()).value): Vec2 | null {
    const typed = Number(this.spacing.value);
    if (this.spacing.value.trim() === "" || !(typed > 0) || typed > 10) return null;
    if (fromHeader && Math.abs(fromHeader[1] - typed) <= SPACING_SHOWN_TOLERANCE * fromHeader[1]) return fromHeader;
    return [typed, typed];
  }

  /** The film as drawn now (window applied), for the result's PA projection; null without a film. */
  async backdrop(): Promise<{ url: string; width: number; height: number; spacing: Vec2 } | null> {
    const spacing = this.pixelSpacing();
    const blob = await this.editor.rasterBlob();
    const s = this.editor.source;
    return blob && s && spacing ? { url: URL.createObjectURL(blob), width: s.width, height: s.height, spacing } : null;
  }

  hasFilm(): boolean {
    return !!this.editor.source || !!this.reopened;
  }

  orientation(): [string, string] {
    return this.chosen ?? this.dicom?.orientation ?? (this.reopened?.patient_orientation as [string, string] | undefined) ?? DEFAULT_ORIENTATION[this.view];
  }

  /** The view of the payload, or null without landmarks. Optional members only when the service takes them. */
  payload(accepts: { acquisition: boolean; calibration: boolean; imageSize: boolean; projectionModel: boolean }): ViewPayload | null {
    const landmarks = this.editor.landmarks();
    if (!landmarks.length) return null;
    if (this.reopened && !this.editor.source) {
      const view: ViewPayload = { ...this.reopened, landmarks: this.reopened.units === "mm" && this.reopened.pixel_spacing ? landmarks.map((lm) => toMm(lm, this.reopened!.pixel_spacing as Vec2)) : landmarks };
      if (this.chosen) view.patient_orientation = this.chosen;
      if (this.geometryIgnored()) {
        const acq = withoutGeometry(this.reopened.acquisition as Acquisition);
        if (Object.keys(acq).length) view.acquisition = acq;
        else delete view.acquisition;
      }
      return view;
    }
    const view: ViewPayload = { units: "px", pixel_spacing: this.pixelSpacing(), patient_orientation: this.orientation(), landmarks };
    const d = this.dicom;
    const read = d && filmSpacing(d, this.geometryIgnored());
    if (read && accepts.calibration) view.pixel_spacing_calibration = read.value && view.pixel_spacing === read.value ? read.calibration : "unknown";
    if (d && accepts.acquisition) {
      const acq = viewAcquisition(d, accepts, this.geometryIgnored());
      if (Object.keys(acq).length) view.acquisition = acq;
    }
    return view;
  }

  /** What stops this film's landmarks from making a valid job, in words. */
  problems(): string[] {
    const out: string[] = [];
    const name = this.view === "pa" ? "PA" : "lateral";
    const placed = this.editor.landmarks();
    const n = placed.length;
    const other = this.otherPatient;
    const theJobs = other ? placed.filter((lm) => other.marks.has(pointsKey(lm))).map((lm) => lm.level) : [];
    if (other && theJobs.length) {
      out.push(`The ${name} film is not the reopened job's: its header says ${other.words}, and the landmarks of ${theJobs.length === 1 ? theJobs[0] : `${theJobs.length} vertebrae (${theJobs[0]}–${theJobs[theJobs.length - 1]})`} over it were placed on the job's film. Close it (“Close film” under it) and open the job's film, or place those landmarks again on this one.`);
    }
    if (this.editor.source && n && !this.pixelSpacing()) {
      out.push(`Enter the pixel spacing of the ${name} film (mm per pixel, between 0.001 and 10): ${this.dicom ? "its header gives none" : "a PNG or JPEG does not carry it"}, and it is never guessed.`);
    }
    out.push(...this.editor.incomplete().map((s) => `${name} film, ${s}: finish or delete it.`));
    this.syncOrientation();
    out.push(...this.editor.problems().map((p) => `${name} film, ${p.level}: ${p.text} (drawn in red): move its points, or undo.`));
    const fromOrder = this.orientationFromOrder();
    if (fromOrder) out.push(`${name === "PA" ? "PA" : "Lateral"} film, orientation likely wrong (said under the film, at “Orientation”): ${fromOrder.text}.`);
    // Said at the controls whenever a film is open; listed here when the view is sent (it has landmarks).
    for (const p of n ? this.orientationProblems() : []) {
      out.push(`${name === "PA" ? "PA" : "Lateral"} film, orientation (under the film, DICOM Patient Orientation): ${p.text}. The service refuses it: ${p.service}.`);
    }
    return out;
  }

  /** A reopened job's view: its landmarks on a blank frame until its film is opened (by hand, or
   * fetched again from the PACS); ``why`` says why the film is not there, in the header and the frame. */
  restore(view: ViewPayload, film: JobFilm | null = null, why = "Not stored by the service: the landmarks are shown on a blank frame. Open the film to see it under them."): void {
    this.reset();
    this.jobFilm = film;
    this.reopened = { ...view, landmarks: [] };
    this.fromJob = true;
    this.dicom = null;
    this.fileName = null;
    this.wlRow.hidden = true;
    this.editor.clearSource();
    this.editor.setLandmarks(view.landmarks, view.pixel_spacing as Vec2 | null, view.units);
    if (view.units === "px" && view.pixel_spacing) this.spacing.value = String(view.pixel_spacing[1]);
    this.ignoreRow.hidden = !this.hasGeometry();
    this.explainBlank(why);
    this.update();
  }

  /** Why the film is not under the landmarks, in the header and in the blank frame. */
  explainBlank(why: string): void {
    this.header.replaceChildren(el("dt", {}, "Film"), el("dd", {}, why));
    this.editor.blankNote = why;
    this.editor.draw();
  }

  /** The editor's order check follows the orientation: down the spine along the rows when they run toward the
   * head or the feet, else along the columns when they do (validation.py `_order_errors`), backward toward H. */
  private syncOrientation(): void {
    const o = this.orientation();
    const axis = o[1] === "H" || o[1] === "F" ? 1 : o[0] === "H" || o[0] === "F" ? 0 : null;
    this.editor.headAxis = axis;
    this.editor.towardHead = axis !== null && o[axis] === "H";
  }

  update(): void {
    const o = this.orientation();
    this.syncOrientation();
    this.markOrientation();
    [this.orient[0].value, this.orient[1].value] = o;
    this.orientHelp.textContent = `Sent as ${o.join(", ")}: the patient's ${o.map((d) => `${d} (${DIRECTION_WORDS[d] ?? "?"})`).join(" toward the image's right, ")} toward its bottom${this.chosen ? " (set here)" : this.dicom?.orientation ? " (from the header)" : ""}. Change it when the film is displayed mirrored or turned: the landmarks stay where they are.`;
    const ed = this.editor;
    const placed = ed.landmarks();
    this.zoomOut.value = ed.source || this.reopened ? `${ed.zoomPercent} %` : "";
    this.undoButton.disabled = !ed.canUndo;
    this.redoButton.disabled = !ed.canRedo;
    if (!ed.source && !this.reopened) {
      this.status.textContent = this.dropNote ?? "";
      this.prompt.textContent = ed.loading ? `Loading ${ed.loading}…` : `Open the ${this.view === "pa" ? "PA" : "lateral"} film to start.`;
      return;
    }
    const next = ed.finished ? `${ed.level} is complete: choose a level to place again, or drag a point to move it.` : `Next: ${ed.nextPart()}.`;
    this.prompt.textContent = ed.loading ? `Loading ${ed.loading}…` : ed.placedNothing ? `${ed.placedNothing}. ${next}` : next;
    const levels = placed.map((l) => l.level);
    const kinds = [
      placed.filter((l) => l.point).length && `${placed.filter((l) => l.point).length} midpoints`,
      placed.filter((l) => l.corners).length && `${placed.filter((l) => l.corners).length} with four corners`,
      placed.filter((l) => l.pedicles).length && `${placed.filter((l) => l.pedicles).length} with pedicles`,
    ].filter(Boolean).join(", ");
    this.status.textContent = (this.dropNote ? `${this.dropNote} ` : "") + (placed.length
      ? `${placed.length} vertebra${placed.length === 1 ? "" : "e"} on the ${this.view === "pa" ? "PA" : "lateral"} film (${levels[0]}–${levels[levels.length - 1]}): ${kinds}.`
      : "No landmark on this film yet.");
  }
}

const round = (x: number): number => Math.round(x * 100) / 100;
/** The least time between two sayings of the crosshair's place (ms): a held arrow key repeats about every
 * 33 ms (30 Hz), each saying would cut the last one short; half a second lets a short phrase be heard. */
const CROSSHAIR_SAY_MS = 500;

/** A landmark's points, without its level: a reopened job's landmark relabelled is still the job's. */
const pointsKey = (lm: ViewPayload["landmarks"][number]): string => JSON.stringify([lm.point ?? null, lm.corners ?? null, lm.pedicles ?? null]);

/** The marks of a film in words: "17 vertebrae (T1–L5): 68 corners", "1 vertebra (T3): 1 midpoint"; "" for none. */
function marksWords(marks: Map<Level, Mark>): string {
  const levels = LEVELS.filter((lv) => marks.has(lv));
  if (!levels.length) return "";
  const all = [...marks.values()];
  const count = (n: number, one: string, many: string): string | null => (n ? `${n} ${n === 1 ? one : many}` : null);
  const points = [
    count(all.filter((m) => m.point).length, "midpoint", "midpoints"),
    count(all.reduce((n, m) => n + (m.corners?.length ?? 0), 0), "corner", "corners"),
    count(all.reduce((n, m) => n + (m.pedicles?.length ?? 0), 0), "pedicle", "pedicles"),
  ].filter(Boolean).join(", ");
  const span = levels.length > 1 ? `${levels[0]}–${levels[levels.length - 1]}` : levels[0];
  return `${levels.length} vertebra${levels.length === 1 ? "" : "e"} (${span}): ${points}`;
}

/** A closed film as the panel showed it, for Undo. */
interface ClosedFilm {
  editor: EditorState;
  dicom: DicomFilm | null;
  fileName: string | null;
  reopened: ViewPayload | null;
  fromJob: boolean;
  jobFilm: JobFilm | null;
  otherPatient: { words: string; marks: Set<string> } | null;
  spacing: string;
  ignoreGeometry: boolean;
  wl: [string, string, boolean];
  wlHidden: boolean;
  warning: string | null;
  header: Node[];
  label: string;
  chosen: [string, string] | null;
}

/** A reopened job's film as its payload's `study` names it. */
export interface JobFilm {
  /** This view's SOP Instance UID (0008,0018): `pa_sop_instance_uid` or `lateral_sop_instance_uid`. */
  sop_instance_uid?: string | null;
  study_instance_uid?: string | null;
  patient_id?: string | null;
}

/** How a DICOM film's header says it is not the reopened job's film. */
export interface OtherFilm {
  /** Of another patient (Patient ID (0010,0020)), not only another study or image. */
  patient: boolean;
  words: string;
}

/** How a DICOM film's header says it is not the reopened job's film; null when nothing says so (an
 * identifier missing on either side says nothing): its Patient ID (0010,0020), Study Instance UID
 * (0020,000D) or SOP Instance UID (0008,0018) differs from the job's `study`. */
export function otherFilm(job: JobFilm | null, film: DicomFilm): OtherFilm | null {
  if (!job) return null;
  const s = film.study;
  const differs = (a: string | null | undefined, b: string | null | undefined): boolean => !!a && !!b && a.trim() !== b.trim();
  if (differs(job.patient_id, s.patient_id)) return { patient: true, words: `patient ID ${s.patient_id}, the job's is ${job.patient_id}` };
  if (differs(job.study_instance_uid, s.study_instance_uid)) return { patient: false, words: `study ${s.study_instance_uid}, the job's is ${job.study_instance_uid}` };
  if (differs(job.sop_instance_uid, s.sop_instance_uid)) return { patient: false, words: `image ${s.sop_instance_uid}, the job's is ${job.sop_instance_uid}` };
  return null;
}

function toMm(lm: ViewPayload["landmarks"][number], spacing: Vec2): ViewPayload["landmarks"][number] {
  const mm = (p: Vec2): Vec2 => [Math.round(p[0] * spacing[1] * 1000) / 1000, Math.round(p[1] * spacing[0] * 1000) / 1000];
  const out: ViewPayload["landmarks"][number] = { level: lm.level };
  if (lm.point) out.point = mm(lm.point);
  if (lm.corners) out.corners = lm.corners.map(mm) as [Vec2, Vec2, Vec2, Vec2];
  if (Array.isArray(lm.pedicles)) out.pedicles = (lm.pedicles as Vec2[]).map(mm);
  return out;
}

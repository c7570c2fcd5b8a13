// "Open from the PACS": a Study Instance UID → the study's images (GET /v1/pacs/studies/{uid}/images),
// each usable as the PA or the lateral film. The chosen image is fetched from the service as a DICOM
// Part 10 file in Explicit VR Little Endian and opened by the film panel exactly as a file from disk,
// so its header (spacing, orientation, window, study and SOP UIDs) is read the same way.
import { Api, ApiError } from "./api";
import type { PacsImage } from "./types";
import type { ViewName } from "./panel";

const UID = /^(0|[1-9][0-9]*)(\.(0|[1-9][0-9]*))*$/;

export interface PacsHooks {
  api: Api;
  /** Opens the DICOM file as the film of `view` (the same path as a file chosen from disk). */
  open: (view: ViewName, file: File) => Promise<void>;
}

function $<T extends HTMLElement = HTMLElement>(id: string): T {
  return document.getElementById(id) as T;
}

function describe(image: PacsImage): string {
  return [image.modality, image.view_position, image.series_description].filter(Boolean).join(" ") || "image";
}

/** The service has no PACS (GET /v1/pacs says it is not configured). */
export class NoPacs extends Error {}

export class PacsOpener {
  private readonly form = $<HTMLFormElement>("pacs-open");
  private readonly study = $<HTMLInputElement>("pacs-study");
  private readonly note = $("pacs-note");
  private readonly problem = $("pacs-problem");
  private readonly table = $("pacs-images-wrap");
  private readonly body = $("pacs-images").querySelector("tbody") as HTMLTableSectionElement;
  private studyUid = "";

  constructor(private readonly hooks: PacsHooks) {
    this.form.addEventListener("submit", (e) => {
      e.preventDefault();
      void this.list();
    });
  }

  /** Shows the control only when the service has the routes and says a PACS is configured. */
  async refresh(hasRoutes: boolean): Promise<void> {
    let configured = false;
    if (hasRoutes) {
      try {
        configured = (await this.hooks.api.pacsStatus()).configured;
      } catch {
        configured = false; // no key yet, or an older service: nothing to offer
      }
    }
    this.form.hidden = !configured;
  }

  private showProblem(message: string | null): void {
    this.problem.hidden = !message;
    this.problem.textContent = message ?? "";
  }

  private async list(): Promise<void> {
    const uid = this.study.value.trim();
    this.showProblem(null);
    this.body.replaceChildren();
    this.table.hidden = true;
    if (!UID.test(uid) || uid.length > 64) {
      this.showProblem("Enter a Study Instance UID: digits in dot-separated groups (no leading zeros), at most 64 characters, e.g. 1.2.840.113619.2.55.3.");
      return;
    }
    this.note.textContent = "Asking the PACS for the study's images…";
    try {
      const study = await this.hooks.api.pacsImages(uid);
      this.studyUid = study.study_instance_uid;
      this.note.textContent = study.images.length
        ? `${study.images.length} image${study.images.length === 1 ? "" : "s"} in study ${uid}: choose the PA film and, optionally, the lateral film.`
        : `Study ${uid} has no image the page can open.`;
      study.images.forEach((image, i) => this.body.append(this.row(image, i)));
      this.table.hidden = study.images.length === 0;
    } catch (error) {
      this.note.textContent = "";
      this.showProblem(error instanceof ApiError ? `The study could not be listed: ${error.message}` : String(error));
    }
  }

  private row(image: PacsImage, i: number): HTMLTableRowElement {
    const tr = document.createElement("tr");
    const cells = [
      image.modality ?? "—",
      image.view_position ?? "—",
      image.series_description ?? "—",
      image.columns && image.rows ? `${image.columns} × ${image.rows}` : "—",
    ];
    for (const text of cells) {
      const td = document.createElement("td");
      td.textContent = text;
      tr.append(td);
    }
    const actions = document.createElement("td");
    for (const [view, label] of [["pa", "PA"], ["lateral", "lateral"]] as [ViewName, string][]) {
      const button = document.createElement("button");
      button.type = "button";
      button.id = `pacs-${view}-${i}`;
      button.textContent = `Use as ${label}`;
      button.setAttribute("aria-label", `Use image ${i + 1} (${describe(image)}) as the ${label} film`);
      button.addEventListener("click", () => void this.use(image, view, label));
      actions.append(button, " ");
    }
    tr.append(actions);
    return tr;
  }

  /** One image of a study as a DICOM file, fetched through the service (uncompressed). */
  private async fetchImage(studyUid: string, image: PacsImage): Promise<File> {
    const path = ["/v1/pacs/studies", studyUid, "series", image.series_instance_uid, "instances", image.sop_instance_uid]
      .map((part, i) => (i % 2 ? encodeURIComponent(part) : part))
      .join("/");
    const blob = await this.hooks.api.blob(path, "application/dicom, application/problem+json");
    return new File([blob], `${image.sop_instance_uid}.dcm`, { type: "application/dicom" });
  }

  /**
   * A reopened job's film, fetched again from the PACS by its UIDs (the series from the study's
   * list); a plain-words Error when it cannot be: no PACS now, the image gone, the PACS refusing.
   */
  async fetchFilm(studyUid: string, sopUid: string): Promise<File> {
    let configured = false;
    try {
      configured = (await this.hooks.api.pacsStatus()).configured;
    } catch (error) {
      throw new Error(`the service could not say whether it has a PACS (${error instanceof Error ? error.message : String(error)})`);
    }
    if (!configured) throw new NoPacs("this service is not connected to a PACS");
    try {
      const study = await this.hooks.api.pacsImages(studyUid);
      const image = study.images.find((i) => i.sop_instance_uid === sopUid);
      if (!image) throw new Error(`the PACS has no image ${sopUid} in study ${studyUid} any more`);
      return await this.fetchImage(studyUid, image);
    } catch (error) {
      throw new Error(error instanceof ApiError ? `the PACS did not give it: ${error.message}` : error instanceof Error ? error.message : String(error));
    }
  }

  private async use(image: PacsImage, view: ViewName, label: string): Promise<void> {
    this.showProblem(null);
    this.note.textContent = `Fetching image ${describe(image)} from the PACS…`;
    try {
      const file = await this.fetchImage(this.studyUid, image);
      await this.hooks.open(view, file);
      this.note.textContent = `Opened ${describe(image)} from the PACS as the ${label} film.`;
    } catch (error) {
      this.note.textContent = "";
      this.showProblem(error instanceof ApiError ? `The image could not be fetched: ${error.message}` : String(error));
    }
  }
}

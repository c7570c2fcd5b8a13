// Problems (RFC 9457 problem+json) in plain sentences: no JSON paths in code form, no Python reprs.
import { DIRECTION_WORDS, ORIENTATION_LABELS } from "./panel";
import type { Problem } from "./types";

const VIEW = { pa: "PA film", lateral: "lateral film" } as Record<string, string>;

/** "pa.landmarks[3].corners" → "PA film, landmark 4 (T4), corners" (with the level when the payload names it). */
export function placeOf(path: string, payload?: unknown): string {
  if (!path || path === "(body)") return "the request";
  const parts = path.split(".");
  const words: string[] = [];
  let node: unknown = payload;
  for (const part of parts) {
    const m = part.match(/^([^[]+)((?:\[\d+\])*)$/);
    const key = m ? m[1] : part;
    node = node && typeof node === "object" ? (node as Record<string, unknown>)[key] : undefined;
    const name = VIEW[key] ?? key.replace(/_/g, " ");
    const indexes = (m?.[2] ?? "").match(/\d+/g) ?? [];
    if (!indexes.length) words.push(name);
    for (const idx of indexes) {
      const item = Array.isArray(node) ? node[Number(idx)] : undefined;
      node = item;
      const level = item && typeof item === "object" ? (item as { level?: string }).level : undefined;
      // "landmarks[3]" → "landmark 4 (T5)"
      words.push(`${name.replace(/s$/, "")} ${Number(idx) + 1}${typeof level === "string" ? ` (${level})` : ""}`);
    }
  }
  return words.join(", ");
}

/** A message without Python list/str reprs: ['L5', 'T1'] → L5 and T1; 'px' → “px”; apostrophes (T3's) kept. */
export function plain(message: string): string {
  return message
    // a patient orientation ['A', 'F'] (DICOM (0020,0020)'s two directions) → A, F
    .replace(/\['([LRAPHF])', '([LRAPHF])'\]/g, "$1, $2")
    .replace(/\[((?:'[^']*'(?:,\s*)?)+)\]/g, (_, items: string) => {
      const list = items.split(/,\s*/).map((s) => s.replace(/^'|'$/g, ""));
      return list.length > 1 ? `${list.slice(0, -1).join(", ")} and ${list[list.length - 1]}` : list[0];
    })
    // a quoted span starts after a non-letter and ends before one: an apostrophe (pedicle's) is no quote
    .replace(/(^|[^\p{L}])'([^']*)'(?![\p{L}])/gu, "$1“$2”")
    .replace(/^Value error, /, "")
    .replace(/^Input should be/, "It should be");
}

/** The sentences of a problem: its detail, then one per offending field. */
export function sentences(problem: Problem, payload?: unknown): { title: string; lines: string[] } {
  const lines: string[] = [];
  const errors = problem.errors ?? [];
  if (problem.detail && !(errors.length && /validation|invalid/i.test(problem.detail))) lines.push(plain(problem.detail));
  for (const e of errors) {
    const msg = plain(e.msg);
    lines.push(`${capital(placeOf(e.path, payload))}: ${msg}${/[.!?]$/.test(msg) ? "" : "."}`);
  }
  if (!lines.length) lines.push(problem.title);
  const status = problem.status === 401 || problem.status === 403
    ? "The service refused the API key"
    : problem.status === 422 ? "The service cannot use this input" : problem.title;
  return { title: status, lines };
}

const capital = (s: string): string => s.charAt(0).toUpperCase() + s.slice(1);

/**
 * A refusal at `<view>.patient_orientation`, in words for the film's orientation controls: what it
 * means, what to change there, and that the landmarks stay. `sent` is the orientation the refused
 * payload gave. A mirrored lateral (`lateral_profile_inverted`, spine_engine/lateral_profile.py) takes
 * the other depth label (A ↔ P) on the axis that carries depth, as the service's message says.
 */
export function orientationWords(error: { type: string; msg: string }, sent: [string, string] | undefined): string {
  const said = plain(error.msg);
  const theirs = `The service's words: ${said}${/[.!?]$/.test(said) ? "" : "."}`;
  const axis = sent ? sent.findIndex((d) => d === "A" || d === "P") : -1;
  if (error.type === "lateral_profile_inverted" && sent && axis >= 0) {
    const now = sent[axis];
    const other = now === "A" ? "P" : "A";
    // the side the patient's front is on when the film is mirrored: opposite to what the label says
    const side = axis === 0 ? (now === "A" ? "left" : "right") : now === "A" ? "top" : "bottom";
    return `Refused by the service: with this orientation the landmarks read as a hollow (lordotic) upper back over a rounded (kyphotic) lower back, both reversed, as a film mirrored left to right reads. ` +
      `Look at the film: if the patient's front is toward the image's ${side}, choose “${other} (${DIRECTION_WORDS[other]})” for “${ORIENTATION_LABELS[axis]}” (the landmarks stay where they are) and Reconstruct again. ${theirs}`;
  }
  return `Refused by the service: ${said}${/[.!?]$/.test(said) ? "" : "."} Set the film's orientation here (the landmarks stay where they are) and Reconstruct again.`;
}

/** Warnings before sending, which do not stop it (the clinician may know better): a box "Check before
 * sending" with one paragraph each, shown in the pre-send list's live region (`#missing`, polite); not
 * list items, so that `#missing li` stays what stops the send. */
export function warningList(lines: string[]): HTMLElement {
  const box = document.createElement("div");
  box.id = "send-warnings";
  box.className = "warning";
  const head = document.createElement("p");
  head.textContent = "Check before sending (a warning: Reconstruct still sends it):";
  box.append(head);
  for (const line of lines) {
    const p = document.createElement("p");
    p.className = "send-warning";
    p.textContent = line;
    box.append(p);
  }
  return box;
}

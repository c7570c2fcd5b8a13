// The page's only network access: the service's own /v1 API, with the API key when one is set.
import type { PatientMeasures } from "./followup";
import type { Job, JobPayload, PacsStatus, PacsStudyImages, Problem } from "./types";

export interface JobPage {
  jobs: Job[];
  next_cursor: string | null;
}

const KEY_STORAGE = "spine.apiKey";

export function loadApiKey(): string {
  try {
    return sessionStorage.getItem(KEY_STORAGE) ?? "";
  } catch {
    return "";
  }
}

export function saveApiKey(key: string): void {
  try {
    if (key) sessionStorage.setItem(KEY_STORAGE, key);
    else sessionStorage.removeItem(KEY_STORAGE);
  } catch {
    /* storage disabled: the key lives in the field only */
  }
}

export class ApiError extends Error {
  /** `retryAfterMs`: the answer's Retry-After (RFC 9110 §10.2.3: delay-seconds or an HTTP-date), in ms from now. */
  constructor(readonly problem: Problem, readonly retryAfterMs: number | null = null) {
    super(problem.detail || problem.title);
  }
}

/** A Retry-After header's wait in ms from now (delay-seconds or an HTTP-date, RFC 9110 §10.2.3); null without one. */
function retryAfterMs(header: string | null): number | null {
  if (!header) return null;
  const text = header.trim();
  const ms = /^\d+$/.test(text) ? Number(text) * 1000 : Date.parse(text) - Date.now();
  return Number.isFinite(ms) ? Math.max(0, ms) : null;
}

function asProblem(status: number, body: unknown, fallback: string): Problem {
  if (body && typeof body === "object" && "title" in body) return body as Problem;
  return { type: "about:blank", title: fallback, status, detail: fallback };
}

export class Api {
  /** Called with the problem of every answer that refuses the key (401, 403). */
  onRefused: (problem: Problem) => void = () => {};
  constructor(private readonly apiKey: () => string) {}

  private headers(extra: Record<string, string> = {}): Headers {
    const headers = new Headers({ Accept: "application/json, application/problem+json", ...extra });
    const key = this.apiKey().trim();
    if (key) headers.set("Authorization", `Bearer ${key}`);
    return headers;
  }

  private async send(method: string, path: string, body?: unknown, accept?: string, headers: Record<string, string> = {}): Promise<Response> {
    const extra: Record<string, string> = body === undefined ? { ...headers } : { "Content-Type": "application/json", ...headers };
    if (accept) extra.Accept = accept;
    try {
      return await fetch(path, {
        method,
        headers: this.headers(extra),
        body: body === undefined ? undefined : JSON.stringify(body),
        cache: "no-store",
      });
    } catch (error) {
      const detail = `the service did not answer (${error instanceof Error ? error.message : String(error)})`;
      throw new ApiError({ type: "about:blank", title: "Network error", status: 0, detail });
    }
  }

  private async json<T>(response: Response): Promise<T> {
    const text = await response.text();
    let body: unknown = undefined;
    try {
      body = text ? JSON.parse(text) : undefined;
    } catch {
      /* not JSON */
    }
    if (!response.ok) {
      const fallback = response.status === 401 || response.status === 403
        ? `the service refused the request (HTTP ${response.status}): check the API key`
        : `HTTP ${response.status} ${response.statusText}`;
      const problem = asProblem(response.status, body, fallback);
      if (response.status === 401 || response.status === 403) this.onRefused(problem);
      throw new ApiError(problem, retryAfterMs(response.headers.get("Retry-After")));
    }
    return body as T;
  }

  /** POST /v1/jobs; with an Idempotency-Key, the same key and body give back the job they first made
   * (`replayed`: the service's Idempotent-Replayed: true) instead of a second one. */
  async submit(payload: JobPayload, idempotencyKey?: string): Promise<{ job: Job; replayed: boolean }> {
    const response = await this.send("POST", "/v1/jobs", payload, undefined, idempotencyKey ? { "Idempotency-Key": idempotencyKey } : {});
    return { job: await this.json<Job>(response), replayed: response.headers.get("Idempotent-Replayed") === "true" };
  }

  async job(id: string): Promise<Job> {
    return this.json<Job>(await this.send("GET", `/v1/jobs/${encodeURIComponent(id)}`));
  }

  /** The caller's jobs, newest first; filters are sent only when non-empty (a list: the parameter repeated). */
  /** One page of the key's jobs, newest first; `cursor` is the previous page's `next_cursor` (the older jobs). */
  async jobs(filters: Record<string, string | string[]> = {}, limit = 50, cursor?: string | null): Promise<JobPage> {
    const q = new URLSearchParams({ limit: String(limit) });
    if (cursor) q.set("cursor", cursor);
    for (const [k, v] of Object.entries(filters)) {
      for (const one of typeof v === "string" ? [v] : v) if (one.trim()) q.append(k, one.trim());
    }
    return this.json<JobPage>(await this.send("GET", `/v1/jobs?${q}`));
  }

  /** The caller's succeeded jobs of a patient by study date, with the changes between visits. */
  async followUp(patientId: string): Promise<PatientMeasures> {
    return this.json<PatientMeasures>(await this.send("GET", `/v1/patients/${encodeURIComponent(patientId)}/measures`));
  }

  async cancel(id: string): Promise<Job> {
    return this.json<Job>(await this.send("POST", `/v1/jobs/${encodeURIComponent(id)}/cancel`));
  }

  /** Whether the service is connected to a PACS (GET /v1/pacs). */
  async pacsStatus(): Promise<PacsStatus> {
    return this.json<PacsStatus>(await this.send("GET", "/v1/pacs"));
  }

  /** The images of a study in the service's PACS (QIDO-RS through the service). */
  async pacsImages(studyInstanceUid: string): Promise<PacsStudyImages> {
    return this.json<PacsStudyImages>(await this.send("GET", `/v1/pacs/studies/${encodeURIComponent(studyInstanceUid)}/images`));
  }

  /** A binary resource (the figures, a DICOM file from the PACS), as a Blob. */
  async blob(path: string, accept?: string): Promise<Blob> {
    const response = await this.send("GET", path, undefined, accept);
    if (!response.ok) await this.json(response);
    return response.blob();
  }
}

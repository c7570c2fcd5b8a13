// What this service's API takes, read once from its own /openapi.json: optional payload members
// and list filters that other releases add (acquisition, calibration, patient fields, job filters)
// are sent only when the service declares them, so the page works against older and newer services.
export interface Capabilities {
  acquisition: boolean;
  /** acquisition.image_size: the film's [columns, rows], for the central ray at the image's centre. */
  imageSize: boolean;
  /** acquisition.projection_model: a CR or DX film sent as projected from a point source. */
  projectionModel: boolean;
  calibration: boolean;
  studyFields: Set<string>;
  jobFilters: Set<string>;
  dicomRoutes: boolean;
  /** GET /v1/jobs/{id}/sr.dcm: the result as a DICOM SR. */
  srExport: boolean;
  /** GET /v1/jobs/{id}/figure.dcm: the figure as a DICOM Secondary Capture. */
  figureDcm: boolean;
  /** GET /v1/jobs/{id}/fhir: the measures as a FHIR R4 Bundle. */
  fhirExport: boolean;
  /** GET /v1/pacs and its study routes: "Open from the PACS" (shown only when /v1/pacs says a PACS is configured). */
  pacsRoutes: boolean;
  /** The API declares a bearer key (components.securitySchemes). */
  needsKey: boolean;
  /** GET /v1/patients/{patient_id}/measures: the Follow-up view. */
  followUp: boolean;
}

const NONE: Capabilities = { acquisition: false, imageSize: false, projectionModel: false, calibration: false, studyFields: new Set(["study_instance_uid", "series_instance_uid", "pa_sop_instance_uid", "lateral_sop_instance_uid"]), jobFilters: new Set(), dicomRoutes: false, srExport: false, figureDcm: false, fhirExport: false, pacsRoutes: false, followUp: false, needsKey: false };

let cached: Promise<Capabilities> | null = null;

type Schema = { properties?: Record<string, unknown> };

export function readCapabilities(spec: unknown): Capabilities {
  const s = spec as { components?: { schemas?: Record<string, Schema> }; paths?: Record<string, Record<string, { parameters?: { name: string }[] }>> };
  const schemas = s.components?.schemas ?? {};
  const view = schemas.PAView?.properties ?? {};
  const study = Object.keys(schemas.Study?.properties ?? {});
  const list = s.paths?.["/v1/jobs"]?.get?.parameters ?? [];
  return {
    acquisition: "acquisition" in view,
    imageSize: "image_size" in (schemas.Acquisition?.properties ?? {}),
    projectionModel: "projection_model" in (schemas.Acquisition?.properties ?? {}),
    calibration: "pixel_spacing_calibration" in view,
    studyFields: study.length ? new Set(study) : NONE.studyFields,
    jobFilters: new Set(list.map((p) => p.name).filter((n) => ["study_instance_uid", "accession_number", "patient_id"].includes(n))),
    dicomRoutes: Object.keys(s.paths ?? {}).some((p) => p.startsWith("/v1/dicom")),
    srExport: "/v1/jobs/{job_id}/sr.dcm" in (s.paths ?? {}),
    figureDcm: "/v1/jobs/{job_id}/figure.dcm" in (s.paths ?? {}),
    fhirExport: "/v1/jobs/{job_id}/fhir" in (s.paths ?? {}),
    pacsRoutes: "/v1/pacs/studies/{study_instance_uid}/images" in (s.paths ?? {}),
    followUp: "/v1/patients/{patient_id}/measures" in (s.paths ?? {}),
    needsKey: Object.keys((s.components as { securitySchemes?: object } | undefined)?.securitySchemes ?? {}).length > 0,
  };
}

export function capabilities(): Promise<Capabilities> {
  cached ??= fetch("/openapi.json", { cache: "no-store" })
    .then((r) => (r.ok ? r.json() : null))
    .then((spec) => (spec ? readCapabilities(spec) : NONE))
    .catch(() => NONE);
  return cached;
}

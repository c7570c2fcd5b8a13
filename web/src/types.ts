// The job contract of the service (spine_engine/models.py, openapi.yaml), as the page uses it.

export const LEVELS = [
  "T1", "T2", "T3", "T4", "T5", "T6", "T7", "T8", "T9", "T10", "T11", "T12",
  "L1", "L2", "L3", "L4", "L5",
] as const;
export type Level = (typeof LEVELS)[number];

export type Vec2 = [number, number];
export type Vec3 = [number, number, number];
export type Mat3 = [Vec3, Vec3, Vec3];

export interface Landmark {
  level: Level;
  /** Top endplate midpoint (column, row); or, instead, the body's four corners. */
  point?: Vec2 | null;
  corners?: [Vec2, Vec2, Vec2, Vec2] | null;
  pedicles?: Vec2[] | null;
  [extra: string]: unknown;
}

/** The landmark's top (superior) endplate midpoint: its point, or the middle of its two top corners, its two
 * bottom ones on a film whose rows run toward the head (`towardHead`: as the service reads them,
 * validation.py `_top_midpoint`). */
export function landmarkPoint(lm: Pick<Landmark, "point"> & { level?: Level; corners?: Vec2[] | null }, towardHead = false): Vec2 {
  if (lm.point) return lm.point;
  const [a, b] = towardHead ? [2, 3] : [0, 1];
  if (lm.corners) return [(lm.corners[a][0] + lm.corners[b][0]) / 2, (lm.corners[a][1] + lm.corners[b][1]) / 2];
  throw new Error(`landmark ${lm.level ?? ""} has neither point nor corners`);
}

export interface ViewPayload {
  units?: "mm" | "px";
  pixel_spacing?: Vec2 | null;
  patient_orientation?: [string, string];
  landmarks: Landmark[];
  projection?: { scale: number; translation: Vec2 } | null;
  [extra: string]: unknown;
}

export interface Pose {
  position: Vec3;
  directors: Mat3;
}

export interface JobPayload {
  pa: ViewPayload;
  lateral?: ViewPayload | null;
  boundary?: { T1: Pose; L5: Pose };
  options?: { profile?: string };
  study?: Study | null;
  [extra: string]: unknown;
}

export interface VertebraResult {
  level: Level;
  position: Vec3;
  directors: Mat3;
  u: Vec3 | null;
  v: Vec3 | null;
  pa_bending_deg: number | null;
  lateral_bending_deg: number | null;
  /** The contract's names (openapi.yaml); pa_/lateral_bending_deg stay as deprecated aliases. */
  sagittal_bending_deg?: number | null;
  frontal_bending_deg?: number | null;
  twist_deg: number | null;
  axial_rotation_deg: number;
  axial_rotation_sd_deg?: number | null;
  /** 1 SD of the position relative to the centroid of the 17, mm. */
  position_sd_mm?: Vec3 | null;
}

/** Frontal bending (the contract's new name, else the deprecated alias). */
export const frontalBending = (v: VertebraResult): number | null => v.frontal_bending_deg ?? v.lateral_bending_deg;
/** Sagittal bending (the contract's new name, else the deprecated alias). */
export const sagittalBending = (v: VertebraResult): number | null => v.sagittal_bending_deg ?? v.pa_bending_deg;

export interface CobbCurve {
  upper: Level;
  lower: Level;
  apex: Level;
  angle_deg: number;
  major: boolean;
  convexity: "left" | "right";
  /** True for a curve of one segment: its apex is the SRS apical disc between `apex` and the vertebra below
   * (`apex` names the disc's upper vertebra). Absent from services before it. */
  apical_disc?: boolean;
  apex_axial_rotation_deg: number;
  plane_of_max_curvature_deg: number;
  max_curvature_deg: number;
  angle_sd_deg?: number | null;
}

export interface LenkeInputs {
  model_estimate: true;
  curves: {
    region: string; upper: Level; lower: Level; apex: Level; angle_deg: number; major: boolean; structural_by_magnitude: boolean; structural_by_kyphosis: boolean;
    /** P(regional kyphosis ≥ +20°) under a normal of its value and SD; absent in results made before it. */
    structural_by_kyphosis_probability?: number | null;
  }[];
  t2_t5_kyphosis_deg: number;
  t5_t12_kyphosis_deg: number;
  t10_l2_kyphosis_deg: number;
  t2_t5_kyphosis_sd_deg?: number | null;
  t5_t12_kyphosis_sd_deg?: number | null;
  t10_l2_kyphosis_sd_deg?: number | null;
  sagittal_thoracic_modifier: "-" | "N" | "+";
  /** Probability of the modifier given under a normal of the T5–T12 kyphosis and its SD. */
  sagittal_thoracic_modifier_probability?: number | null;
  not_supported: string[];
}

export interface ViewProjection {
  scale: number;
  translation: Vec2;
  estimated: boolean;
  model?: "weak_perspective" | "perspective";
  rotation_deg?: number;
  scale_source?: "given" | "acquisition" | "prior" | "estimated";
  pixel_spacing_calibration?: string | null;
}

export interface RegistrationResult {
  vertebrae: VertebraResult[];
  measures: {
    cobb: CobbCurve[];
    largest_cobb?: {
      upper: Level;
      lower: Level;
      angle_deg: number;
      angle_sd_deg?: number | null;
      tilt_source: "corners" | "model" | "mixed";
      reported_as_curve: boolean;
    } | null;
    thoracic_kyphosis_t4_t12_deg: number;
    thoracic_kyphosis_t5_t12_deg: number;
    lumbar_lordosis_l1_l5_deg: number;
    thoracic_kyphosis_t4_t12_sd_deg?: number | null;
    thoracic_kyphosis_t5_t12_sd_deg?: number | null;
    lumbar_lordosis_l1_l5_sd_deg?: number | null;
    aasce2019?: { angle_deg: number; upper: Level; lower: Level } | null;
    lenke?: LenkeInputs | null;
  };
  fit: {
    residuals: { view: "pa" | "lateral"; level: Level; residual_mm: number }[];
    mean_registration_error_mm: number;
    energy_fit: number;
    energy_internal: number;
    iterations: number;
    converged: boolean;
    runtime_ms: number;
    pa: ViewProjection;
    lateral?: ViewProjection | null;
    boundary?: "given" | "soft" | "estimated";
    /** Each prior or default that decided a number because the input did not give it: its name (an extensible
     * list: a newer service may name others), the view it concerns and the reason in plain words. */
    assumed?: { name: string; view?: "pa" | "lateral" | null; reason: string }[];
    /** Quantities from the model's prior: scale, depth, kyphosis, lordosis, plane_of_max_curvature, axial_rotation,
     * twist, cobb (every frontal Cobb angle: measures.cobb, largest_cobb, the Lenke curves). */
    unreliable?: string[];
    /** The factor applied to the Laplace SDs: the calibrated constant, times landmark_misfit_ratio when above 1. */
    uncertainty_scale?: number | null;
    /** Birge ratio of the image landmarks about the fitted spine against their stated SDs: above 1 every SD is
     * widened by it. */
    landmark_misfit_ratio?: number | null;
  };
  engine: { version: string; profile: string };
}

export type JobStatus = "queued" | "running" | "succeeded" | "failed" | "cancelled";
export const FINAL_STATUSES: ReadonlySet<JobStatus> = new Set(["succeeded", "failed", "cancelled"]);

export interface Problem {
  type: string;
  title: string;
  status: number;
  detail: string;
  instance?: string | null;
  errors?: { path: string; msg: string; type: string }[] | null;
  [extra: string]: unknown;
}

export interface Job {
  id: string;
  status: JobStatus;
  owner: string | null;
  created_at: string;
  started_at: string | null;
  finished_at: string | null;
  attempts: number;
  engine_version: string | null;
  result: RegistrationResult | null;
  error: Problem | null;
  payload?: JobPayload | null;
  study?: Study | null;
}

export interface Study {
  study_instance_uid: string;
  series_instance_uid?: string | null;
  pa_sop_instance_uid?: string | null;
  lateral_sop_instance_uid?: string | null;
  patient_id?: string | null;
  patient_name?: string | null;
  accession_number?: string | null;
  study_date?: string | null;
}

export function isLevel(value: string): value is Level {
  return (LEVELS as readonly string[]).includes(value);
}

/** GET /v1/pacs */
export interface PacsStatus {
  configured: boolean;
}

/** One image of a study in the PACS (GET /v1/pacs/studies/{study}/images); null when the PACS did not say. */
export interface PacsImage {
  series_instance_uid: string;
  sop_instance_uid: string;
  sop_class_uid: string | null;
  modality: string | null;
  view_position: string | null;
  image_laterality: string | null;
  rows: number | null;
  columns: number | null;
  series_description: string | null;
  series_number: number | null;
  instance_number: number | null;
  patient_id: string | null;
  patient_name: string | null;
  study_date: string | null;
  accession_number: string | null;
}

export interface PacsStudyImages {
  study_instance_uid: string;
  images: PacsImage[];
}

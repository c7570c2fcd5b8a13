// A DICOM radiograph read in the browser with dicom-parser: pixels, window, spacing, geometry,
// patient and study. Uncompressed syntaxes only (implicit and explicit VR little endian,
// PS3.5 §A.1–A.2); a compressed or big-endian film is refused by name.
import { parseDicom, type DataSet } from "dicom-parser";
import type { Vec2 } from "./types";

export type SpacingCalibration = "calibrated" | "projection" | "detector" | "unknown";

export interface Spacing {
  /** mm per pixel [row spacing, column spacing], as DICOM orders (0028,0030); null when unknown. */
  value: Vec2 | null;
  calibration: SpacingCalibration;
  /** Where the value comes from and what it measures, in words. */
  explanation: string;
}

export interface Acquisition {
  magnification?: number;
  distance_source_to_detector_mm?: number;
  distance_source_to_patient_mm?: number;
  /** [columns, rows] of the image in the view's units (px here): DICOM Columns (0028,0011), Rows (0028,0010). */
  image_size?: [number, number];
  /** "perspective" for a projection radiograph's SOP Class (CR, DX...): projected from a point source, its SID and
   * SOD assumed when missing. */
  projection_model?: "perspective" | "weak_perspective";
}

export interface DicomStudy {
  study_instance_uid?: string;
  series_instance_uid?: string;
  sop_instance_uid?: string;
  patient_id?: string;
  patient_name?: string;
  accession_number?: string;
  study_date?: string;
}

export interface DicomFilm {
  width: number;
  height: number;
  /** Stored values after the modality LUT (Rescale Slope/Intercept, PS3.3 §C.11.1.1.2). */
  pixels: Float32Array;
  min: number;
  max: number;
  monochrome1: boolean;
  photometric: string;
  window: { center: number; width: number; fromHeader: boolean };
  /** The spacing as the service reads the header (readSpacing). */
  spacing: Spacing;
  /** The spacing read as if the header gave no ERMF, SID or SOD: what "Ignore header geometry" sends. */
  spacingWithoutGeometry: Spacing;
  acquisition: Acquisition;
  /** The header's geometry values left out of `acquisition`, in words (geometryLeftOut). */
  geometryLeftOut: string[];
  /** The header's spacing attributes left out of `spacing`, in words (spacingLeftOut). */
  spacingLeftOut: string[];
  orientation: [string, string] | null;
  orientationRaw: string | null;
  study: DicomStudy;
  modality: string | null;
  /** SOP Class UID (0008,0016). */
  sopClassUid: string | null;
  viewPosition: string | null;
  transferSyntax: string;
}

/** Storage SOP Classes of projection radiographs (PS3.4 Annex B.5: CR, DX, MG, IO, XA, RF), the list of
 * spine_client/dicom/header.py's PROJECTION_RADIOGRAPH_SOP_CLASSES and Cornerstone3D's: their image is cast
 * from a point source, whatever the Modality (0008,0060) says. */
export const PROJECTION_RADIOGRAPH_SOP_CLASSES: ReadonlySet<string> = new Set([
  "1.2.840.10008.5.1.4.1.1.1", // CR Image Storage
  "1.2.840.10008.5.1.4.1.1.1.1", // Digital X-Ray Image Storage - For Presentation
  "1.2.840.10008.5.1.4.1.1.1.1.1", // Digital X-Ray Image Storage - For Processing
  "1.2.840.10008.5.1.4.1.1.1.2", // Digital Mammography X-Ray Image Storage - For Presentation
  "1.2.840.10008.5.1.4.1.1.1.2.1", // Digital Mammography X-Ray Image Storage - For Processing
  "1.2.840.10008.5.1.4.1.1.1.3", // Digital Intra-Oral X-Ray Image Storage - For Presentation
  "1.2.840.10008.5.1.4.1.1.1.3.1", // Digital Intra-Oral X-Ray Image Storage - For Processing
  "1.2.840.10008.5.1.4.1.1.12.1", // X-Ray Angiographic Image Storage
  "1.2.840.10008.5.1.4.1.1.12.1.1", // Enhanced XA Image Storage
  "1.2.840.10008.5.1.4.1.1.12.2", // X-Ray Radiofluoroscopic Image Storage
  "1.2.840.10008.5.1.4.1.1.12.2.1", // Enhanced XRF Image Storage
  "1.2.840.10008.5.1.4.1.1.12.3", // X-Ray Angiographic Bi-plane Image Storage (retired)
]);

/** The acquisition members that state a film's geometry. */
export const GEOMETRY_KEYS = ["magnification", "distance_source_to_detector_mm", "distance_source_to_patient_mm"] as const;

/** An acquisition without its geometry: what a film whose header gives none is sent with. */
export function withoutGeometry(acq: Acquisition | null | undefined): Acquisition {
  const out: Acquisition = { ...(acq ?? {}) };
  for (const k of GEOMETRY_KEYS) delete out[k];
  return out;
}

/** What the service's schema accepts of a view's acquisition (capabilities.ts). */
export interface AcquisitionMembers {
  imageSize: boolean;
  projectionModel: boolean;
}

/** The header's spacing reading that goes with the film's acquisition: without its geometry when "Ignore header
 * geometry" is ticked. */
export function filmSpacing(d: DicomFilm, geometryIgnored: boolean): Spacing {
  return geometryIgnored ? d.spacingWithoutGeometry : d.spacing;
}

/**
 * The acquisition a view of this film is sent with, as spine_client/dicom/header.py's
 * ``RadiographHeader.view_acquisition`` makes it: the header's ERMF, SID and SOD (readAcquisition), for a
 * calibrated spacing too (the engine multiplies its patient-plane mm by that magnification back to the
 * detector's, spine_engine/clinical.py `calibrated_magnification`); the film's extent in px (the payload's
 * units), for the central ray at its centre; and a point source (projection_model "perspective") for a
 * projection radiograph's SOP class (PROJECTION_RADIOGRAPH_SOP_CLASSES) unless its spacing is calibrated
 * without an ERMF (header.py's `sources["acquisition.projection_model"]` rule). "Ignore header geometry"
 * sends it as a film whose header gives no ERMF, SID or SOD, its spacing read so (filmSpacing).
 */
export function viewAcquisition(d: DicomFilm, accepts: AcquisitionMembers, geometryIgnored: boolean): Acquisition {
  const acq: Acquisition = geometryIgnored ? withoutGeometry(d.acquisition) : { ...d.acquisition };
  if (accepts.imageSize) acq.image_size = [d.width, d.height];
  const pointSource = d.sopClassUid !== null && PROJECTION_RADIOGRAPH_SOP_CLASSES.has(d.sopClassUid);
  const calibrated = filmSpacing(d, geometryIgnored).calibration === "calibrated";
  if (accepts.projectionModel && pointSource && (!calibrated || acq.magnification !== undefined)) {
    acq.projection_model = "perspective";
  }
  return acq;
}

export const UNCOMPRESSED_SYNTAXES: Record<string, string> = {
  "1.2.840.10008.1.2": "implicit VR little endian",
  "1.2.840.10008.1.2.1": "explicit VR little endian",
};

export class DicomError extends Error {}

const tags = {
  transferSyntax: "x00020010",
  rows: "x00280010",
  columns: "x00280011",
  bitsAllocated: "x00280100",
  bitsStored: "x00280101",
  pixelRepresentation: "x00280103",
  samplesPerPixel: "x00280002",
  photometric: "x00280004",
  numberOfFrames: "x00280008",
  slope: "x00281053",
  intercept: "x00281052",
  windowCenter: "x00281050",
  windowWidth: "x00281051",
  pixelSpacing: "x00280030",
  imagerPixelSpacing: "x00181164",
  calibrationType: "x00280a02",
  calibrationDescription: "x00280a04",
  ermf: "x00181114",
  sid: "x00181110",
  sod: "x00181111",
  dse: "x00400306",
  patientOrientation: "x00200020",
  studyUid: "x0020000d",
  seriesUid: "x0020000e",
  sopUid: "x00080018",
  sopClass: "x00080016",
  patientId: "x00100020",
  patientName: "x00100010",
  accession: "x00080050",
  studyDate: "x00080020",
  modality: "x00080060",
  viewPosition: "x00185101",
  pixelData: "x7fe00010",
};

const text = (ds: DataSet, tag: string): string | undefined => {
  const v = ds.string(tag);
  return v === undefined || v.trim() === "" ? undefined : v.trim();
};
/** A Decimal String (DS) value, PS3.5 §6.2: a fixed or floating point number, "0"-"9", "+", "-", "E", "e",
 * "." and leading or trailing spaces only, at most 16 bytes (parseFloat would read "0.15mm" as 0.15). */
const DS_VALUE = /^ *[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)? *$/;
/** The attribute's values as numbers when it holds exactly `count` of them, each a DS value (PS3.5 §6.2) and
 * finite; undefined otherwise (absent, another multiplicity than the attribute's VM, PS3.6 §6, or not a DS). */
const decimals = (ds: DataSet, tag: string, count: number): number[] | undefined => {
  if (!ds.elements[tag] || ds.numStringValues(tag) !== count) return undefined;
  const values: number[] = [];
  for (let i = 0; i < count; i++) {
    const raw = ds.string(tag, i);
    if (raw === undefined || raw.length > 16 || !DS_VALUE.test(raw)) return undefined;
    const v = Number(raw.trim());
    if (!Number.isFinite(v)) return undefined;
    values.push(v);
  }
  return values;
};
const decimal = (ds: DataSet, tag: string): number | undefined => decimals(ds, tag, 1)?.[0];
/** The first of a DS attribute's values whatever their number (Window Center and Width, VM 1-n: the first
 * window is the default, PS3.3 §C.11.2.1.2). */
const firstDecimal = (ds: DataSet, tag: string): number | undefined => {
  const count = ds.elements[tag] ? ds.numStringValues(tag) : undefined;
  return count === undefined || count < 1 ? undefined : decimals(ds, tag, count)?.[0];
};
const pair = (ds: DataSet, tag: string): Vec2 | null => {
  const v = decimals(ds, tag, 2);
  return v && v[0] > 0 && v[1] > 0 ? [v[0], v[1]] : null;
};
/** Pixel Spacing Calibration Type (0028,0A02) Enumerated Values (PS3.3 §10.7.1.2); another value says nothing. */
const CALIBRATION_TYPES = new Set(["GEOMETRY", "FIDUCIAL"]);
const close = (a: Vec2, b: Vec2): boolean => Math.abs(a[0] - b[0]) < 1e-6 && Math.abs(a[1] - b[1]) < 1e-6;
const mm = (v: Vec2): string => (v[0] === v[1] ? `${v[0]} mm` : `${v[0]} × ${v[1]} mm (row × column)`);

/** What a header says of the film's magnification, for its spacing (readSpacing): ERMF (0018,1114) as read (≤ 1
 * named and ignored), SID (0018,1110), and the SOD of the spine's mid-plane from (0018,1111) and (0040,0306)
 * (sourceToPatient) with its rule in words. Empty for a film sent without its header's geometry. */
export interface SpacingGeometry {
  ermf?: number;
  sid?: number;
  sod?: { mm: number; rule: string };
}

/** The SOD of the spine's mid-plane from the header's distances, without ERMF (spine_client/dicom/header.py
 * `_source_to_patient`, docs/dicom.md "Acquisition geometry" rules (b) and (c)), with its rule in words:
 * (DSP + DSE) / 2 with both, else either alone; undefined without a positive one. */
export function sourceToPatient(dsp: number | undefined, dse: number | undefined): { mm: number; rule: string } | undefined {
  const p = dsp !== undefined && dsp > 0 ? dsp : undefined;
  const e = dse !== undefined && dse > 0 ? dse : undefined;
  if (p !== undefined && e !== undefined) return { mm: (p + e) / 2, rule: "the mid-plane between Distance Source to Patient (0018,1111) and Distance Source to Entrance (0040,0306)" };
  if (p !== undefined) return { mm: p, rule: "Distance Source to Patient (0018,1111), the detector-side surface" };
  if (e !== undefined) return { mm: e, rule: "Distance Source to Entrance (0040,0306), the source-side skin" };
  return undefined;
}

/** A spacing rounded for words (4 decimals), in mm. */
const mmRounded = (v: Vec2): string => mm([Number(v[0].toFixed(4)), Number(v[1].toFixed(4))]);

/**
 * Which spacing gives millimetres, as spine_client/dicom/header.py `read_spacing` reads it: PS3.3 §10.7.1.1
 * (Basic Pixel Spacing Calibration Macro) and §C.8.11.4 (Imager Pixel Spacing) as Cornerstone3D's
 * getPixelSpacingInformation and getERMF (which OHIF uses) read them. Only a projection radiograph's SOP Class
 * (PROJECTION_RADIOGRAPH_SOP_CLASSES) has an imager spacing that says anything: another film's Pixel Spacing
 * (0028,0030) is taken as it is ("unknown"). For a projection radiograph, in this order:
 * 1. Pixel Spacing with Pixel Spacing Calibration Type (0028,0A02) GEOMETRY or FIDUCIAL (its Enumerated Values,
 *    §10.7.1.2; another value says nothing): "calibrated", in the patient plane.
 * 2. With Imager Pixel Spacing (0018,1164), the magnification M: ERMF (0018,1114) when > 1, else SID/SOD when
 *    the SOD (sourceToPatient) is below the SID (0018,1110); spacing = Imager Pixel Spacing / M, "calibrated".
 *    Without M, Pixel Spacing smaller than Imager Pixel Spacing (row values) has the magnification already
 *    taken out: "calibrated"; else Pixel Spacing ("projection") or Imager Pixel Spacing ("detector"), mm at
 *    the detector.
 * 3. Else Pixel Spacing alone: "unknown".
 */
export function readSpacing(pixelSpacing: Vec2 | null, imagerSpacing: Vec2 | null, calibrationTypeRead: string | undefined,
  sopClassUid: string | null, geometry: SpacingGeometry = {}): Spacing {
  const ps = pixelSpacing;
  const ips = imagerSpacing;
  if (sopClassUid === null || !PROJECTION_RADIOGRAPH_SOP_CLASSES.has(sopClassUid)) {
    const what = `SOP Class ${sopClassUid ?? "(not given)"} is not a projection radiograph's (PS3.4 Annex B.5)`;
    if (!ps) return { value: null, calibration: "unknown", explanation: `The header gives no pixel spacing of the image (${what}): enter it.` };
    return { value: ps, calibration: "unknown", explanation: `Pixel Spacing ${mm(ps)} taken as it is: ${what}, so the plane it measures is not known.` };
  }
  const calibrationType = calibrationTypeRead && CALIBRATION_TYPES.has(calibrationTypeRead.toUpperCase()) ? calibrationTypeRead.toUpperCase() : undefined;
  if (ps && calibrationType) {
    const same = calibrationType === "GEOMETRY" && ips && close(ps, ips) ? " (though it equals the Imager Pixel Spacing)" : "";
    return { value: ps, calibration: "calibrated", explanation: `Pixel Spacing ${mm(ps)} in the patient plane (calibration type ${calibrationType}${same}).` };
  }
  if (ips) {
    const { ermf, sid, sod } = geometry;
    const illegal = ermf !== undefined && !(ermf > 1) ? ` Its ERMF ${ermf} (≤ 1) is no radiograph's: ignored.` : "";
    const m: [number, string] | null = ermf !== undefined && ermf > 1 ? [ermf, `ERMF ${ermf}`]
      : sid !== undefined && sod !== undefined && sod.mm < sid ? [sid / sod.mm, `SID/SOD ${sid}/${Number(sod.mm.toFixed(4))} mm (SOD: ${sod.rule})`] : null;
    if (m) {
      const v: Vec2 = [ips[0] / m[0], ips[1] / m[0]];
      return { value: v, calibration: "calibrated", explanation: `Imager Pixel Spacing ${mm(ips)} / ${m[1]} = ${mmRounded(v)} in the patient plane.` };
    }
    if (ps && ips[0] > ps[0]) {
      return { value: ps, calibration: "calibrated", explanation: `Pixel Spacing ${mm(ps)} in the patient plane: smaller than the Imager Pixel Spacing ${mm(ips)}, the magnification already taken out.${illegal}` };
    }
    if (ps) {
      const words = close(ps, ips) ? "equals the Imager Pixel Spacing:" : `is larger than the Imager Pixel Spacing ${mm(ips)}, which it stands for:`;
      return { value: ps, calibration: "projection", explanation: `Pixel Spacing ${mm(ps)} ${words} millimetres at the detector, magnified.${illegal}` };
    }
    return { value: ips, calibration: "detector", explanation: `Imager Pixel Spacing ${mm(ips)}: millimetres at the detector, magnified.${illegal}` };
  }
  if (ps) {
    return { value: ps, calibration: "unknown", explanation: `Pixel Spacing ${mm(ps)} without Imager Pixel Spacing or calibration type: the plane it measures is not known.` };
  }
  return { value: null, calibration: "unknown", explanation: "The header gives no pixel spacing: enter it." };
}

/** Patient Orientation (0020,0020) as the principal directions of its two values, or null when it is not of
 * that form. PS3.3 §C.7.6.1.1.1: each value is one of L, R, A, P, H, F, refined by "one or two additional
 * letters", "the principal orientation designated in the first character" (an oblique "FL\\RF" is F, R). */
export function readOrientation(raw: string | undefined): [string, string] | null {
  if (!raw) return null;
  const parts = raw.split("\\").map((p) => p.trim().toUpperCase());
  if (parts.length !== 2 || !parts.every((p) => /^[LRAPHF]{1,3}$/.test(p))) return null;
  return [parts[0][0], parts[1][0]];
}

/**
 * The view's acquisition geometry from the header, by the rules of spine_client/dicom/header.py (docs/dicom.md,
 * "Acquisition geometry"): magnification = ERMF (0018,1114) when > 1 (≤ 1 is no radiograph's, ignored as
 * Cornerstone3D does); SID = (0018,1110); the SOD of the spine's mid-plane = (a) SID / ERMF (ERMF is SID/SOD of
 * the object of interest, PS3.3 §C.8.11.7), else (b) the mid-point of Distance Source to Patient (0018,1111,
 * the detector-side surface) and Distance Source to Entrance (0040,0306, the source-side skin), else (c) either
 * alone. Non-positive values are not distances: left out.
 */
export function readAcquisition(ermf: number | undefined, sid: number | undefined, dsp: number | undefined, dse: number | undefined): Acquisition {
  const m = ermf !== undefined && ermf > 1 ? ermf : undefined;
  const d = sid !== undefined && sid > 0 ? sid : undefined;
  const acquisition: Acquisition = {};
  if (m !== undefined) acquisition.magnification = m;
  if (d !== undefined) acquisition.distance_source_to_detector_mm = d;
  // kept as the header says, even not below the SID: the page names it before sending (checks.ts
  // geometryProblems) rather than sending the SID alone with an assumed SOD
  const sod = d !== undefined && m !== undefined ? d / m : sourceToPatient(dsp, dse)?.mm;
  if (sod !== undefined) acquisition.distance_source_to_patient_mm = sod;
  return acquisition;
}

/** The geometry attributes of spine_client/dicom/header.py's GEOMETRY_KEYWORDS, in words, with what a value
 * of each must be. */
const GEOMETRY_ATTRIBUTES: [string, string, string][] = [
  [tags.ermf, "Estimated Radiographic Magnification Factor (0018,1114)", "a ratio"],
  [tags.sid, "Distance Source to Detector (0018,1110)", "a distance"],
  [tags.sod, "Distance Source to Patient (0018,1111)", "a distance"],
  [tags.dse, "Distance Source to Entrance (0040,0306)", "a distance"],
];

/** Each geometry value the header gives that is no distance or ratio (not one finite number, or not a positive
 * one: a writer's 0 for "not known"), in words: readAcquisition leaves it out, as the service does with a
 * warning (docs/dicom.md, "Acquisition geometry"). */
export function geometryLeftOut(ds: DataSet): string[] {
  const out: string[] = [];
  for (const [tag, name, what] of GEOMETRY_ATTRIBUTES) {
    const element = ds.elements[tag];
    if (!element || element.length === 0) continue;
    const value = decimal(ds, tag);
    if (value === undefined) out.push(`${name} "${(ds.string(tag) ?? "").trim()}" is not one number: left out`);
    else if (!(value > 0)) out.push(`${name} ${value} is not ${what}: left out`);
  }
  return out;
}

/** The spacing attributes (spine_client/dicom/header.py read_spacing), in words. */
const SPACING_ATTRIBUTES: [string, string][] = [
  [tags.pixelSpacing, "Pixel Spacing (0028,0030)"],
  [tags.imagerPixelSpacing, "Imager Pixel Spacing (0018,1164)"],
];

/** Each spacing attribute the header gives that is not two positive numbers (`pair`: a writer's "0\0", a
 * unit in the value), in words: readSpacing reads the other one, as the service does with a warning
 * (docs/dicom.md, "Pixel spacing"); with neither, the film has no spacing. */
export function spacingLeftOut(ds: DataSet): string[] {
  const out: string[] = [];
  for (const [tag, name] of SPACING_ATTRIBUTES) {
    const element = ds.elements[tag];
    if (!element || element.length === 0 || pair(ds, tag) !== null) continue;
    out.push(`${name} "${(ds.string(tag) ?? "").trim()}" is not two positive numbers: left out`);
  }
  return out;
}

/** DICOM DA (YYYYMMDD) as ISO YYYY-MM-DD, or undefined. */
export function isoDate(da: string | undefined): string | undefined {
  const m = da?.match(/^(\d{4})(\d{2})(\d{2})$/);
  return m ? `${m[1]}-${m[2]}-${m[3]}` : undefined;
}

/** PN with its ^ separators as spaces ("DOE^JANE" → "DOE JANE"). */
export function personName(pn: string | undefined): string | undefined {
  return pn?.split("=")[0].split("^").filter(Boolean).join(" ") || undefined;
}

/** The text of what dicom-parser threw: a string, an Error, or {exception, dataSet} (parseDicom wraps
 * the reader's error with the data set read so far). */
export function parserMessage(error: unknown): string {
  if (typeof error === "string") return error;
  if (error instanceof Error) return error.message;
  if (error && typeof error === "object" && "exception" in error) return parserMessage((error as { exception: unknown }).exception);
  return String(error);
}

export function parseFilm(bytes: Uint8Array, name: string): DicomFilm {
  let ds: DataSet;
  try {
    ds = parseDicom(bytes);
  } catch (error) {
    // Without the "DICM" prefix of a DICOM file (PS3.10 §7.1) the bytes are most likely not DICOM at all.
    const part10 = bytes.length > 132 && String.fromCharCode(...bytes.subarray(128, 132)) === "DICM";
    if (!part10) throw new DicomError(`${name} is not a DICOM file: open the radiograph as a DICOM file (.dcm), PNG or JPEG.`);
    throw new DicomError(`${name} is a damaged DICOM file: its header could not be read (${parserMessage(error)}).`);
  }
  const syntax = text(ds, tags.transferSyntax) ?? "1.2.840.10008.1.2";
  if (!(syntax in UNCOMPRESSED_SYNTAXES)) {
    throw new DicomError(
      `${name} is stored with transfer syntax ${syntax}, which this page cannot decode: it reads uncompressed little-endian films only. Export the film uncompressed from the PACS, or as PNG.`,
    );
  }
  const width = ds.uint16(tags.columns) ?? 0;
  const height = ds.uint16(tags.rows) ?? 0;
  const bits = ds.uint16(tags.bitsAllocated) ?? 16;
  const samples = ds.uint16(tags.samplesPerPixel) ?? 1;
  const photometric = text(ds, tags.photometric) ?? "MONOCHROME2";
  const frames = ds.intString(tags.numberOfFrames) ?? 1;
  const element = ds.elements[tags.pixelData];
  if (!element || !width || !height) throw new DicomError(`${name} has no image (no Pixel Data, Rows or Columns).`);
  if (samples !== 1 || !photometric.startsWith("MONOCHROME")) {
    throw new DicomError(`${name} is a ${photometric} image; a radiograph is MONOCHROME1 or MONOCHROME2.`);
  }
  if (frames > 1) throw new DicomError(`${name} has ${frames} frames; open a single radiograph.`);
  if (bits !== 8 && bits !== 16) throw new DicomError(`${name} has ${bits} bits per pixel; 8 or 16 are supported.`);
  const count = width * height;
  if (element.length < count * (bits / 8)) throw new DicomError(`${name}'s Pixel Data is shorter than Rows × Columns.`);
  const signed = ds.uint16(tags.pixelRepresentation) === 1;
  const buffer = ds.byteArray.buffer as ArrayBuffer;
  const offset = ds.byteArray.byteOffset + element.dataOffset;
  const raw = bits === 8
    ? (signed ? new Int8Array(buffer, offset, count) : new Uint8Array(buffer, offset, count))
    : new (signed ? Int16Array : Uint16Array)(buffer.slice(offset, offset + count * 2));
  const bitsStored = ds.uint16(tags.bitsStored) ?? bits;
  const slope = decimal(ds, tags.slope) ?? 1;
  const intercept = decimal(ds, tags.intercept) ?? 0;
  const pixels = new Float32Array(count);
  const mask = bitsStored < bits && !signed ? (1 << bitsStored) - 1 : -1;
  let min = Infinity;
  let max = -Infinity;
  for (let i = 0; i < count; i++) {
    const stored = mask === -1 ? raw[i] : raw[i] & mask;
    const v = stored * slope + intercept;
    pixels[i] = v;
    if (v < min) min = v;
    if (v > max) max = v;
  }
  const center = firstDecimal(ds, tags.windowCenter);
  const widthW = firstDecimal(ds, tags.windowWidth);
  const window = center !== undefined && widthW !== undefined && widthW >= 1
    ? { center, width: widthW, fromHeader: true }
    : { center: (min + max) / 2, width: Math.max(1, max - min), fromHeader: false };
  const [ermf, sid, dsp, dse] = [decimal(ds, tags.ermf), decimal(ds, tags.sid), decimal(ds, tags.sod), decimal(ds, tags.dse)];
  const acquisition = readAcquisition(ermf, sid, dsp, dse);
  const sopClassUid = text(ds, tags.sopClass)?.replace(/\0+$/, "") ?? null;
  const spacingRead = (geometry: SpacingGeometry): Spacing =>
    readSpacing(pair(ds, tags.pixelSpacing), pair(ds, tags.imagerPixelSpacing), text(ds, tags.calibrationType), sopClassUid, geometry);
  const orientationRaw = text(ds, tags.patientOrientation) ?? null;
  return {
    width,
    height,
    pixels,
    min,
    max,
    monochrome1: photometric === "MONOCHROME1",
    photometric,
    window,
    spacing: spacingRead({ ermf, sid: acquisition.distance_source_to_detector_mm, sod: sourceToPatient(dsp, dse) }),
    spacingWithoutGeometry: spacingRead({}),
    acquisition,
    geometryLeftOut: geometryLeftOut(ds),
    spacingLeftOut: spacingLeftOut(ds),
    orientation: readOrientation(orientationRaw ?? undefined),
    orientationRaw,
    study: {
      study_instance_uid: text(ds, tags.studyUid),
      series_instance_uid: text(ds, tags.seriesUid),
      sop_instance_uid: text(ds, tags.sopUid),
      patient_id: text(ds, tags.patientId),
      patient_name: text(ds, tags.patientName), // PN form (Family^Given…), as the payload takes it
      accession_number: text(ds, tags.accession),
      study_date: isoDate(text(ds, tags.studyDate)),
    },
    modality: text(ds, tags.modality) ?? null,
    sopClassUid,
    viewPosition: text(ds, tags.viewPosition) ?? null,
    transferSyntax: syntax,
  };
}

/**
 * 8-bit grey of a value through the linear VOI window of PS3.3 §C.11.2.1.2.1:
 * y = ((x − (c − 0.5)) / (w − 1) + 0.5), clipped to [0, 1]; MONOCHROME1 inverted (white is low).
 */
export function windowToGrey(pixels: Float32Array, center: number, width: number, invert: boolean, out: Uint8ClampedArray): void {
  const w = Math.max(1, width);
  const lo = center - 0.5 - (w - 1) / 2;
  const k = 255 / Math.max(1e-9, w - 1);
  for (let i = 0, j = 0; i < pixels.length; i++, j += 4) {
    let g = (pixels[i] - lo) * k;
    g = g < 0 ? 0 : g > 255 ? 255 : g;
    if (invert) g = 255 - g;
    out[j] = out[j + 1] = out[j + 2] = g;
    out[j + 3] = 255;
  }
}

// Reads a DICOM SR as OHIF does: @cornerstonejs/adapters' MeasurementReport.generateToolState on the
// dcmjs-naturalized dataset, with the referenced image's plane given by Cornerstone3D's metadata registry.
// Usage: node read_sr.mjs SR.dcm SOP_INSTANCE_UID ROW_SPACING COLUMN_SPACING
// Prints JSON: {"CobbAngle": [{"angle": deg, "points": [[x, y, z] x4] (world mm), "imagePoints": [[col, row] x4]}],
//               "tools": {toolType: count}, "skipped": groups without a tool}
import { readFileSync } from 'node:fs';
import dcmjs from 'dcmjs';
import { metaData, utilities } from '@cornerstonejs/core';
import { adaptersSR } from '@cornerstonejs/adapters';

const [path, sop, rowSpacing, columnSpacing] = process.argv.slice(2);
const imageId = `spine:${sop}`;
const plane = {
  frameOfReferenceUID: '1.2.3',
  rows: 1,
  columns: 1,
  rowCosines: [1, 0, 0],
  columnCosines: [0, 1, 0],
  imageOrientationPatient: [1, 0, 0, 0, 1, 0],
  imagePositionPatient: [0, 0, 0],
  rowPixelSpacing: Number(rowSpacing),
  columnPixelSpacing: Number(columnSpacing),
  pixelSpacing: [Number(rowSpacing), Number(columnSpacing)],
};
metaData.addProvider((type, id) => (type === 'imagePlaneModule' && id === imageId ? plane : undefined), 10000);

const bytes = readFileSync(path);
const dict = dcmjs.data.DicomMessage.readFile(bytes.buffer.slice(bytes.byteOffset, bytes.byteOffset + bytes.length));
const dataset = dcmjs.data.DicomMetaDictionary.naturalizeDataset(dict.dict);
const { MeasurementReport } = adaptersSR.Cornerstone3D;
const { log, warn } = console;
let skipped = 0; // groups the adapter has no tool for (per-vertebra measures...): it warns on each
console.log = () => {}; // and logs every measurement it reads
console.warn = () => { skipped += 1; };
const state = MeasurementReport.generateToolState(dataset, { [`${sop}:1`]: imageId }, metaData);
console.log = log;
console.warn = warn;

const cobb = (state.CobbAngle || []).map((m) => {
  const points = m.annotation.data.handles.points.map((p) => Array.from(p));
  return {
    angle: m.annotation.data.cachedStats[`imageId:${imageId}`]?.angle ?? null,
    points,
    imagePoints: points.map((p) => Array.from(utilities.worldToImageCoords(imageId, p))),
    referencedImageId: m.annotation.metadata.referencedImageId,
    findingSites: (m.findingSites || []).map((s) => s.CodeValue),
  };
});
const tools = Object.fromEntries(Object.entries(state).map(([k, v]) => [k, v.length]));
process.stdout.write(JSON.stringify({ CobbAngle: cobb, tools, skipped }) + '\n');

"""The two readers of a radiograph's header agree on what the engine receives.

A film reaches the engine through the service's reader (``spine_client/dicom/header.py``, merged into the
view by ``spine_client/dicom/merge.py``) or through the web page's (``web/src/dicom.ts``, whose film
``web/src/panel.ts`` ``payload()`` turns into the view). Both read the spacing as Cornerstone3D does (Imager
Pixel Spacing divided by the ERMF or SID/SOD, ``calibrated``) and send a calibrated film with the header's
geometry; each view is compared as the engine takes it: detector mm per pixel
(``clinical.detector_spacing``), the point-source geometry (``clinical.pinhole_geometry``), the
fit's initial magnification (``clinical._scale_prior``), the orientation and the image size.

``web/src/dicom.ts`` runs in Node, bundled with the rolldown Vite installs under web/node_modules; the
page's ``payload()`` is restated in ``PAGE_PAYLOAD_JS`` (panel.ts needs a DOM): a film opened in the
panel of its role, its header's spacing confirmed, geometry not ignored, every optional member accepted.
The corpus is written with ``tools.dicom.synthetic`` (explicit and implicit VR little endian), values the
writer cannot make (malformed decimal strings) as raw bytes. The wider differential check, 85 variants,
is described in the report that added this file; it lives outside the repository.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from pydicom.datadict import dictionary_VR, tag_for_keyword
from pydicom.dataelem import RawDataElement
from pydicom.tag import Tag

from spine_client.dicom.errors import InvalidAttribute, MissingAttribute
from spine_client.dicom.header import read_header
from spine_client.dicom.merge import DicomProvenance, merge_view
from spine_engine import clinical, models
from tools.dicom import synthetic

ROOT = Path(__file__).resolve().parents[2]
WEB = ROOT / "web"
ROLLDOWN = WEB / "node_modules" / ".bin" / "rolldown"

PAGE_PAYLOAD_JS = r"""
// web/src/panel.ts payload() for a DICOM film opened in the panel of its role (orientation not chosen,
// spacing confirmed as read, header geometry not ignored, every optional member accepted); its acquisition
// is the page's own viewAcquisition.
import { readFileSync } from "node:fs";
const { parseFilm, viewAcquisition } = await import(process.argv[2]);
const DEFAULT = { pa: ["L", "F"], lateral: ["A", "F"] };
const out = JSON.parse(readFileSync(0, "utf8")).map(({ path, role }) => {
  let d;
  try {
    d = parseFilm(new Uint8Array(readFileSync(path)), path);
  } catch (e) {
    return { error: e.constructor.name, message: String(e.message ?? e) };
  }
  const typed = d.spacing.value ? String(d.spacing.value[1]) : "";
  const t = Number(typed);
  let spacing = null;
  if (typed.trim() !== "" && t > 0 && t <= 10) {
    spacing = Math.abs(d.spacing.value[1] - t) < 1e-9 ? d.spacing.value : [t, t];
  }
  const view = { units: "px", pixel_spacing: spacing, patient_orientation: d.orientation ?? DEFAULT[role] };
  const confirmed = d.spacing.value && view.pixel_spacing === d.spacing.value;
  view.pixel_spacing_calibration = confirmed ? d.spacing.calibration : "unknown";
  view.acquisition = viewAcquisition(d, { imageSize: true, projectionModel: true }, false);
  return { view, leftOut: [...d.geometryLeftOut, ...d.spacingLeftOut] };
});
process.stdout.write(JSON.stringify(out));
"""

IPS = (0.15, 0.15)
"""Imager Pixel Spacing of every film (synthetic's default), mm: what the engine's detector mm must be."""

# (name, role, synthetic.radiograph kwargs, raw DS/CS values by keyword, the engine's detector mm per px
# (column, row) when the header gives a usable spacing, else None)
CASES: list[tuple[str, str, dict[str, Any], dict[str, str], tuple[float, float] | None]] = [
    ("imager spacing only", "pa", {}, {}, IPS),
    ("pixel = imager spacing, implicit VR", "pa", dict(pixel_spacing=IPS, transfer_syntax="implicit"), {}, IPS),
    ("GEOMETRY", "pa", dict(pixel_spacing=(0.12, 0.12), calibration_type="GEOMETRY"), {}, (0.12, 0.12)),
    ("ERMF 1.1", "pa", dict(ermf=1.1), {}, IPS),
    # PS3.3 §C.8.11.7: ERMF is SID/SOD; ≤ 1 is no radiograph's, ignored by both (Cornerstone3D's getERMF)
    ("ERMF 0.9", "pa", dict(ermf=0.9), {}, IPS),
    # docs/dicom.md rule (a): the SOD is SID / ERMF, not (0018,1111)
    ("ERMF, SID and (0018,1111)", "pa", dict(ermf=1.1, sid=1800.0, sod=1640.0), {}, IPS),
    # rule (b): the mid-plane between (0018,1111) and (0040,0306); the service's spacing divided by the same SOD
    ("SID, (0018,1111), (0040,0306), implicit VR", "pa",
     dict(sid=1800.0, sod=1700.0, dse=1450.0, transfer_syntax="implicit"), {}, IPS),
    ("SID, (0040,0306)", "pa", dict(sid=1800.0, dse=1450.0), {}, IPS),
    # a geometry value that is not a positive number (a writer's 0 for "not known", a value with its unit) is no
    # distance or ratio: left out by both, the rest of the geometry read as without it (header.py GEOMETRY_KEYWORDS)
    ("SID 0, (0018,1111)", "pa", dict(sid=0.0, sod=1600.0), {}, IPS),
    ("SID, (0018,1111) 0, (0040,0306)", "pa", dict(sid=1800.0, sod=0.0, dse=1450.0), {}, IPS),
    ("SID negative, (0018,1111)", "pa", dict(sid=-1800.0, sod=1600.0), {}, IPS),
    ("ERMF 0, SID and (0018,1111)", "pa", dict(ermf=0.0, sid=1800.0, sod=1600.0), {}, IPS),
    ("SID not a number, (0018,1111)", "pa", dict(sod=1600.0), {"DistanceSourceToDetector": "1800mm"}, IPS),
    ("ERMF of two values, SID and (0018,1111)", "pa", dict(sid=1800.0, sod=1600.0),
     {"EstimatedRadiographicMagnificationFactor": "1.1\\1.2"}, IPS),
    # a spacing that is not two positive numbers beside one that is: left out by both, the other read
    ("pixel spacing 0, imager spacing", "pa", dict(pixel_spacing=IPS), {"PixelSpacing": "0\\0"}, IPS),
    ("pixel spacing negative, imager spacing", "pa", dict(pixel_spacing=IPS), {"PixelSpacing": "-0.15\\-0.15"}, IPS),
    ("pixel spacing with units, imager spacing", "pa", dict(pixel_spacing=IPS), {"PixelSpacing": "0.15mm\\0.15"},
     IPS),
    ("imager spacing 0, pixel spacing", "pa", dict(pixel_spacing=IPS), {"ImagerPixelSpacing": "0\\0"}, IPS),
    # PS3.3 §10.7.1.2: GEOMETRY and FIDUCIAL are the Enumerated Values; another says nothing
    ("calibration type not enumerated", "pa", dict(pixel_spacing=IPS, calibration_type="XYZ"), {}, IPS),
    # PS3.3 §C.7.6.1.1.1: the first letter of each value is the principal direction
    ("oblique turned film", "pa", dict(patient_orientation=("FL", "RF")), {}, IPS),
    ("mirrored film", "pa", dict(patient_orientation=("R", "F")), {}, IPS),
    # docs/dicom.md: a point source by the SOP Class (PS3.4 Annex B.5), whatever the Modality says
    ("DX storage, Modality OT, SID and SOD", "pa", dict(sid=1800.0, sod=1600.0), {"Modality": "OT"}, IPS),
    ("lateral by View Position", "lateral", dict(patient_orientation=None, view_position="LL"), {}, IPS),
    ("DS exponent and spaces", "pa", dict(imager_pixel_spacing=None), {"ImagerPixelSpacing": " 1.5E-1\\15e-2"}, IPS),
    # PS3.6: Imager Pixel Spacing has VM 2; PS3.5 §6.2: a DS holds digits, sign, exponent, point and spaces only
    ("one spacing value", "pa", dict(imager_pixel_spacing=None), {"ImagerPixelSpacing": "0.15"}, None),
    ("spacing with units", "pa", dict(imager_pixel_spacing=None), {"ImagerPixelSpacing": "0.15mm\\0.15"}, None),
    # Cornerstone3D's getERMF without a calibration type (docs/dicom.md "Pixel spacing"): Pixel Spacing below Imager
    # Pixel Spacing has the magnification taken out ('calibrated') when the header gives no magnification ...
    ("pixel < imager spacing", "pa", dict(pixel_spacing=(0.12, 0.12)), {}, (0.12, 0.12)),
    # ... but ERMF > 1, then SID/SOD, come first: Imager Pixel Spacing / (1800/1600), multiplied back by the engine
    ("pixel < imager spacing, SID and SOD", "pa", dict(pixel_spacing=(0.12, 0.12), sid=1800.0, sod=1600.0), {}, IPS),
    # Pixel Spacing above Imager Pixel Spacing stands for the detector's ('projection'), a point source
    ("pixel > imager spacing", "pa", dict(pixel_spacing=(0.18, 0.18)), {}, (0.18, 0.18)),
    # calibrated films keep the header's geometry (header.py view_acquisition): the engine multiplies their
    # patient-plane mm by the ERMF (0.12 · 1.25 = 0.15), else SID/SOD (0.13 · 1800/1560 = 0.15)
    ("GEOMETRY with ERMF", "pa", dict(pixel_spacing=(0.12, 0.12), calibration_type="GEOMETRY", ermf=1.25), {}, IPS),
    ("FIDUCIAL with SID and SOD", "pa",
     dict(pixel_spacing=(0.13, 0.13), calibration_type="FIDUCIAL", sid=1800.0, sod=1560.0), {}, IPS),
    # PS3.3 §C.8.11.7: an ERMF ≤ 1 is ignored, so no point source for calibrated mm (header.py projection_model) ...
    ("GEOMETRY with ERMF 0.9", "pa", dict(pixel_spacing=(0.12, 0.12), calibration_type="GEOMETRY", ermf=0.9), {},
     (0.12, 0.12)),
    # ... but SID and SOD still make one: 0.12 · 1800/1600 = 0.135 mm at the detector
    ("GEOMETRY with ERMF 0.9, SID and SOD", "pa",
     dict(pixel_spacing=(0.12, 0.12), calibration_type="GEOMETRY", ermf=0.9, sid=1800.0, sod=1600.0), {},
     (0.135, 0.135)),
    # PS3.4 Annex B.5: Secondary Capture (1.2.840.10008.5.1.4.1.1.7) is no projection radiograph; its Imager Pixel
    # Spacing says nothing of the image (Cornerstone3D reads Pixel Spacing only)
    ("Secondary Capture, imager spacing only", "pa", dict(extra={"SOPClassUID": "1.2.840.10008.5.1.4.1.1.7"}), {},
     None),
]  # fmt: skip


def _film(path: Path, kwargs: dict[str, Any], raw: dict[str, str]) -> Path:
    """A synthetic film with ``raw`` values written as their bytes (a malformed DS pydicom would not write)."""
    ds = synthetic.radiograph(**kwargs)
    implicit = kwargs.get("transfer_syntax") == "implicit"
    for keyword, text in raw.items():
        tag = Tag(tag_for_keyword(keyword) or 0)
        data = text.encode("ascii")
        data += b" " * (len(data) % 2)  # PS3.5 §7.1.1: even length, DS padded with a space
        vr = None if implicit else dictionary_VR(tag)
        ds._dict[tag] = RawDataElement(tag, vr, len(data), data, 0, implicit, True)
    synthetic.write(ds, path)
    return path


def _page_views(tmp_path: Path, films: list[tuple[Path, str]]) -> list[dict[str, Any]]:
    bundle = tmp_path / "dicom.mjs"
    subprocess.run([str(ROLLDOWN), "src/dicom.ts", "--platform", "node", "--format", "esm", "--file", str(bundle)],
                   cwd=WEB, check=True, capture_output=True, timeout=60)  # fmt: skip
    script = tmp_path / "page_payload.mjs"
    script.write_text(PAGE_PAYLOAD_JS)
    request = json.dumps([{"path": str(p), "role": role} for p, role in films])
    done = subprocess.run(["node", str(script), str(bundle)], input=request, capture_output=True, text=True,
                          check=True, timeout=60)  # fmt: skip
    views: list[dict[str, Any]] = json.loads(done.stdout)
    return views


LEFT_OUT_TAG = re.compile(r"\((0018,111[04]|0018,1111|0040,0306|0028,0030|0018,1164)\)")
"""The tag of a geometry attribute (header.py GEOMETRY_KEYWORDS) or a spacing one (``read_spacing``) named in a
reader's words."""


SPACING_TAGS = ("0028,0030", "0018,1164")
"""Pixel Spacing and Imager Pixel Spacing."""


def _left_out(messages: list[str]) -> list[str]:
    """The geometry and spacing attributes' tags that the messages name as left out, sorted."""
    return sorted(m[1] for m in (LEFT_OUT_TAG.search(w) for w in messages if w.endswith("left out")) if m)


def _service_view(path: Path, role: str) -> dict[str, Any] | None:
    """The view the service builds from the film (None when it refuses the film for its spacing)."""
    header = read_header(path)
    payload: dict[str, Any] = {role: {"units": "px", "landmarks": []}}
    try:
        merge_view(payload, role, header, source="file", provenance=DicomProvenance())  # type: ignore[arg-type]
    except MissingAttribute:
        return None
    view: dict[str, Any] = payload[role]
    return view


def _engine(view: dict[str, Any], role: str) -> dict[str, Any]:
    """What the engine takes from a view (module docstring), rounded to 1e-6 (DS values carry at most 16
    characters, PS3.5 §6.2; the readers' arithmetic differs in the last bits)."""
    cls = models.PAView if role == "pa" else models.LateralView
    model = cls.model_validate({**view, "landmarks": [{"level": "T1", "point": [10.0, 10.0]}]})
    pinhole = clinical.pinhole_geometry(model, role)
    scale, from_prior = clinical._scale_prior(model)  # the fit's initial magnification, and whether it is the prior
    acq = model.acquisition
    geometry = None
    if pinhole is not None:
        geometry = [round(pinhole.sid_mm, 6), round(pinhole.sod_mm, 6), pinhole.depth_prior_sd_mm, pinhole.assumed]
    return {
        "detector_mm_per_px": [round(float(v), 6) for v in clinical.detector_spacing(model)],
        "pinhole": geometry,
        "initial_scale": [round(scale, 6), from_prior],
        "orientation": list(model.patient_orientation),
        "image_size": None if acq is None or acq.image_size is None else list(acq.image_size),
    }


@pytest.fixture(scope="module")
def readings(tmp_path_factory: pytest.TempPathFactory) -> list[tuple[str, Any, Any, Any]]:
    if shutil.which("node") is None or not ROLLDOWN.exists():
        pytest.skip("needs node and web/node_modules (make node-deps)")
    tmp_path = tmp_path_factory.mktemp("agreement")
    films = [(_film(tmp_path / f"{i}.dcm", kwargs, raw), role) for i, (_, role, kwargs, raw, _) in enumerate(CASES)]
    pages = _page_views(tmp_path, films)
    out = []
    for (name, role, _, _, detector), (path, _), page in zip(CASES, films, pages, strict=True):
        service: dict[str, Any] | InvalidAttribute | None
        try:
            service = _service_view(path, role)
        except InvalidAttribute as exc:
            service = exc
        out.append((name, detector, service, page))
    return out


@pytest.mark.parametrize("case", [c[0] for c in CASES])
def test_page_and_service_name_the_same_values_left_out(
    case: str, tmp_path: Path, readings: list[tuple[str, Any, Any, Any]]
) -> None:
    """A geometry value that is no distance or ratio, and a spacing that is not two positive numbers beside a
    usable one, are left out by both readers, and both say which: the service in the job's warnings
    (``dicom.<view>.warnings``), the page in the film's header panel (Geometry and Spacing rows)."""
    _, _, kwargs, raw, _ = next(c for c in CASES if c[0] == case)
    page = next(r for r in readings if r[0] == case)[3]
    page_left_out = _left_out(page["leftOut"])
    try:
        service: tuple[str, ...] = read_header(_film(tmp_path / "film.dcm", kwargs, raw)).warnings
    except InvalidAttribute:  # refused for its spacing (the test above), naming it: no geometry is read of it
        service = ()
        page_left_out = [tag for tag in page_left_out if tag not in SPACING_TAGS]  # the page asks for a spacing
    assert page_left_out == _left_out(list(service)), (page["leftOut"], service)


@pytest.mark.parametrize("case", [c[0] for c in CASES])
def test_page_and_service_give_the_engine_the_same_film(case: str, readings: list[tuple[str, Any, Any, Any]]) -> None:
    _, detector, service, page = next(r for r in readings if r[0] == case)
    role = next(c[1] for c in CASES if c[0] == case)
    assert "error" not in page, f"the page failed to open the film: {page}"
    if detector is None:
        # neither reader takes a spacing from the header: the service refuses the film naming the attribute,
        # the page asks for the spacing (its view has none)
        assert isinstance(service, InvalidAttribute | type(None)), service
        assert page["view"]["pixel_spacing"] is None
        return
    assert not isinstance(service, Exception) and service is not None, service
    service_engine, page_engine = _engine(service, role), _engine(page["view"], role)
    assert service_engine == page_engine
    assert service_engine["detector_mm_per_px"] == pytest.approx(detector, rel=1e-9)

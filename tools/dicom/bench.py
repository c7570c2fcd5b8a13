"""Timing of the DICOM layer: read a header (file, and WADO-RS metadata from a local Orthanc), build
the SR and the figure's SC, push both by STOW-RS. ``python -m tools.dicom.bench [--repeat N] [--out FILE]``.

Inputs: a synthetic DX radiograph of 3000 × 2500 pixels at 16 bits (15 MB of pixel data; the header
read stops before the pixels), the 17-level C-curve payload of the tests, its registered result, and
its figure (spine_engine.figures, 110 dpi). The PACS is a throwaway Orthanc on loopback
(``tools.dicom.orthanc``), so network time is near zero: a hospital PACS adds its round trips.
Prints a Markdown table of median, 90th percentile and minimum per step, in milliseconds; ``--out``
also writes them as JSON, with the command and the versions of Orthanc and its DICOMweb plug-in.
"""

from __future__ import annotations

import argparse
import io
import math
import statistics
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import requests

from benches.report import write_json
from services.core.config import DicomwebConfig
from services.dicom.dicomweb import Pacs, part10
from services.dicom.sc import build_sc
from services.dicom.sr import SourceImage, StudyIdentity, build_sr
from spine_client.dicom.header import read_header
from spine_engine import register
from spine_engine.figures import render_figure
from spine_engine.levels import LEVELS
from tools.dicom import synthetic
from tools.dicom.orthanc import OrthancServer, orthanc_missing, start_orthanc, stop_orthanc

SPACING_MM = 0.15


def _payload() -> dict[str, Any]:
    """17 endplate midpoints (px at 0.15 mm) on a 15 mm C-curve over 420 mm, T1 and L5 given."""
    identity = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]
    landmarks = []
    for i, level in enumerate(LEVELS):
        t = i / (len(LEVELS) - 1)
        col, row = 100.0 + 15.0 * math.sin(math.pi * t), 50.0 + 420.0 * t
        landmarks.append({"level": level, "point": [col / SPACING_MM, row / SPACING_MM]})
    return {
        "pa": {"units": "px", "pixel_spacing": [SPACING_MM, SPACING_MM], "landmarks": landmarks},
        "boundary": {"T1": {"position": [0.0, 0.0, 0.0], "directors": identity},
                     "L5": {"position": [0.0, 0.0, -420.0], "directors": identity}},
    }  # fmt: skip


def _time(fn: Callable[[], Any], repeat: int) -> list[float]:
    fn()  # warm-up: first imports and caches
    out = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn()
        out.append((time.perf_counter() - start) * 1000.0)
    return out


def _row(name: str, samples: list[float]) -> dict[str, Any]:
    """One step's figures: median, 90th percentile (nearest rank), minimum (ms) and number of runs."""
    ordered = sorted(samples)
    p90 = ordered[min(len(ordered) - 1, math.ceil(0.9 * len(ordered)) - 1)]
    return {"step": name, "median_ms": statistics.median(ordered), "p90_ms": p90, "min_ms": ordered[0],
            "runs": len(ordered)}  # fmt: skip


def _line(row: dict[str, Any]) -> str:
    return f"| {row['step']} | {row['median_ms']:.1f} | {row['p90_ms']:.1f} | {row['min_ms']:.1f} | {row['runs']} |"


def _versions(server: OrthancServer) -> dict[str, str | None]:
    """Versions of the Orthanc under test and of its DICOMweb plug-in, as its REST API reports them."""

    def version(path: str) -> str | None:
        try:
            answer = requests.get(f"{server.url}{path}", auth=server.auth(), timeout=5)
            return str(answer.json()["Version"]) if answer.ok else None
        except (requests.RequestException, ValueError, KeyError):
            return None

    return {"version": version("/system"), "dicomweb_plugin": version("/plugins/dicom-web")}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.dicom.bench", description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=20, help="timed runs per step (after one warm-up)")
    parser.add_argument("--out", type=Path, help="also write the figures as JSON to this file")
    args = parser.parse_args(argv)
    versions: dict[str, str | None] | None = None

    image = synthetic.radiograph(rows=3000, columns=2500, imager_pixel_spacing=(SPACING_MM, SPACING_MM))
    data = part10(image)
    payload = _payload()
    result = register(payload)
    png = render_figure(result, payload)
    header = read_header(data)
    identity = StudyIdentity(study_instance_uid=header.study_instance_uid, patient_id=header.patient_id,
                             patient_name=header.patient_name, accession_number=header.accession_number,
                             study_date=header.study_date)  # fmt: skip
    source = {"pa": SourceImage(header.sop_instance_uid, str(header.sop_class_uid), header.series_instance_uid,
                                header.study_instance_uid)}  # fmt: skip
    job = uuid.uuid4()
    rows = [
        _row(f"read header, Part 10 file of {len(data) / 1e6:.0f} MB (pydicom, stops before pixels)",
             _time(lambda: read_header(data), args.repeat)),
        _row("build SR (highdicom TID 1500, 17 landmarks) and write Part 10",
             _time(lambda: part10(build_sr(result, payload, job, identity, source)), args.repeat)),
        _row(f"build figure SC ({len(png) / 1e3:.0f} kB PNG) and write Part 10",
             _time(lambda: part10(build_sc(png, job, identity)), args.repeat)),
    ]  # fmt: skip
    missing = orthanc_missing()
    if missing:
        print(f"no Orthanc: {missing}; PACS steps not measured", file=sys.stderr)
    else:
        sr, sc = build_sr(result, payload, job, identity, source), build_sc(png, job, identity)
        with tempfile.TemporaryDirectory(prefix="spine-dicom-bench-") as folder:
            proc, server = start_orthanc(Path(folder))
            try:
                versions = _versions(server)
                with Pacs(DicomwebConfig(server.dicomweb_url, server.username, server.password)) as pacs:
                    pacs.store([image])
                    sop, study, series = image.SOPInstanceUID, image.StudyInstanceUID, image.SeriesInstanceUID
                    rows.append(_row("read header by WADO-RS metadata (series known)",
                                     _time(lambda: pacs.read_header(study, sop, series), args.repeat)))  # fmt: skip
                    rows.append(_row("read header by QIDO-RS + WADO-RS metadata (series unknown)",
                                     _time(lambda: pacs.read_header(study, sop), args.repeat)))  # fmt: skip
                    size = (len(part10(sr)) + len(part10(sc))) / 1e6
                    rows.append(_row(f"STOW-RS of SR + SC ({size:.1f} MB, one request)",
                                     _time(lambda: pacs.store([sr, sc]), args.repeat)))  # fmt: skip
            finally:
                stop_orthanc(proc)
    out = io.StringIO()
    out.write("| step | median ms | p90 ms | min ms | runs |\n| --- | --- | --- | --- | --- |\n")
    out.write("\n".join(_line(row) for row in rows) + "\n")
    sys.stdout.write(out.getvalue())
    if args.out:
        command = " ".join(["python -m tools.dicom.bench", *(sys.argv[1:] if argv is None else argv)])
        write_json(args.out, {"command": command, "settings": {"repeat": args.repeat}, "orthanc": versions,
                              "steps": rows})  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())

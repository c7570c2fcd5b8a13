"""/v1/pacs: open a study from the PACS the service is connected to (``SPINE_DICOMWEB_URL``).

``GET /v1/pacs`` says whether a PACS is configured; ``…/studies/{study}/images`` lists a study's images
(QIDO-RS, PS3.18 §10.6); ``…/studies/{study}/series/{series}/instances/{sop}`` returns one image as a
DICOM Part 10 file in Explicit VR Little Endian (WADO-RS, §10.4, the PACS transcoding it), the only
encoding the page decodes. Every request needs an API key that may browse the PACS (``may_browse_pacs``):
an admin key, or a key of a client named in ``SPINE_PACS_CLIENTS``; any other key gets a 403 problem
``forbidden`` naming the permission ``pacs``, before the PACS is contacted, on every route here (the
page, refused ``GET /v1/pacs``, offers no "Open from the PACS"). A client's integration submits jobs
naming its films and needs none of this: without the permission, its key cannot read any patient's
images. Browsing the PACS touches no job, so there is no audit row (the audit trail is per job): the
access log line (request id, key id, path with the UIDs) records who opened what, and the job posted
from the page is audited as any other.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Annotated

from fastapi import APIRouter, Depends, Path
from fastapi.responses import Response

from services.api.deps import AccessDep, CurrentCaller, SettingsDep
from services.api.errors import ProblemError
from services.api.schemas import BINARY_SCHEMA, PacsStatus, PacsStudyImages, problem_responses
from services.core.config import Settings
from services.core.problems import problem
from services.db.keys import Caller
from services.dicom.dicomweb import Pacs, part10
from services.dicom.errors import DicomwebError, InstanceNotFound, PacsUnavailable, TransferSyntaxUnavailable
from services.dicom.results import PART10_MEDIA_TYPE
from spine_engine.models import DICOM_UID_STRICT_PATTERN

PERMISSION = "pacs"
"""The permission a key needs for /v1/pacs, named by the 403 problem (its ``permission`` member)."""


def may_browse_pacs(caller: Caller, settings: Settings) -> bool:
    """Whether ``caller`` may browse the PACS: an admin key, or a key of a client in ``SPINE_PACS_CLIENTS``."""
    return caller.is_admin or caller.name in settings.pacs_client_names


async def require_pacs_permission(caller: CurrentCaller, settings: SettingsDep) -> None:
    """A 403 ``forbidden`` problem naming the permission ``pacs`` for a key that may not browse the PACS."""
    if not may_browse_pacs(caller, settings):
        raise ProblemError(problem(
            "forbidden",
            f"this API key may not browse the PACS (permission `{PERMISSION}`): its client {caller.name!r} is not "
            "in the service's SPINE_PACS_CLIENTS, and the PACS's images are every patient's; ask the operator",
            permission=PERMISSION,
        ))  # fmt: skip


router = APIRouter(prefix="/v1/pacs", tags=["dicom"], dependencies=[Depends(require_pacs_permission)])
RETRY_AFTER_S = 10
"""Retry-After of a 503 when the PACS did not answer (s)."""

Uid = Annotated[
    str,
    Path(
        pattern=DICOM_UID_STRICT_PATTERN,
        max_length=64,
        description="A DICOM UID (PS3.5 §9.1): digits in dot-separated components without leading zeros, "
        "at most 64 characters.",
    ),
]


NOT_CONFIGURED = (
    "403 `forbidden` (member `permission`: `pacs`) for a key that may not browse the PACS: only admin keys and the "
    "keys of the clients named in SPINE_PACS_CLIENTS may, since the PACS holds every patient's images; "
    "404 `dicomweb-not-configured` when the service has no PACS (SPINE_DICOMWEB_URL unset); 503 "
    "`dicomweb-unavailable` (with Retry-After) when the PACS does not answer, times out, or refuses the "
    "service's credentials; 422 for a path parameter that is not a DICOM UID."
)


@contextmanager
def _pacs(settings: Settings) -> Iterator[Pacs]:
    """The configured PACS, its errors turned into the problems their types name (``DicomError.problem``),
    whose details name the PACS by ``dicomweb.shown_url``."""
    config = settings.dicomweb
    if config is None:
        raise ProblemError(problem("dicomweb-not-configured",
                                   "the service is not connected to a PACS: set SPINE_DICOMWEB_URL"))  # fmt: skip
    try:
        with Pacs(config) as pacs:
            yield pacs
    except InstanceNotFound as exc:  # StudyNotFound too
        # an image asked for by its path is a 404 here, where a job naming it fails with 422
        detail = exc.message
        raise ProblemError(problem(exc.problem, detail, status=404, uids=exc.uids)) from None
    except TransferSyntaxUnavailable as exc:
        raise ProblemError(problem(exc.problem, exc.message)) from None
    except PacsUnavailable as exc:
        raise ProblemError(problem(exc.problem, exc.message),
                           headers={"Retry-After": str(RETRY_AFTER_S)}) from None  # fmt: skip
    except DicomwebError as exc:  # the PACS answered with something unusable (502)
        raise ProblemError(problem(exc.problem, exc.message)) from None


@router.get(
    "",
    response_model=PacsStatus,
    summary="Whether the service is connected to a PACS",
    description="`configured` is true when SPINE_DICOMWEB_URL is set; the PACS is not contacted. 403 `forbidden` "
    "(member `permission`: `pacs`) for a key that may not browse the PACS (admin keys and the keys of the clients "
    "named in SPINE_PACS_CLIENTS may).",
    responses=problem_responses(403),
)
def pacs_status(settings: SettingsDep, access: AccessDep) -> PacsStatus:
    return PacsStatus(configured=settings.dicomweb is not None)


@router.get(
    "/studies/{study_instance_uid}/images",
    response_model=PacsStudyImages,
    summary="The images of a study in the PACS",
    description="QIDO-RS search of the study's instances with their series, SOP class, modality, view position, "
    "laterality, size, series description and the patient and study identifiers; only images (radiograph "
    "modalities, or any instance with Rows and Columns), sorted by series then instance number. 404 "
    "`dicomweb-study-not-found` when the PACS lists no instance of the study. " + NOT_CONFIGURED,
    responses=problem_responses(403, 404, 422, 503),
)
def study_images(study_instance_uid: Uid, settings: SettingsDep, access: AccessDep) -> PacsStudyImages:
    with _pacs(settings) as pacs:
        images = pacs.study_images(study_instance_uid)
    return PacsStudyImages(study_instance_uid=study_instance_uid, images=images)


@router.get(
    "/studies/{study_instance_uid}/series/{series_instance_uid}/instances/{sop_instance_uid}",
    response_class=Response,
    summary="One image from the PACS as a DICOM file (Explicit VR Little Endian)",
    description="WADO-RS retrieve of the instance asking for transfer syntax 1.2.840.10008.1.2.1 (the PACS "
    "transcodes a compressed image), returned as a DICOM Part 10 file: what the page opens like a file from "
    "disk. 404 `dicomweb-instance-not-found` when the PACS does not hold it; 502 "
    "`dicomweb-transfer-syntax-unavailable` when the PACS cannot send it uncompressed. " + NOT_CONFIGURED,
    responses={
        200: {
            "content": {PART10_MEDIA_TYPE: {"schema": BINARY_SCHEMA}},
            "description": "The image as a DICOM Part 10 file, Explicit VR Little Endian.",
        },
        **problem_responses(403, 404, 422, 502, 503),
    },
)
def study_instance(
    study_instance_uid: Uid, series_instance_uid: Uid, sop_instance_uid: Uid, settings: SettingsDep, access: AccessDep
) -> Response:
    with _pacs(settings) as pacs:
        ds = pacs.retrieve_explicit_le(study_instance_uid, series_instance_uid, sop_instance_uid)
    headers = {"Content-Disposition": f'attachment; filename="{sop_instance_uid}.dcm"'}
    return Response(part10(ds), media_type=PART10_MEDIA_TYPE, headers=headers)

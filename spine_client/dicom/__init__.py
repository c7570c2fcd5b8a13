"""A radiograph's DICOM header read into the payload's view and study fields (``header``), merged
into a payload with the provenance of each value (``merge``), and the refusals of both (``errors``);
the rules for DICOM times, date-times and UTC offsets that the service's SR, SC and FHIR export share
(``datetimes``, standard library only).

Needs pydicom: the ``spine-client[dicom]`` extra. One reader for both sides: ``spine submit
--pa-dicom`` reads the files on the client's machine, and the service's DICOM layer
(``services.dicom``) reads the images it fetches from its PACS with the same code.
"""

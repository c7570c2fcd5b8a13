"""DICOM times, date-times and UTC offsets: one rule for each, used by the header reader (``header``), the
checks of a client's ``dicom`` block (``merge``), the SR and SC (``services.dicom.sr``) and the FHIR export
(``services.fhir.export``). Standard library only: the service imports it without pydicom's reader.

UTC offsets. PS3.5 §6.2 (DT): ``&ZZXX`` is ``+`` or ``-``, ZZ hours and XX minutes of the offset, in the
range -1200 to +1400; UTC is ``+0000`` and ``-0000`` shall not be used. PS3.3 §C.12.1.1.8: Timezone Offset
From UTC (0008,0201) has that form and dates every DA and TM of the instance, and every DT without its own
suffix (its Note 2); without it they are in no stated zone. A value that is not such an offset
(``"+2500"``, ``"0100"``, ``"-0000"``, ``"+01:00"``) is ignored, as if absent, never a refusal: the
attribute is Type 3 and changes no measurement, refusing the film would block the clinical job for a
clock label, and the header reader skips a malformed date or time the same way (docs/dicom.md, "Text
values"). ``-0000`` is ignored too: RFC 3339 §4.3 gives it the meaning "offset unknown", which is what
absent says.

Leap seconds. PS3.5 §6.2 gives the seconds of a TM and of a DT the range 00–60, 60 being a leap second
(ITU-R TF.460: 23:59:60 UTC); ISO 8601, RFC 3339 §5.6 (``time-second`` 00–60) and FHIR R4 ``dateTime``
write it too, but Python's ``datetime`` holds no second 60. Representation: a value stays text as its
standard writes it, second 60 included: a TM as the header has it (``"235960"``), a date-time as ISO 8601
(``"2016-12-31T23:59:60+00:00"``, ``iso_time``). Where a ``datetime`` is needed, to check the calendar
date and the rest of the value, second 60 is read as second 59 of the same minute (``parse_iso_datetime``),
as pydicom's ``valuerep.TM`` and ``DT`` do; the text is never rewritten. Like DICOM, RFC 3339 and FHIR,
the syntax is checked, not the leap-second table: 60 is taken in any minute (in a zone other than UTC a
leap second falls in another minute, 00:59:60+01:00).
"""

from __future__ import annotations

import re
from datetime import UTC, date, datetime, timedelta, timezone

_OFFSET = re.compile(r"^([+-])(\d{2})(\d{2})$")
LOWEST_OFFSET = timedelta(hours=-12)
HIGHEST_OFFSET = timedelta(hours=14)
"""The range of a DICOM offset (PS3.5 §6.2, DT), also inside FHIR's (R4 ``dateTime``: -14:00 to +14:00)."""
UTC_OFFSET_FORM = "&ZZXX from -1200 to +1400, never -0000 (PS3.5 §6.2, DT; PS3.3 §C.12.1.1.8)"
"""What a UTC offset must be, in the words of every message about one."""

UTC_OFFSET_PATTERN = r"^(\+(0\d|1[0-3])[0-5]\d|\+1400|-(00(0[1-9]|[1-5]\d)|0[1-9][0-5]\d|1[01][0-5]\d)|-1200)$"
"""``utc_offset_problem``'s rule as one regular expression (no look-around, so JSON Schema and pydantic's
Rust engine take it): +0000 to +1359, +1400, -0001 to -1159, -1200. A test holds the two equal on every
sign and four digits."""


def utc_offset_problem(text: str) -> str | None:
    """Why ``text`` is not a DICOM UTC offset as DICOM writes it (module docstring), None when it is."""
    match = _OFFSET.match(text)
    if match is None:
        return "is not a UTC offset &ZZXX (a sign, two digits of hours and two of minutes, PS3.5 §6.2)"
    sign, hours, minutes = match.groups()
    if int(minutes) > 59:
        return f"has {minutes} minutes: an offset's minutes are 00 to 59 (PS3.5 §6.2)"
    if text == "-0000":
        return "is an offset that shall not be used: UTC is +0000, never -0000 (PS3.3 §C.12.1.1.8)"
    offset = timedelta(hours=int(hours), minutes=int(minutes)) * (-1 if sign == "-" else 1)
    if not LOWEST_OFFSET <= offset <= HIGHEST_OFFSET:
        return "is beyond the range of an offset, -1200 to +1400 (PS3.5 §6.2)"
    return None


def parse_utc_offset(text: object) -> timezone | None:
    """The zone of a DICOM offset ``&ZZXX`` (module docstring; padding spaces aside); None when absent or
    not a valid offset (``utc_offset_problem``)."""
    if not isinstance(text, str) or utc_offset_problem(text.strip()) is not None:
        return None
    sign, hours, minutes = _OFFSET.match(text.strip()).groups()  # type: ignore[union-attr]
    offset = timedelta(hours=int(hours), minutes=int(minutes)) * (-1 if sign == "-" else 1)
    return UTC if offset == timedelta(0) else timezone(offset)


def format_utc_offset(zone: timezone) -> str:
    """``zone`` as DICOM writes an offset (``+0100``, ``-0530``, ``+0000`` for UTC)."""
    offset = zone.utcoffset(None)
    sign = "-" if offset < timedelta(0) else "+"
    minutes = abs(offset) // timedelta(minutes=1)
    return f"{sign}{minutes // 60:02d}{minutes % 60:02d}"


def iso_offset(zone: timezone) -> str:
    """``zone`` as ISO 8601 and FHIR ``dateTime`` write an offset (``+01:00``, ``+00:00`` for UTC)."""
    text = format_utc_offset(zone)
    return f"{text[:3]}:{text[3:]}"


TM_PATTERN = re.compile(r"^([01]\d|2[0-3])(?:([0-5]\d)(?:([0-5]\d|60)(\.\d{1,6})?)?)?$")
"""A DICOM TM (PS3.5 §6.2): HH, HHMM, HHMMSS or HHMMSS.F to HHMMSS.FFFFFF; hours 00–23, minutes 00–59,
seconds 00–60 (a leap second). Groups: hours, minutes, seconds, fraction with its dot."""


def is_dicom_time(text: str) -> bool:
    """Whether ``text`` is a TM as DICOM writes it (``TM_PATTERN``), a leap second ``235960`` included."""
    return TM_PATTERN.match(text) is not None


def iso_time(tm: str) -> str | None:
    """A TM's time of day to the second as ISO 8601 ``hh:mm:ss`` (its fraction left out, second 60
    kept); None when ``tm`` is not a TM or stops before its seconds (a time to the minute is not one to
    the second)."""
    match = TM_PATTERN.match(tm)
    if match is None or match.group(3) is None:
        return None
    hh, mm, ss, _ = match.groups()
    return f"{hh}:{mm}:{ss}"


_DT = re.compile(r"^(\d{4}(?:\d{2}(?:\d{2})?)?)([0-9.]*)([+-].*)?$")


def split_dt(text: str) -> tuple[str, str, str | None] | None:
    """A DICOM DT ``YYYYMMDDHHMMSS.FFFFFF&ZZXX`` (PS3.5 §6.2) as (date digits, time as a TM, offset suffix
    or None), each part as written and unchecked (a suffix that is no offset included, for the caller to
    judge); None when it does not start with a year, or its time holds other characters than digits and a
    dot."""
    match = _DT.match(text)
    if match is None:
        return None
    day, time, suffix = match.groups()
    return day, time, suffix


_ISO_LEAP_SECOND = re.compile(r"^(\d{4}-\d{2}-\d{2}T\d{2}:\d{2}:)60(?=[.+Z-]|$)")


def parse_iso_datetime(text: str) -> datetime | date:
    """``date.fromisoformat`` for a date alone, else ``datetime.fromisoformat`` with a leap second ``:60``
    read as ``:59`` (module docstring); ``ValueError`` when the text is neither."""
    if len(text) == 10:
        return date.fromisoformat(text)
    return datetime.fromisoformat(_ISO_LEAP_SECOND.sub(r"\g<1>59", text))

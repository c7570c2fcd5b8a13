"""Vertebral levels T1..L5, the 17 names used everywhere in the contract."""

from typing import Literal

LEVELS: tuple[str, ...] = (
    "T1", "T2", "T3", "T4", "T5", "T6", "T7", "T8", "T9", "T10", "T11", "T12",
    "L1", "L2", "L3", "L4", "L5",
)
N_LEVELS = len(LEVELS)
LEVEL_INDEX: dict[str, int] = {name: i for i, name in enumerate(LEVELS)}

Level = Literal[
    "T1", "T2", "T3", "T4", "T5", "T6", "T7", "T8", "T9", "T10", "T11", "T12",
    "L1", "L2", "L3", "L4", "L5",
]


def apex_words(apex: str, apical_disc: bool = False) -> str:
    """A Cobb curve's apex as a report names it: the apical vertebra ("T8"), or, for a curve of one
    segment (``CobbCurve.apical_disc``), the apical disc by the two vertebrae it lies between
    ("L4/L5 disc"; SRS Revised Glossary of Terms, "apical disc")."""
    if not apical_disc:
        return apex
    return f"{apex}/{LEVELS[LEVEL_INDEX[apex] + 1]} disc"

"""SUMO's own option table, read from the installed ``sumo``: every option's canonical name,
synonyms, section and type, so that a ``.sumocfg`` is read as SUMO reads it.

``sumo --save-template`` writes every option of the installed SUMO with its synonyms
(``<statistic-output value="" synonymes="statistics-output" type="FILE"/>``); the table is
read once per process (about 0.1 s). A config may name an option by any synonym
(``<tripinfo>``, ``<log-file>``, ``<save-config>``): :func:`canonical` gives the name twin
checks and overrides.
"""

from __future__ import annotations

import functools
import xml.etree.ElementTree as ET
from dataclasses import dataclass

from twin.errors import UserError
from twin.sumo.tools import binary, run_sumo_program

#: Sections of the template whose file options SUMO writes (besides ``*-output`` elsewhere).
OUTPUT_SECTIONS = ("output", "report")


@dataclass(frozen=True)
class SumoOption:
    """One option of ``sumo``: its canonical name, section, type and synonyms."""

    name: str
    section: str
    type: str
    synonyms: tuple[str, ...]

    @property
    def writes_file(self) -> bool:
        """An option naming a file SUMO writes: a file option of the output and report
        sections (not an ``*.input-file`` filter SUMO reads), any ``...output`` file, or a
        device's output file (``device.ssm.file``, ``device.toc.file``: typed STR)."""
        if self.name.startswith("device.") and self.name.endswith(".file"):
            return True
        if self.type != "FILE":
            return False
        if self.name.endswith("input-file"):
            return False
        return self.section in OUTPUT_SECTIONS or self.name.endswith("output")


def parse_template(text: str) -> dict[str, SumoOption]:
    """The options of a ``sumo --save-template`` file, by canonical name."""
    root = ET.fromstring(text)
    table: dict[str, SumoOption] = {}
    for section in root:
        if not isinstance(section.tag, str):
            continue
        for option in section:
            if not isinstance(option.tag, str):
                continue
            synonyms = tuple((option.get("synonymes") or "").split())
            table[option.tag] = SumoOption(
                option.tag, section.tag, option.get("type", ""), synonyms
            )
    return table


@functools.cache
def sumo_options() -> dict[str, SumoOption]:
    """The installed ``sumo``'s options (``sumo --save-template -``), by canonical name."""
    text = run_sumo_program([binary("sumo"), "--save-template", "-"], "sumo --save-template", 60)
    try:
        return parse_template(text)
    except ET.ParseError as exc:
        raise UserError(
            f"sumo --save-template: SUMO's option table is not XML ({exc}); reinstall eclipse-sumo"
        ) from None


@functools.cache
def _names() -> dict[str, str]:
    names: dict[str, str] = {}
    for option in sumo_options().values():
        for synonym in option.synonyms:
            names.setdefault(synonym, option.name)
    names.update({name: name for name in sumo_options()})
    return names


def canonical(name: str) -> str:
    """The canonical name of the option ``name`` (a synonym or the name itself); a name SUMO
    does not know is returned as it is."""
    return _names().get(name, name)


@functools.cache
def output_options() -> frozenset[str]:
    """Canonical names of the options that name files SUMO writes."""
    return frozenset(o.name for o in sumo_options().values() if o.writes_file)

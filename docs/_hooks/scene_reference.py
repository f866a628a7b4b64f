"""MkDocs hook: the scene-file reference page (reference/scenes.md), generated at build time
from the scene parser's own reads (jointsim.scene.parameter_table) and the paper's scene file's
comments, so that it cannot drift from the code."""

from __future__ import annotations

import re

from mkdocs.structure.files import File

PAGE = "reference/scenes.md"


def _comments(text: str) -> dict[tuple[str, str], str]:
    """(section, key) → the comment on the key's line in a scene file (continuation lines of a
    multi-line value are skipped)."""
    out, section = {}, ""
    for line in text.splitlines():
        if m := re.match(r"^\s*\[\[?([\w.]+)\]\]?", line):
            section = m.group(1)
        elif m := re.match(r"^\s*#?\s*(\w+)\s*=\s*[^#]*#\s*(.+)$", line):
            out.setdefault((section, m.group(1)), m.group(2).strip())
    return out


def _cell(v) -> str:
    return "" if v is None else str(v).replace("|", "\\|")


def page() -> str:
    from jointsim.scene import SCENES_DIR, parameter_table

    notes = _comments((SCENES_DIR / "paper_sensor.toml").read_text())
    rows = parameter_table()
    L = ["# Scene files", "",
         "A scene is a TOML file, one table per part of the sensor and per job, with the unit in every key's name. "
         "`extends = \"paper_sensor\"` starts from a shipped scene and changes what it names. A value outside what "
         "is allowed is refused on load, naming the key and the range, before any work.", "",
         "This page is generated from the parser itself (`jointsim.scene.parameter_table`: every key the shipped "
         "scenes' parse reads, its default when absent and what is allowed) and the comments of "
         "`jointsim/scenes/paper_sensor.toml` (the paper's sensor, every value the paper does not give marked "
         "ASSUMED). *value*: a list, a table or a flag, checked by the key's own rules (its error says them).", ""]
    section = None
    for r in rows:
        if r["section"] != section:
            section = r["section"]
            head = f"[[{section}]]" if "." in section else f"[{section}]"
            L += ["", f"## `{head}`", "", "| key | kind | allowed | default | paper's sensor |", "|---|---|---|---|---|"]
        L.append(f"| `{r['key']}` | {r['kind']} | {_cell(r['allowed'])} | {_cell(r['default'])} | "
                 f"{_cell(notes.get((section, r['key']), ''))} |")
    return "\n".join(L) + "\n"


def on_files(files, config):
    files.append(File.generated(config, PAGE, content=page()))
    return files

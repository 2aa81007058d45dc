"""The files a MuJoCo model (MJCF) is made of: the XML file, the XML files it includes, and the assets they name
(meshes, textures, height fields, skins, attached models), found the way MuJoCo finds them.

- ``<include file=...>`` is relative to the main model file's directory (MuJoCo's rule; the including file's own
  directory is tried as well, for nested includes written that way);
- asset files are relative to ``<compiler meshdir=...>`` (meshes, height fields, skins) or ``texturedir`` (textures),
  each falling back to ``assetdir``, all three relative to the main model file's directory; absolute paths stay.
"""

from __future__ import annotations

import hashlib
import os
import xml.etree.ElementTree as ElementTree
from pathlib import Path

ASSET_FILES = {
    "mesh": ("file",),
    "hfield": ("file",),
    "skin": ("file",),
    "texture": ("file", "fileright", "fileleft", "fileup", "filedown", "filefront", "fileback"),
    "model": ("file",),
}
"""Elements that name asset files, and the attributes that do."""
ASSET_DIR = {"mesh": "meshdir", "hfield": "meshdir", "skin": "meshdir", "texture": "texturedir"}
"""The ``<compiler>`` attribute each kind of asset is looked up in (before ``assetdir``)."""
MISSING = "missing"
"""The digest recorded for a file the model names that is not there."""


def model_files(xml: str | Path) -> list[Path]:
    """The main XML file first, then every included XML file and asset file, each once, in the order they appear."""
    main = Path(xml)
    root_dir = main.parent
    found: list[Path] = [main]
    assets: list[tuple[str, str]] = []
    compiler: dict[str, str] = {}
    queue = [main]
    while queue:
        current = queue.pop(0)
        try:
            tree = ElementTree.parse(current)
        except (ElementTree.ParseError, OSError):
            continue  # MuJoCo compiled it, or reports why not: the file itself is still hashed
        for element in tree.iter():
            if element.tag == "include" and element.get("file"):
                included = _first_existing(element.get("file"), [root_dir, current.parent])
                if included not in found:
                    found.append(included)
                    queue.append(included)
            elif element.tag == "compiler":
                dirs = ("meshdir", "texturedir", "assetdir")
                compiler.update({key: element.get(key) for key in dirs if element.get(key)})
            elif element.tag in ASSET_FILES:
                assets += [(element.tag, element.get(name)) for name in ASSET_FILES[element.tag] if element.get(name)]
    for kind, name in assets:
        folder = compiler.get(ASSET_DIR.get(kind, ""), compiler.get("assetdir", ""))
        path = _first_existing(name, [root_dir / folder])
        if path not in found:
            found.append(path)
    return found


def file_digests(xml: str | Path) -> dict[str, str]:
    """``{name: SHA-256}`` of ``model_files(xml)``, each named relative to the main file's directory (the same on
    every machine), ``missing`` for a file that is not there."""
    main_dir = Path(xml).parent
    digests = {}
    for path in model_files(xml):
        digests[os.path.relpath(path, main_dir)] = (
            hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else MISSING
        )
    return digests


def _first_existing(name: str, folders: list[Path]) -> Path:
    """``name`` in the first of ``folders`` that has it (the first folder if none has)."""
    if Path(name).is_absolute():
        return Path(name)
    candidates = [Path(os.path.normpath(folder / name)) for folder in folders]
    return next((path for path in candidates if path.exists()), candidates[0])

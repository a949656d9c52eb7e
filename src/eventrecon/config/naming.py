"""What a run's data is called: the name in its log, output folder, records and tables.

A simulated scene is called by its config's ``name``. A dataset folder
(``data.root=DIR``) is called by the name its ``meta.json`` records (``scene_name``, or
the simulator's ``scene.name``), else by the folder's own name — never by the default
scene's, which it is not.

>>> import tempfile, pathlib
>>> d = pathlib.Path(tempfile.mkdtemp()) / "sword"
>>> d.mkdir()
>>> dataset_name(str(d), "spheres"), dataset_name(None, "spheres")
('sword', 'spheres')
>>> _ = (d / "meta.json").write_text('{"scene_name": "sword_take2"}')
>>> dataset_name(str(d), "spheres")
'sword_take2'
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

__all__ = ["dataset_name", "name_from_meta"]


def name_from_meta(meta: Mapping[str, Any]) -> str | None:
    """The dataset's own name in its ``meta.json`` contents, if it records one."""
    scene = meta.get("scene")
    name = meta.get("scene_name") or (scene.get("name") if isinstance(scene, Mapping) else None)
    return str(name) if name else None


def dataset_name(root: str | None, scene_name: str | None) -> str:
    """The run's data name: ``root``'s (module docstring), or ``scene_name`` without one."""
    if not root:
        return str(scene_name or "scene")
    path = Path(root)
    try:
        meta = json.loads((path / "meta.json").read_text())
    except (OSError, ValueError):
        meta = {}
    return (name_from_meta(meta) if isinstance(meta, dict) else None) or path.resolve().name
